"""A sun for the `pbr` fit: a directional light split off the environment and shadowed.

The split-sum path shades the whole environment without visibility, and its diffuse term sees
the light through an order-2 SH projection. Under a sky with a sun both fail where the sun
dominates: the SH of a near-delta light rings (about 9 % of the sun's irradiance on the
terminator, where the true irradiance is 0, and 6 % on the side facing away), and a body's
cast shadows are not there at all. Moving the sun out of the map into a directional light
shades it exactly (recon.render.pbr.pbr_shade's directional term: max(0, n.l) and the full
GGX lobe) and lets a shadow map give it visibility.

- split_sun: the brightest spot of a lat-long map -> a directional light (the radiance-weighted
  mean direction of the spot's excess over its surroundings, the excess's irradiance) and the
  map with that excess removed.
- reclaim_sun: the share of a sun that a Lambertian fit's order-2 SH light absorbed (the SH of
  a sun is a smooth lobe that mimics its irradiance but for the clamp): the map's linear band
  along the sun, moved into the sun, the sun's order-2 SH taken out of the map.
- ShadowMap: shadow-map visibility of the light at surface points, drawn with recon's own
  rasterizer orthographically along the light (recon.effects.light_transport.OrthographicFrames,
  filtered_visibility: a slope-scaled bias and a 2 x 2 percentage-closer filter). The map is
  drawn without gradient (a shadow edge moves in steps of a texel); gradients reach the points
  through their depth along the light, and the shading gradients (irradiance, direction, the
  material, the normals) flow through the visibility-weighted term as without shadows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from recon.effects.light_transport import OrthographicFrames, filtered_visibility
from recon.errors import ReconError
from recon.render.environment import latlong_directions, project_to_sh
from recon.render.shading import sh_basis

# Y_1m = BAND_ONE (y, z, x): a delta light of irradiance I along d has band-one coefficients
# I BAND_ONE (d_y, d_z, d_x).
BAND_ONE = 0.4886025119029199


@dataclass
class ShadowSettings:
    """Shadow-map settings (config fit.pbr.shadow_*): map side in texels, bias in texels
    (constant + times tan of the light's angle to the normal), softness of the depth test in
    texels."""

    resolution: int = 512
    bias_texels: float = 2.0
    slope_bias_texels: float = 2.0
    softness_texels: float = 0.5


def split_sun(
    environment: torch.Tensor, cone_degrees: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split the brightest spot off a lat-long radiance map.

    environment: [h, w, C] radiance. cone_degrees: half-angle of the spot around the brightest
    texel. The spot's background is the per-channel median of the ring between one and two
    cone angles; the excess over it inside the cone becomes the sun.
    Returns (environment [h, w, C] with the excess removed, direction_to_light [3] unit,
    irradiance [C] = the excess integrated over solid angle). No gradient.
    """
    if environment.ndim != 3:
        raise ReconError(
            f"split_sun: environment: expected [h, w, C], got {tuple(environment.shape)}"
        )
    if not 0 < cone_degrees < 90:
        raise ReconError(f"split_sun: cone_degrees: expected in (0, 90), got {cone_degrees}")
    with torch.no_grad():
        height, width, channels = environment.shape
        directions, solid_angle = latlong_directions(
            height, width, environment.device, environment.dtype
        )
        directions, solid_angle = directions.reshape(-1, 3), solid_angle.reshape(-1)
        flat = environment.reshape(-1, channels)
        peak = directions[flat.mean(-1).argmax()]
        cosine = directions @ peak
        cone = cosine >= math.cos(math.radians(cone_degrees))
        ring = ~cone & (cosine >= math.cos(math.radians(min(2 * cone_degrees, 89.0))))
        background = flat[ring].median(dim=0).values if bool(ring.any()) else flat.amin(0)
        excess = (flat - background).clamp_min(0) * cone[:, None]
        weight = excess.mean(-1) * solid_angle
        direction = torch.nn.functional.normalize((weight[:, None] * directions).sum(0), dim=0)
        irradiance = (excess * solid_angle[:, None]).sum(0)
        remaining = (flat - excess).reshape(height, width, channels)
    return remaining, direction, irradiance


def reclaim_sun(
    environment: torch.Tensor, direction_to_light: torch.Tensor, share: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move the irradiance a sun along direction_to_light [3] would explain of the map's linear
    SH band into the sun.

    environment: [h, w, C] radiance. The irradiance I [C] = share x the band-one coefficients
    along the direction / BAND_ONE (0 where negative); the map loses the order-2 SH radiance of
    that delta light, I sum_k Y_k(d) Y_k(w), clamped at 0 (a sun's SH rings: negative
    radiance on its horizon). Returns (environment [h, w, C], irradiance [C]). No gradient.
    """
    with torch.no_grad():
        height, width, _ = environment.shape
        direction = torch.nn.functional.normalize(direction_to_light.to(environment), dim=0)
        band_one = project_to_sh(environment)[1:4]  # [3, C] in (y, z, x) order
        along = direction[[1, 2, 0]] @ band_one / BAND_ONE
        irradiance = share * along.clamp_min(0)
        directions, _ = latlong_directions(height, width, environment.device, environment.dtype)
        kernel = sh_basis(directions.reshape(-1, 3)) @ sh_basis(direction[None])[0]  # [h w]
        removed = kernel.reshape(height, width, 1) * irradiance
    return (environment - removed).clamp_min(0), irradiance


@dataclass
class ShadowMap:
    """A directional light's shadow map: the orthographic frame along it and the nearest
    surface's NDC depth [1, R, R] (no gradient)."""

    frames: OrthographicFrames
    depth: torch.Tensor

    @staticmethod
    def draw(
        verts: torch.Tensor,
        faces: torch.Tensor,
        direction_to_light: torch.Tensor,
        settings: ShadowSettings,
    ) -> ShadowMap:
        """The map of the mesh verts [V, 3], faces [F, 3] along direction_to_light [3]."""
        direction = torch.nn.functional.normalize(direction_to_light.detach().to(verts), dim=0)
        frames = OrthographicFrames.build(verts, direction[None])
        return ShadowMap(frames, frames.depth_maps(verts, faces, settings.resolution))

    def visibility(
        self, points: torch.Tensor, normals: torch.Tensor, settings: ShadowSettings
    ) -> torch.Tensor:
        """Visibility [N, 1] in [0, 1] of the light from points [N, 3] (differentiable: their
        depth along the light) with unit normals [N, 3] (for the slope-scaled bias)."""
        direction = -self.frames.axes[0, 2].to(points)
        cosine = (normals.detach() * direction).sum(-1).clamp(0.05, 1.0)
        slope = torch.sqrt(1 - cosine * cosine) / cosine
        texel = 2.0 / settings.resolution  # NDC units
        bias = texel * (settings.bias_texels + settings.slope_bias_texels * slope.clamp(max=10.0))
        softness = torch.tensor(
            settings.softness_texels * texel, dtype=points.dtype, device=points.device
        )
        visible = filtered_visibility(self.depth, self.frames.to_ndc(points), bias[None], softness)
        return visible[0][:, None]
