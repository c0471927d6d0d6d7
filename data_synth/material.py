"""The world's glossy material: the 'specular' effect's metallic-roughness parameters, with an
optional spatially varying roughness (scene.material.roughness_texture), and recon's own
rendering of it (backend 'own': the split-sum shading of recon.render.pbr).

Both backends render the same material: Mitsuba's principled BSDF takes the roughness map as a
bitmap texture (MitsubaOptions.roughness_map), recon's Renderer.shade_pbr samples it from the
material texture [h, w, 5] beside the albedo. The ground truth's reference mesh carries the
maps (roughness, metalness as map_Pr / map_Pm), so a fit's roughness texture can be compared
with the true one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from tqdm import tqdm

from data_synth.environment import project_to_sh
from data_synth.textures import make_texture
from recon.camera import Cameras
from recon.config.run_config import EffectConfig, MaterialConfig, OwnSpecularConfig
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.antialias import build_topology
from recon.render.environment import latlong_directions, prefilter_environment
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import sh_basis
from recon.render.texture import build_mip_pyramid


@dataclass
class WorldMaterial:
    """The specular material the world renders.

    roughness: [h, w] perceptual roughness on the mesh's UVs (uniform without a texture);
    textured: whether it varies (scene.material.roughness_texture) or is the effect's scalar;
    metalness, specular_level: principled's metallic and specular level; plastic: Mitsuba's
    roughplastic instead of principled (a single roughness, Mitsuba only).
    """

    roughness: torch.Tensor
    textured: bool
    metalness: float
    specular_level: float
    plastic: bool = False

    def maps(self) -> torch.Tensor:
        """[h, w, 2] roughness, metalness: recon's material maps (save_mesh material_maps)."""
        return torch.stack([self.roughness, torch.full_like(self.roughness, self.metalness)], -1)


def roughness_pattern(material: MaterialConfig, size: tuple[int, int]) -> torch.Tensor | None:
    """The roughness map [h, w] of material.roughness_texture (None for 'none'): the pattern's
    first channel, seeded with material.seed + 1 (independent of the albedo's pattern), scaled so
    that its lowest and highest values are material.roughness_range."""
    if material.roughness_texture == "none":
        return None
    pattern = make_texture(material.roughness_texture, size=size, seed=material.seed + 1)[..., 0]
    low, high = (float(value) for value in material.roughness_range)
    spread = float(pattern.max() - pattern.min())
    unit = (pattern - pattern.min()) / spread if spread > 0 else torch.zeros_like(pattern)
    return low + (high - low) * unit


def world_material(
    effects: list[EffectConfig], material: MaterialConfig, mesh: Mesh
) -> WorldMaterial | None:
    """The material of the 'specular' effect among effects (None without one): its parameters
    where it sets them, else the scene's material's, and the roughness texture when the scene
    has one (on the mesh texture's grid)."""
    from data_synth.effects.light_transport import mitsuba_options_for

    specular = [effect for effect in effects if effect.name == "specular"]
    if not specular:
        return None
    options = mitsuba_options_for(specular, material=material)
    size = (
        tuple(mesh.texture.shape[:2])
        if mesh.texture is not None
        else (material.texture_size, material.texture_size)
    )
    pattern = roughness_pattern(material, size)
    if pattern is None:
        roughness = torch.full(size, float(options.roughness))
    else:
        if "roughness" in (specular[0].parameters or {}):
            raise ReconError(
                "capture.effects: specular: roughness "
                f"{specular[0].parameters['roughness']} and scene.material.roughness_texture "
                f"{material.roughness_texture!r} both set the roughness; give one"
            )
        if options.material == "roughplastic":
            raise ReconError(
                "scene.material.roughness_texture: needs the principled BSDF (specular with "
                "plastic false); Mitsuba's roughplastic takes a single roughness"
            )
        if mesh.texture is None or mesh.uvs is None:
            raise ReconError(
                f"scene.material.roughness_texture {material.roughness_texture!r}: the mesh "
                "has no UVs and texture to carry it"
            )
        roughness = pattern
    return WorldMaterial(
        roughness.float(),
        pattern is not None,
        float(options.metalness),
        float(options.specular_level),
        plastic=options.material == "roughplastic",
    )


def world_environment(world: Any, size: tuple[int, int]) -> torch.Tensor:
    """One lat-long radiance map [h, w, 3] (recon.render.environment's convention) of the
    world's environment: its map (area-resampled) plus whatever of the SH light is not the map's
    projection (ambient, sky gradient), clamped at 0. world: data_synth.scene.WorldLighting."""
    height, width = size
    directions, _ = latlong_directions(height, width)
    basis = sh_basis(directions.reshape(-1, 3))
    sh = world.lighting.sh_coefficients.detach().float().cpu()
    environment = world.environment_map
    if environment is not None:
        environment = environment.detach().float().cpu()
        # recon shades the map through its SH projection, which build_lighting included.
        sh = sh - project_to_sh(environment)
        resampled = F.interpolate(
            environment.permute(2, 0, 1)[None], size=(height, width), mode="area"
        )[0].permute(1, 2, 0)
    else:
        resampled = torch.zeros(height, width, 3)
    return (resampled + (basis @ sh).reshape(height, width, 3)).clamp_min(0)


def render_views_pbr(
    mesh: Mesh,
    material: WorldMaterial,
    cameras: Cameras,
    world: Any,
    settings: OwnSpecularConfig,
    views_per_batch: int,
    description: str,
) -> list[RenderOutput]:
    """recon's split-sum rendering of the glossy world (backend 'own'), in batches: the mesh's
    albedo texture and material's maps under the world's environment (world_environment) and
    directional lights. Point and area lights have no split-sum counterpart and are refused, as
    is Mitsuba's roughplastic. Returns one RenderOutput per batch (on the cameras' device)."""
    lighting = world.lighting
    if lighting.points or getattr(world, "area_lights", None):
        raise ReconError(
            "capture.backend 'own': the 'specular' effect is shaded under the environment and "
            "directional lights only; scene.lighting.points / areas need backend 'mitsuba'"
        )
    if material.plastic:
        raise ReconError(
            "capture.backend 'own': specular with plastic true is Mitsuba's roughplastic; "
            "recon's own shading is the principled model (plastic false), or use 'mitsuba'"
        )
    if mesh.texture is None or mesh.uvs is None:
        raise ReconError(
            "capture.backend 'own': the 'specular' effect needs a textured mesh (uvs and an "
            "albedo texture) to carry its material maps; use a textured albedo or 'mitsuba'"
        )
    device = cameras.device
    texture = torch.cat([mesh.texture, material.maps()], dim=-1).to(device)
    pyramid = build_mip_pyramid(texture)
    environment = prefilter_environment(
        world_environment(world, tuple(settings.environment_size)).to(device),
        settings.prefilter_levels,
    )
    directional = lighting.to(device).directional
    renderer = Renderer()
    mesh = mesh.to(device)
    topology = build_topology(mesh.faces, mesh.verts.shape[0])
    outputs = []
    with torch.no_grad():
        for start in tqdm(
            range(0, len(cameras), views_per_batch), desc=description, unit="batch", leave=False
        ):
            batch = cameras[start : start + views_per_batch]
            buffers = renderer.surface_buffers(mesh, batch, topology=topology)
            outputs.append(
                renderer.shade_pbr(
                    buffers,
                    batch.centers(),
                    texture,
                    environment,
                    directional,
                    specular_level=material.specular_level,
                    mip_pyramid=pyramid,
                )
            )
    return outputs
