"""Physically based shading: a metallic-roughness material under an environment light
(split-sum, Karis 2013) plus optional directional lights (evaluated exactly).

Outgoing radiance at a point with base colour b, roughness r, metalness m, normal n and
direction to the viewer v, reflection direction R = 2 (n.v) n - v:

    specular = prefiltered(R, r) (F0 A(n.v, r) + B(n.v, r)),      F0 = mix(0.08 s, b, m)
    diffuse  = b (1 - m) / pi E(n)                     (diffuse_weighting 'none', the default)
    diffuse  = b (1 - m) / pi E(n) (1 - (F0 A + B))    (diffuse_weighting 'specular_albedo')

'none' is Karis' and Mitsuba's principled BSDF's choice (data_synth renders glossy scenes with
the latter; tests/data_synth/test_mitsuba_backend_pbr.py measures the agreement); it can
reflect a few percent more than it receives at grazing angles. 'specular_albedo' gives the
diffuse lobe only what the specular lobe does not reflect, so a white material under a white
furnace never exceeds 1. With roughness 1, metalness 0 and specular level 0 either is close to lambertian()
under the same light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from recon.errors import ReconError
from recon.render.brdf import MINIMUM_COSINE, lookup_split_sum, specular_brdf, specular_f0
from recon.render.environment import PrefilteredEnvironment
from recon.render.lobe_sampling import SampledEnvironment
from recon.render.shading import DirectionalLight


@dataclass
class PbrMaterial:
    """Per-point material [N, ...]: base_color [N, C], roughness [N, 1], metalness [N, 1] (all
    in [0, 1]); specular_level scales the dielectric F0 (0.5 gives 0.04); diffuse_weighting
    'none' or 'specular_albedo' (see the module docstring)."""

    base_color: torch.Tensor
    roughness: torch.Tensor
    metalness: torch.Tensor
    specular_level: float = 0.5
    diffuse_weighting: str = "none"

    @staticmethod
    def from_channels(
        channels: torch.Tensor,
        specular_level: float = 0.5,
        diffuse_weighting: str = "none",
    ) -> PbrMaterial:
        """From packed channels [N, 5]: base colour (3), roughness, metalness."""
        if channels.shape[-1] != 5:
            raise ReconError(
                f"material channels: expected [N, 5] (base colour, roughness, metalness), got "
                f"{tuple(channels.shape)}"
            )
        return PbrMaterial(
            channels[..., :3],
            channels[..., 3:4],
            channels[..., 4:5],
            specular_level,
            diffuse_weighting,
        )


def pbr_shade(
    material: PbrMaterial,
    normals: torch.Tensor,
    to_viewer: torch.Tensor,
    environment: PrefilteredEnvironment | SampledEnvironment | None,
    directional: list[DirectionalLight] | None = None,
    directional_visibility: list[torch.Tensor | None] | None = None,
) -> torch.Tensor:
    """Outgoing linear radiance [N, C].

    normals, to_viewer: [N, 3] unit vectors (to_viewer points from the surface to the camera).
    environment: the pre-filtered environment (None: directional lights only), or a
        SampledEnvironment to integrate the specular lobe per pixel instead of the split sum.
    directional: distant lights, each adding (f_d + f_s) E cos with the exact BRDF.
    directional_visibility: per directional light, its visibility [N, 1] in [0, 1] (a shadow
        map, recon.optimize.sun_light) or None (unshadowed); None: all unshadowed.
    """
    base, roughness, metalness = material.base_color, material.roughness, material.metalness
    f0 = specular_f0(base, metalness, material.specular_level)
    # Grazing and back-facing views (silhouettes of smoothed normals) are clamped, not culled.
    n_dot_v = (normals * to_viewer).sum(-1, keepdim=True).clamp(MINIMUM_COSINE, 1)
    scale_bias = lookup_split_sum(n_dot_v, roughness)
    specular_albedo = f0 * scale_bias[..., 0:1] + scale_bias[..., 1:2]
    diffuse_albedo = base * (1 - metalness)
    if material.diffuse_weighting == "specular_albedo":
        diffuse_albedo = diffuse_albedo * (1 - specular_albedo)
    elif material.diffuse_weighting != "none":
        raise ReconError(
            "PbrMaterial.diffuse_weighting: expected 'specular_albedo' or 'none', got "
            f"{material.diffuse_weighting!r}"
        )
    radiance = torch.zeros_like(base)
    if environment is not None:
        reflected = F.normalize(2 * n_dot_v * normals - to_viewer, dim=-1, eps=1e-12)
        if isinstance(environment, SampledEnvironment):
            # The full lobe per pixel (recon.render.lobe_sampling) instead of the split sum.
            specular = environment.specular_lobe(normals, to_viewer, roughness, f0)
        else:
            specular = specular_albedo * environment.specular(reflected, roughness)
        radiance = diffuse_albedo / math.pi * environment.irradiance(normals) + specular
    directional = directional or []
    visibilities = directional_visibility or [None] * len(directional)
    if len(visibilities) != len(directional):
        raise ReconError(
            f"pbr_shade: {len(visibilities)} directional visibilities for "
            f"{len(directional)} directional lights"
        )
    for light, visibility in zip(directional, visibilities, strict=True):
        to_light = F.normalize(light.direction_to_light, dim=-1).expand_as(normals)
        cosine = (normals * to_light).sum(-1, keepdim=True).clamp_min(0)
        specular = specular_brdf(normals, to_light, to_viewer, roughness, f0)
        if visibility is not None:
            cosine = cosine * visibility
        radiance = radiance + (diffuse_albedo / math.pi + specular) * cosine * light.irradiance
    return radiance


def perturb_normals(
    normals: torch.Tensor,
    tangents: torch.Tensor,
    bitangents: torch.Tensor,
    tangent_normals: torch.Tensor,
) -> torch.Tensor:
    """Shading normals [N, 3] from a tangent-space normal map.

    normals: [N, 3] unit interpolated normals; tangents, bitangents: [N, 3] interpolated UV
    tangent frames (recon.mesh.mesh.uv_tangents), orthonormalised here against the normal
    (Gram-Schmidt; the bitangent keeps only its handedness); tangent_normals: [N, 3] the map's
    (x, y, z), z along the normal ((0, 0, 1) leaves the normal unchanged).
    """
    tangent = F.normalize(
        tangents - (tangents * normals).sum(-1, keepdim=True) * normals, dim=-1, eps=1e-12
    )
    side = torch.linalg.cross(normals, tangent, dim=-1)
    handedness = torch.where((side * bitangents).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    x, y, z = tangent_normals.unbind(-1)
    perturbed = x[..., None] * tangent + y[..., None] * handedness * side + z[..., None] * normals
    return F.normalize(perturbed, dim=-1, eps=1e-12)
