"""Build the reference scene (mesh with albedo, lighting) from a config's scene section."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from data_synth.environment import (
    load_environment,
    procedural_sky,
    procedural_studio,
    project_to_sh,
    sun_light,
)
from data_synth.shapes import make_shape
from data_synth.textures import TEXTURES, make_texture, vertex_color_field
from recon.config.run_config import AreaLightConfig, LightingConfig, SceneConfig
from recon.errors import ReconError
from recon.io.meshes import load_mesh
from recon.mesh.mesh import Mesh
from recon.render.shading import SH_COEFFICIENT_COUNT, DirectionalLight, Lighting, PointLight

# SH band-1 y coefficient of radiance L(w) = a * g * w_y: <y, Y_1,-1> over the sphere.
_GRADIENT_TO_SH = 0.4886025119029199 * 4 * math.pi / 3


def build_mesh(config: SceneConfig) -> Mesh:
    """The reference mesh with its albedo (texture when it has UVs, else vertex colours)."""
    shape = config.shape
    material = config.material
    if shape.mesh_path is not None:
        mesh = load_mesh(shape.mesh_path, texture_path=shape.texture_path)
        # Normalise into the unit sphere so camera rigs and metrics have one scale.
        center = (mesh.verts.amax(0) + mesh.verts.amin(0)) / 2
        radius = (mesh.verts - center).norm(dim=-1).max()
        mesh.verts = (mesh.verts - center) / radius * 0.9
    else:
        mesh = make_shape(shape.procedural, resolution=shape.resolution)
    if material.albedo == "file":
        if mesh.texture is None:
            raise ReconError(
                "scene.material.albedo: 'file' needs a mesh with a texture, but "
                f"{shape.mesh_path or shape.procedural} has none"
            )
        return mesh
    if material.albedo == "vertex_noise":
        mesh.vertex_colors = vertex_color_field(mesh.verts, "noise", seed=material.seed)
        mesh.texture = None
        return mesh
    if material.albedo not in TEXTURES:
        raise ReconError(f"scene.material.albedo: unknown texture {material.albedo!r}")
    if mesh.uvs is not None:
        mesh.texture = make_texture(material.albedo, size=material.texture_size, seed=material.seed)
    else:
        # No UVs on this shape: the same pattern as a 3D field at the vertices.
        mesh.vertex_colors = vertex_color_field(mesh.verts, material.albedo, seed=material.seed)
        mesh.texture = None
    return mesh


@dataclass
class AreaLight:
    """A one-sided rectangle emitter: center [3], unit normal [3] (facing the scene), u/v edge
    vectors [3] (full side lengths), radiance [3]."""

    center: torch.Tensor
    normal: torch.Tensor
    edge_u: torch.Tensor
    edge_v: torch.Tensor
    radiance: torch.Tensor

    @property
    def area(self) -> float:
        return float(torch.linalg.cross(self.edge_u, self.edge_v).norm())


@dataclass
class WorldLighting:
    """The world's light. `lighting` is what recon's renderer shades with (SH + directional +
    point lights; area lights approximated at their centres); the path tracer also gets the full
    environment map and the true area lights."""

    lighting: Lighting
    environment_map: torch.Tensor | None = None  # [h, w, 3], data_synth.environment convention
    area_lights: list[AreaLight] = field(default_factory=list)


def _area_light(config: AreaLightConfig) -> AreaLight:
    center = torch.tensor(config.center, dtype=torch.float32)
    normal = torch.nn.functional.normalize(-center, dim=0)  # faces the origin
    helper = (
        torch.tensor([0.0, 1.0, 0.0])
        if abs(float(normal[1])) < 0.9
        else torch.tensor([1.0, 0.0, 0.0])
    )
    axis_u = torch.nn.functional.normalize(torch.linalg.cross(helper, normal), dim=0)
    axis_v = torch.linalg.cross(normal, axis_u)
    return AreaLight(
        center=center,
        normal=normal,
        edge_u=axis_u * config.size[0],
        edge_v=axis_v * config.size[1],
        radiance=torch.tensor(config.radiance, dtype=torch.float32),
    )


def build_lighting(config: LightingConfig) -> WorldLighting:
    """SH environment (ambient, brighter toward +y by sky_gradient, plus the projected map),
    suns, point lights, area lights."""
    ambient = torch.tensor(config.ambient, dtype=torch.float32)
    sh = torch.zeros(SH_COEFFICIENT_COUNT, 3)
    sh[0] = ambient * math.sqrt(4 * math.pi)
    sh[1] = ambient * config.sky_gradient * _GRADIENT_TO_SH
    suns = [
        DirectionalLight(
            torch.nn.functional.normalize(torch.tensor(sun.direction, dtype=torch.float32), dim=0),
            torch.tensor(sun.irradiance, dtype=torch.float32),
        )
        for sun in config.suns
    ]
    environment = config.environment
    environment_map = None
    height, width = environment.resolution
    if environment.kind == "sky":
        environment_map = procedural_sky(height, width, strength=environment.strength)
        suns.append(
            sun_light(
                environment.sun_elevation_deg,
                environment.sun_azimuth_deg,
                environment.sun_irradiance * environment.strength,
            )
        )
    elif environment.kind == "studio":
        environment_map = procedural_studio(height, width, strength=environment.strength)
    elif environment.kind == "exr":
        environment_map = load_environment(environment.path, strength=environment.strength)
    if environment_map is not None:
        sh = sh + project_to_sh(environment_map)
    areas = [_area_light(area) for area in config.areas]
    points = [
        PointLight(
            torch.tensor(point.position, dtype=torch.float32),
            torch.tensor(point.intensity, dtype=torch.float32),
        )
        for point in config.points
    ]
    # Far from a small area light, it acts like a point with intensity L * A * cos(emission).
    points += [
        PointLight(area.center, area.radiance * area.area, emitter_normal=area.normal)
        for area in areas
    ]
    lighting = Lighting(sh_coefficients=sh, directional=suns, points=points)
    return WorldLighting(lighting, environment_map=environment_map, area_lights=areas)


def lighting_to_json(world: WorldLighting) -> dict:
    lighting = world.lighting
    return {
        "sh_coefficients": lighting.sh_coefficients.cpu().tolist(),
        "sh_convention": "real SH bands 0-2 of incident radiance, rows Y00,Y1-1,Y10,Y11,Y2-2,"
        "Y2-1,Y20,Y21,Y22; columns RGB",
        "directional": [
            {
                "direction_to_light": light.direction_to_light.cpu().tolist(),
                "irradiance": light.irradiance.cpu().tolist(),
            }
            for light in lighting.directional
        ],
        "points": [
            {
                "position": light.position.cpu().tolist(),
                "intensity": light.intensity.cpu().tolist(),
                "emitter_normal": None
                if light.emitter_normal is None
                else light.emitter_normal.cpu().tolist(),
            }
            for light in lighting.points
        ],
        "area_lights": [
            {
                "center": area.center.tolist(),
                "normal": area.normal.tolist(),
                "edge_u": area.edge_u.tolist(),
                "edge_v": area.edge_v.tolist(),
                "radiance": area.radiance.tolist(),
            }
            for area in world.area_lights
        ],
        "environment_map": None if world.environment_map is None else "environment.exr",
    }
