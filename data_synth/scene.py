"""Build the reference scene (mesh with albedo, lighting) from a config's scene section."""

from __future__ import annotations

import math

import torch

from data_synth.shapes import make_shape
from data_synth.textures import TEXTURES, make_texture, vertex_color_field
from recon.config.run_config import LightingConfig, SceneConfig
from recon.errors import ReconError
from recon.io.meshes import load_mesh
from recon.mesh.mesh import Mesh
from recon.render.shading import SH_COEFFICIENT_COUNT, DirectionalLight, Lighting

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


def build_lighting(config: LightingConfig) -> Lighting:
    """SH environment (ambient, brighter toward +y by sky_gradient) plus the suns."""
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
    return Lighting(sh_coefficients=sh, directional=suns)


def lighting_to_json(lighting: Lighting) -> dict:
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
    }
