"""Shading effects: specular, shadows, interreflection, from the render's buffers.

They change the shaded radiance of covered pixels using the render's world normals, albedo
and coverage, the fitted light and the mesh. Each adds a term (zero at zero parameters) to the
rendered colour, weighted by the antialiased alpha (the render's colour is premultiplied).

The light they use is the fitted light's dominant direction (dominant_light): the brightest
directional light when there is one, else the direction of the SH environment's linear band
with the irradiance of the directional light that band would come from. A light fixed to the
camera (Lighting.frame 'camera', turntable captures) has that direction in each view's camera
axes: view_light_directions turns it into the world per view, so the highlight and the shadow
move with the camera as the render's diffuse shading does.

- specular: a normalised Blinn-Phong lobe (e + 8) / (8 pi) (n.h)^e under the dominant light,
  white (dielectric), strength s (linear, 0 = off) and exponent e = 32 exp(log_exponent). The
  world uses a GGX lobe with Fresnel, lit by the whole environment.
- shadows: a shadow map. The mesh is rasterised orthographically along the dominant light
  (recon's rasterizer with w = 1 clip coordinates, the mesh's bounding sphere filling the map);
  each covered pixel's world point is compared with the map's depth at its position, with a
  slope-scaled bias, through a sigmoid of learnable softness and a 2 x 2 percentage-closer
  filter. The occluded share of the dominant light's Lambertian term is removed with strength s
  (linear, 0 = off, 1 = a full shadow). The world ray-traces soft shadows from a disk sun.
- interreflection: per-vertex occlusion from the mesh (the cosine-weighted share of the
  hemisphere that sees the mesh itself, from depth maps along 64 directions), interpolated to
  pixels. In a concavity that share of the incident light comes from the surface, which
  reflects about albedo x mean irradiance / pi, so one bounce adds
  s x occlusion x albedo^2 x E_mean / pi, with E_mean the sphere-averaged irradiance of the
  fitted light and s (linear, 0 = off, ~1 for one full bounce). The world path-traces many
  bounces.

Visibility (the shadow map, the occlusion) is computed without gradients and cached for an
unchanged mesh and light; gradients reach the strengths, the softness, the exponent, the
albedo, the normals and the light's irradiance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from recon.camera import Cameras
from recon.effects.base import ModelEffect, to_float
from recon.effects.facts import DiagnosisFacts
from recon.errors import ReconError
from recon.mesh.mesh import Mesh, vertex_normals
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import rasterize, scatter_to_image
from recon.render.renderer import RenderOutput
from recon.render.shading import Lighting, sh_basis

if TYPE_CHECKING:
    from recon.effects.forward import EffectContext

# Y_1m = _SH_BAND_ONE * (y, z, x): a delta light of irradiance I along d has band-one
# coefficients I * _SH_BAND_ONE * d.
_SH_BAND_ONE = 0.4886025119029199
_SH_BAND_ZERO = 0.28209479177387814
# Interreflection keeps its occlusion while no vertex moves more than this share of the mesh's
# bounding-box diagonal (about a tenth of a texel of its 96-texel depth maps).
OCCLUSION_TOLERANCE = 0.002
# Depth maps: background depth (NDC units) far behind everything, so it never occludes.
_EMPTY_DEPTH = 1.0e4


# --------------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------------


def dominant_light(lighting: Lighting) -> tuple[torch.Tensor, torch.Tensor]:
    """(direction_to_light [3] unit, irradiance [C]) of the fitted light's dominant direction.

    The brightest directional light (by mean irradiance) if any; else the SH linear band:
    its luminance-averaged direction d and, per channel, the irradiance (c_1 . d) / Y1 of the
    delta light with that band (zero when the band is zero, e.g. a uniform environment).
    """
    if lighting.directional:
        brightness = [float(light.irradiance.detach().mean()) for light in lighting.directional]
        light = lighting.directional[max(range(len(brightness)), key=brightness.__getitem__)]
        direction = torch.nn.functional.normalize(light.direction_to_light, dim=-1)
        return direction, light.irradiance
    sh = lighting.sh_coefficients
    # Band-one coefficients per axis (x, y, z) and channel: [3, C].
    linear = torch.stack([sh[3], sh[1], sh[2]], dim=0)
    mean_vector = linear.mean(dim=-1)
    length = mean_vector.norm()
    if float(length.detach()) < 1e-12:
        direction = torch.tensor([0.0, 1.0, 0.0], dtype=sh.dtype, device=sh.device)
        return direction, torch.zeros_like(sh[0])
    direction = mean_vector / length
    irradiance = (direction @ linear).clamp(min=0.0) / _SH_BAND_ONE
    return direction, irradiance


def view_light_directions(
    lighting: Lighting, cameras: Cameras, like: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(directions [B, 3] unit world directions toward the dominant light per view, irradiance
    [C]). A world-frame light has the same direction in every view; a camera-frame light's
    direction d (OpenCV camera axes) is R_b^T d in view b's world axes."""
    direction, irradiance = dominant_light(lighting)
    direction, irradiance = direction.to(like), irradiance.to(like)
    batch = len(cameras)
    if lighting.frame != "camera":
        return direction.expand(batch, 3), irradiance
    rotation = cameras.world_to_cam[:, :3, :3].to(like)
    # Row vector d @ R = (R^T d)^T.
    return direction @ rotation, irradiance


def mean_irradiance(lighting: Lighting) -> torch.Tensor:
    """Irradiance [C] averaged over all normal directions: the SH band-zero irradiance plus a
    quarter of each directional light's (the mean of max(0, cos) over the sphere)."""
    total = math.pi * _SH_BAND_ZERO * lighting.sh_coefficients[0]
    for light in lighting.directional:
        total = total + 0.25 * light.irradiance
    return total


def view_directions(cameras: Cameras, height: int, width: int, like: torch.Tensor) -> torch.Tensor:
    """Unit world directions [B, H, W, 3] from each pixel's surface point toward its camera."""
    intrinsics = cameras.intrinsics.to(device=like.device, dtype=like.dtype)
    fx, fy, cx, cy = (
        intrinsics[:, row, column][:, None, None]
        for row, column in ((0, 0), (1, 1), (0, 2), (1, 2))
    )
    columns = torch.arange(width, device=like.device, dtype=like.dtype) + 0.5
    rows = torch.arange(height, device=like.device, dtype=like.dtype) + 0.5
    x = ((columns[None, None, :] - cx) / fx).expand(-1, height, -1)
    y = ((rows[None, :, None] - cy) / fy).expand(-1, -1, width)
    rays_camera = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [B, H, W, 3]
    rotation = cameras.world_to_cam[:, :3, :3].to(like)
    # World ray = R^T ray_camera, i.e. the row vector ray_camera @ R.
    rays_world = torch.einsum("bhwi,bij->bhwj", rays_camera, rotation)
    return -torch.nn.functional.normalize(rays_world, dim=-1)


def _fingerprint(tensor: torch.Tensor) -> tuple:
    """A cheap content key for caching (shape, sum, pseudo-randomly weighted sum)."""
    values = tensor.detach().reshape(-1).double()
    weights = torch.sin(
        torch.arange(values.numel(), dtype=torch.float64, device=values.device) * 0.7548776662 + 0.3
    )
    return (tuple(tensor.shape), float(values.sum()), float((values * weights).sum()))


@dataclass
class OrthographicFrames:
    """Orthographic views of a mesh's bounding sphere along K directions.

    center [3], radius (world), axes [K, 3, 3] rows (right, down, forward), forward pointing
    away from the light (the viewing direction), so NDC depth grows away from the light.
    """

    center: torch.Tensor
    radius: float
    axes: torch.Tensor

    @staticmethod
    def build(verts: torch.Tensor, directions_to_light: torch.Tensor) -> OrthographicFrames:
        """Frames for mesh verts [V, 3] and unit directions toward the light [K, 3]."""
        verts = verts.detach()
        center = 0.5 * (verts.amin(dim=0) + verts.amax(dim=0))
        radius = float((verts - center).norm(dim=-1).max()) * 1.02 + 1e-6
        forward = -torch.nn.functional.normalize(directions_to_light.detach().to(verts), dim=-1)
        up = torch.tensor([0.0, 1.0, 0.0], dtype=verts.dtype, device=verts.device).expand_as(
            forward
        )
        other = torch.tensor([0.0, 0.0, 1.0], dtype=verts.dtype, device=verts.device)
        # Looking straight along the up axis: pick another up so the basis stays defined.
        parallel = (forward * up).sum(-1).abs() > 0.999
        up = torch.where(parallel[:, None], other.expand_as(forward), up)
        right = torch.nn.functional.normalize(torch.linalg.cross(forward, up, dim=-1), dim=-1)
        down = torch.linalg.cross(forward, right, dim=-1)
        return OrthographicFrames(center, radius, torch.stack([right, down, forward], dim=1))

    def to_ndc(self, points: torch.Tensor) -> torch.Tensor:
        """NDC (x, y, depth) [K, M, 3] of points [M, 3] or [K, M, 3] (differentiable)."""
        relative = (points - self.center.to(points)) / self.radius
        axes = self.axes.to(points)
        if relative.ndim == 2:
            return torch.einsum("mj,kij->kmi", relative, axes)
        return torch.einsum("kmj,kij->kmi", relative, axes)

    def depth_maps(self, verts: torch.Tensor, faces: torch.Tensor, resolution: int) -> torch.Tensor:
        """NDC depth of the nearest surface [K, R, R] (_EMPTY_DEPTH where none), no gradient."""
        with torch.no_grad():
            ndc = self.to_ndc(verts.detach().float())
            clip = torch.cat([ndc, torch.ones_like(ndc[..., :1])], dim=-1).contiguous()
            fragments = rasterize(clip, faces, (resolution, resolution))
            depth = fragments.depth
            return torch.where(torch.isfinite(depth), depth, torch.full_like(depth, _EMPTY_DEPTH))


def filtered_visibility(
    depth_maps: torch.Tensor, ndc: torch.Tensor, bias: torch.Tensor, softness: torch.Tensor
) -> torch.Tensor:
    """Soft visibility [K, M] of points at ndc [K, M, 3] in depth maps [K, R, R].

    Each of the 2 x 2 texels around a point votes sigmoid((map - depth + bias) / softness),
    the votes weighted bilinearly (percentage-closer filtering); texels outside the map are lit.
    bias [K, M] or scalar, softness scalar, both in NDC depth units.
    """
    count, resolution = depth_maps.shape[0], depth_maps.shape[-1]
    maps = depth_maps.to(ndc.dtype).reshape(count, -1)
    # Continuous texel coordinates: centres at integers (NDC -1 is the outer edge of texel 0).
    position = ((ndc[..., :2].detach() + 1) * 0.5 * resolution - 0.5).clamp(-2, resolution + 1)
    base = position.floor()
    fraction = position - base
    base = base.long()
    visibility = torch.zeros_like(ndc[..., 0])
    for step_x in (0, 1):
        for step_y in (0, 1):
            column = base[..., 0] + step_x
            row = base[..., 1] + step_y
            inside = (column >= 0) & (column < resolution) & (row >= 0) & (row < resolution)
            index = row.clamp(0, resolution - 1) * resolution + column.clamp(0, resolution - 1)
            occluder = torch.where(
                inside, maps.gather(1, index), torch.full_like(ndc[..., 0], _EMPTY_DEPTH)
            )
            vote = torch.sigmoid((occluder - ndc[..., 2] + bias) / softness)
            weight_x = fraction[..., 0] if step_x else 1 - fraction[..., 0]
            weight_y = fraction[..., 1] if step_y else 1 - fraction[..., 1]
            visibility = visibility + weight_x * weight_y * vote
    return visibility


def fibonacci_directions(count: int) -> torch.Tensor:
    """count roughly uniform unit directions on the sphere [count, 3] (float64)."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    height = 1 - 2 * index / count
    azimuth = index * math.pi * (3 - math.sqrt(5))
    ring = torch.sqrt((1 - height * height).clamp(min=0))
    return torch.stack([ring * torch.cos(azimuth), height, ring * torch.sin(azimuth)], dim=-1)


def _check_shading_inputs(render_output: RenderOutput, context: EffectContext, name: str) -> None:
    if context is None or context.mesh is None or context.lighting is None:
        raise ReconError(f"effect {name}: needs an EffectContext with the mesh and the lighting")
    if context.cameras is None or len(context.cameras) != render_output.color.shape[0]:
        raise ReconError(
            f"effect {name}: the context's cameras must be the {render_output.color.shape[0]} "
            "cameras the batch was rendered from"
        )


# --------------------------------------------------------------------------------------------
# specular
# --------------------------------------------------------------------------------------------

_BASE_EXPONENT = 32.0


class Specular(ModelEffect):
    """Normalised Blinn-Phong highlight under the dominant light, added to the radiance.

    delta = s E_c max(0, n.l) (e + 8) / (8 pi) max(0, n.h)^e x alpha, e = 32 exp(log_exponent).
    """

    name = "specular"
    diagnosis = DiagnosisFacts(
        family="light_transport",
        evidence=("absorption",),
        absorption="frozen",
        modelled_by=("pbr",),
        confusable=("exposure", "view_dependent_reflectance"),
        identifiable_when="views spread around the light, so highlights move over the surface",
    )
    stage = "shading"
    per_view = False
    default_learning_rate = 0.02
    default_lock_fraction = 0.3
    learning_rate_scales = {"log_exponent": 2.0}

    def __init__(self, view_count: int | None = None, **options) -> None:
        super().__init__(view_count, **options)
        self.strength = torch.nn.Parameter(torch.zeros(()))
        self.log_exponent = torch.nn.Parameter(torch.zeros(()))

    def exponent(self) -> torch.Tensor:
        return _BASE_EXPONENT * self.log_exponent.exp()

    def forward(self, render_output: RenderOutput, context: EffectContext) -> RenderOutput:
        _check_shading_inputs(render_output, context, self.name)
        color = render_output.color
        height, width = color.shape[1:3]
        directions, irradiance = view_light_directions(context.lighting, context.cameras, color)
        direction = directions[:, None, None, :]  # [B, 1, 1, 3]
        normals = render_output.normals.to(color)
        to_camera = view_directions(context.cameras, height, width, color)
        halfway = torch.nn.functional.normalize(to_camera + direction, dim=-1)
        cosine = (normals * direction).sum(-1, keepdim=True).clamp(min=0.0)
        # n.h is clamped above 0 so that pow's gradient in the exponent (log n.h) stays finite.
        alignment = (normals * halfway).sum(-1, keepdim=True).clamp(min=1e-6)
        exponent = self.exponent().to(color)
        lobe = (exponent + 8) / (8 * math.pi) * alignment.pow(exponent)
        highlight = self.strength.to(color) * irradiance * cosine * lobe
        return replace(render_output, color=color + highlight * render_output.alpha.to(color))

    def parameters_summary(self) -> dict:
        exponent = float(self.exponent().detach())
        alpha = math.sqrt(2.0 / (exponent + 2.0))
        return {
            "strength": to_float(self.strength.detach()),
            "exponent": to_float(exponent),
            "equivalent_ggx_alpha": to_float(alpha),
            "equivalent_roughness": to_float(math.sqrt(alpha)),
        }


# --------------------------------------------------------------------------------------------
# shadows
# --------------------------------------------------------------------------------------------


class Shadows(ModelEffect):
    """Shadow-map visibility of the dominant light; removes s x (1 - V) of its Lambertian term.

    delta = -s (1 - V) albedo / pi E_c max(0, n.l) x alpha, V the filtered visibility with
    softness = 0.5 texel x exp(log_softness) in depth. A point passes the depth test by the
    bias (bias_texels + slope_bias_texels x tan(light angle)) texels, several softnesses, so
    lit surfaces stay at V ~ 1 (no acne) while points a few texels behind an occluder reach
    V ~ 0. map_resolution: the shadow map's side.
    """

    name = "shadows"
    diagnosis = DiagnosisFacts(
        family="light_transport",
        evidence=("fingerprint", "cast_shadow"),
        fingerprint_side="blocked",
        confusable=("interreflection",),
        identifiable_when="views under a second light, or a mesh that shadows itself",
    )
    stage = "shading"
    per_view = False
    default_learning_rate = 0.02
    default_lock_fraction = 0.3
    learning_rate_scales = {"log_softness": 2.0}

    def __init__(
        self,
        view_count: int | None = None,
        map_resolution: int = 256,
        bias_texels: float = 2.0,
        slope_bias_texels: float = 2.0,
        **options,
    ) -> None:
        super().__init__(view_count, **options)
        if int(map_resolution) < 8:
            raise ReconError(
                f"effect {self.name}: map_resolution must be >= 8, got {map_resolution}"
            )
        self.map_resolution = int(map_resolution)
        self.bias_texels = float(bias_texels)
        self.slope_bias_texels = float(slope_bias_texels)
        self.strength = torch.nn.Parameter(torch.zeros(()))
        self.log_softness = torch.nn.Parameter(torch.zeros(()))
        self._cache: tuple[tuple, OrthographicFrames, torch.Tensor] | None = None
        self._receivers: tuple | None = None  # see receivers

    def shadow_map(
        self, mesh: Mesh, directions: torch.Tensor
    ) -> tuple[OrthographicFrames, torch.Tensor]:
        """(frames, depth maps [K, R, R]) along directions [K, 3] or [3] (K = 1), cached for
        an unchanged mesh and light."""
        directions = directions.reshape(-1, 3)
        key = (
            _fingerprint(mesh.verts),
            _fingerprint(mesh.faces),
            tuple(float(value) for value in directions.detach().cpu().reshape(-1)),
            self.map_resolution,
        )
        if self._cache is None or self._cache[0] != key:
            frames = OrthographicFrames.build(mesh.verts, directions)
            maps = frames.depth_maps(mesh.verts, mesh.faces, self.map_resolution)
            self._cache = (key, frames, maps)
        return self._cache[1], self._cache[2]

    def receivers(
        self, render_output: RenderOutput, mesh: Mesh, directions: torch.Tensor
    ) -> tuple[torch.Tensor, list[tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]]]:
        """What the depth test of the covered pixels needs, whatever the softness: (depth maps
        [K, R, R], per map (pixels [N] bool or None for all, their NDC [1, M, 3], their bias
        [1, M])). directions as in visibility.

        Without gradients the result is kept for the same fragments, normals, mesh and light:
        a diagnosis probe renders one frozen scene many times over, changing only the
        strength and softness (the same tensors, not recomputed)."""
        fragments = render_output.fragments
        dtype = render_output.color.dtype
        per_view = directions.ndim == 2 and directions.shape[0] > 1
        directions = directions.reshape(-1, 3)
        frames, maps = self.shadow_map(mesh, directions if per_view else directions[:1])
        kept = self._receivers
        if (
            not torch.is_grad_enabled()
            and kept is not None
            and kept[0] is fragments
            and kept[1] is render_output.normals
            and kept[2] is maps
            and kept[3] == dtype
        ):
            return maps, kept[4]
        points = interpolate_packed(mesh.verts, fragments, mesh.faces).to(dtype)  # [N, 3]
        normals = render_output.normals.reshape(-1, 3)[fragments.covered_index].to(dtype)
        # Each covered pixel's own map: its view's (per-view light) or the only one.
        which = fragments.covered_batch if per_view else torch.zeros_like(fragments.covered_batch)
        direction = directions.to(dtype)[which]  # [N, 3]
        cosine = (normals * direction).sum(-1).clamp(0.05, 1.0)
        # (The floor keeps sqrt's derivative finite where a normal faces the light square on:
        # at zero it is infinite, and times the clamp's zero it is NaN for the whole backward.)
        slope = torch.sqrt((1 - cosine * cosine).clamp_min(1e-12)) / cosine
        texel = 2.0 / self.map_resolution  # NDC units
        bias = texel * (self.bias_texels + self.slope_bias_texels * slope.clamp(max=10.0))
        ndc = frames.to_ndc(points)  # [K, N, 3]
        if per_view:
            parts = []
            for view in range(maps.shape[0]):
                chosen = which == view
                parts.append((chosen, ndc[view : view + 1, chosen], bias[chosen][None]))
        else:
            parts = [(None, ndc, bias[None])]
        self._receivers = None
        if not torch.is_grad_enabled():
            self._receivers = (fragments, render_output.normals, maps, dtype, parts)
        return maps, parts

    def visibility(
        self, render_output: RenderOutput, mesh: Mesh, directions: torch.Tensor
    ) -> torch.Tensor:
        """Soft visibility [B, H, W, 1] of the light from each covered pixel (1 on background).

        directions: [3] (every view) or [B, 3] (one per view: a camera-frame light), unit world
        directions toward the light."""
        fragments = render_output.fragments
        dtype = render_output.color.dtype
        maps, parts = self.receivers(render_output, mesh, directions)
        texel = 2.0 / self.map_resolution  # NDC units
        softness = 0.5 * texel * self.log_softness.exp().to(dtype)
        # Without gradients, kept for the same receivers and softness: a probe's Jacobian
        # columns that move the strength (or another effect) leave the visibility as it was.
        kept = getattr(self, "_visibility", None)
        if not torch.is_grad_enabled() and kept is not None and kept[0] is parts:
            if kept[1] == float(softness):
                return kept[2]
        if parts[0][0] is not None:  # one map per view
            packed = torch.ones(fragments.covered_index.shape[0], dtype=dtype, device=maps.device)
            for view, (chosen, ndc, bias) in enumerate(parts):
                packed = packed.masked_scatter(
                    chosen, filtered_visibility(maps[view : view + 1], ndc, bias, softness)[0]
                )
        else:
            _, ndc, bias = parts[0]
            packed = filtered_visibility(maps, ndc, bias, softness)[0]
        batch = fragments.batch_size
        height, width = fragments.resolution
        visible = scatter_to_image(
            1 - packed[:, None], fragments.covered_index, batch, height, width
        )
        visibility = 1 - visible
        self._visibility = None
        if not torch.is_grad_enabled():
            self._visibility = (parts, float(softness), visibility)
        return visibility

    def forward(self, render_output: RenderOutput, context: EffectContext) -> RenderOutput:
        _check_shading_inputs(render_output, context, self.name)
        color = render_output.color
        directions, irradiance = view_light_directions(context.lighting, context.cameras, color)
        if context.lighting.frame == "camera":
            visibility = self.visibility(render_output, context.mesh, directions)
        else:
            visibility = self.visibility(render_output, context.mesh, directions[0])
        direct = self._direct(render_output, directions, irradiance)
        darkening = self.strength.to(color) * (1 - visibility) * direct
        return replace(render_output, color=color - darkening * render_output.alpha.to(color))

    def _direct(
        self, render_output: RenderOutput, directions: torch.Tensor, irradiance: torch.Tensor
    ) -> torch.Tensor:
        """The direct light [B, H, W, C] the shadow takes away at full strength; without
        gradients kept for the same buffers and light (it does not depend on the parameters)."""
        color = render_output.color
        key = (render_output.normals, render_output.albedo, color.dtype)
        kept = getattr(self, "_direct_kept", None)
        if (
            not torch.is_grad_enabled()
            and kept is not None
            and all(one is other for one, other in zip(kept[0], key, strict=True))
            and torch.equal(kept[1], directions)
            and torch.equal(kept[2], irradiance)
        ):
            return kept[3]
        normals = render_output.normals.to(color)
        cosine = (normals * directions[:, None, None, :]).sum(-1, keepdim=True).clamp(min=0.0)
        direct = render_output.albedo.to(color) / math.pi * irradiance * cosine
        self._direct_kept = None
        if not torch.is_grad_enabled():
            self._direct_kept = (key, directions.clone(), irradiance.clone(), direct)
        return direct

    def parameters_summary(self) -> dict:
        return {
            "strength": to_float(self.strength.detach()),
            "softness_texels": to_float(0.5 * self.log_softness.detach().exp()),
            "map_resolution": self.map_resolution,
        }


# --------------------------------------------------------------------------------------------
# interreflection
# --------------------------------------------------------------------------------------------


def vertex_direction_visibility(
    verts: torch.Tensor, faces: torch.Tensor, sphere: torch.Tensor, resolution: int = 96
) -> tuple[torch.Tensor, torch.Tensor]:
    """(cosine [K, V], seen [K, V]) of each vertex toward each direction of sphere [K, 3].

    seen is 1 where the depth map along the direction has no surface in front of the vertex (a
    2 x 2 filtered, nearly hard comparison, with the vertex lifted by a texel along its normal
    against self-occlusion); cosine is max(0, n.d). No gradient.
    """
    with torch.no_grad():
        verts = verts.detach().float()
        normals = vertex_normals(verts, faces)
        sphere = sphere.to(verts)
        frames = OrthographicFrames.build(verts, sphere)
        maps = frames.depth_maps(verts, faces, resolution)
        texel = 2.0 / resolution
        lifted = verts + normals * (texel * frames.radius)
        ndc = frames.to_ndc(lifted)  # [K, V, 3]
        cosine = (normals @ sphere.T).clamp(min=0.0).T  # [K, V]
        slope = torch.sqrt(1 - cosine.clamp(0.05, 1.0) ** 2) / cosine.clamp(0.05, 1.0)
        bias = texel * (1.0 + 1.5 * slope.clamp(max=10.0))
        seen = filtered_visibility(maps, ndc, bias, torch.tensor(0.1 * texel))
        return cosine, seen


# The last sky-visibility computation: the interreflection module and the diagnosis' visibility
# fingerprint ask for the same mesh's 64 directions one after the other.
_SKY_CACHE: list = []


def sky_visibility(
    verts: torch.Tensor, faces: torch.Tensor, directions: int = 64, resolution: int = 96
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(sphere [K, 3], cosine [K, V], seen [K, V]) along `directions` Fibonacci directions
    (vertex_direction_visibility), cached for the last mesh asked about. No gradient."""
    key = (_fingerprint(verts), _fingerprint(faces), int(directions), int(resolution))
    if _SKY_CACHE and _SKY_CACHE[0][0] == key:
        return _SKY_CACHE[0][1]
    sphere = fibonacci_directions(directions).to(verts.device)
    cosine, seen = vertex_direction_visibility(verts, faces, sphere, resolution)
    _SKY_CACHE[:] = [(key, (sphere, cosine, seen))]
    return sphere, cosine, seen


def vertex_occlusion(
    verts: torch.Tensor, faces: torch.Tensor, directions: int = 64, resolution: int = 96
) -> torch.Tensor:
    """Cosine-weighted share [V] of each vertex's hemisphere that sees the mesh itself
    (vertex_direction_visibility along `directions` Fibonacci directions). No gradient."""
    _, cosine, seen = sky_visibility(verts, faces, directions, resolution)
    weight = cosine.sum(dim=0).clamp(min=1e-12)
    return 1 - (cosine * seen).sum(dim=0) / weight


def rotation_between(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The rotation [3, 3] (float64) about source x target that takes unit source [3] onto unit
    target [3] (a half turn about any perpendicular axis when they are opposite)."""
    source, target = source.double(), target.double()
    axis = torch.linalg.cross(source, target)
    sine, cosine = float(axis.norm()), float(source @ target)
    if sine < 1e-9:
        if cosine > 0:
            return torch.eye(3, dtype=torch.float64)
        helper = torch.eye(3, dtype=torch.float64)[int(source.abs().argmin())]
        axis = torch.nn.functional.normalize(torch.linalg.cross(source, helper), dim=0)
        return 2 * torch.outer(axis, axis) - torch.eye(3, dtype=torch.float64)
    axis = axis / sine
    cross = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
        dtype=torch.float64,
    )
    return torch.eye(3, dtype=torch.float64) + sine * cross + (1 - cosine) * cross @ cross


def rotated_light_visibility(
    verts: torch.Tensor,
    faces: torch.Tensor,
    lighting: Lighting,
    rotations: torch.Tensor,
    directions: int = 64,
    resolution: int = 96,
) -> torch.Tensor:
    """vertex_light_visibility [R, V] of the light turned by each rotation [R, 3, 3] (world
    frame): the environment's radiance along direction w is the light's along R^T w, and each
    directional light points along R d. The identity gives vertex_light_visibility. No
    gradient."""
    with torch.no_grad():
        sphere, cosine, seen = sky_visibility(verts, faces, directions, resolution)
        sphere, cosine, seen = sphere.double(), cosine.double(), seen.double()
        rotations = rotations.double().to(sphere.device)
        weights = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64, device=verts.device)
        coefficients = lighting.sh_coefficients.detach().to(sphere)
        channels = coefficients.shape[-1]
        luminance = weights[:channels] / weights[:channels].sum()
        # Radiance along R^T w for every rotation: the row vector w R.
        turned = torch.einsum("kd,rde->rke", sphere, rotations)  # [R, K, 3]
        radiance = (sh_basis(turned) @ coefficients).clamp(min=0.0) @ luminance  # [R, K]
        power = radiance * (4 * math.pi / directions)
        total = power @ cosine  # [R, V]
        visible = power @ (cosine * seen)
        if lighting.directional:
            suns = torch.nn.functional.normalize(
                torch.stack([light.direction_to_light.detach() for light in lighting.directional]),
                dim=-1,
            ).to(sphere)
            sun_power = torch.stack(
                [light.irradiance.detach().to(sphere) @ luminance for light in lighting.directional]
            )
            pointed = torch.einsum("rde,se->rsd", rotations, suns).reshape(-1, 3)  # [R * S, 3]
            sun_cosine, sun_seen = vertex_direction_visibility(verts, faces, pointed, resolution)
            count = rotations.shape[0]
            sun_cosine = sun_cosine.double().reshape(count, len(suns), -1)
            sun_seen = sun_seen.double().reshape(count, len(suns), -1)
            total = total + torch.einsum("s,rsv->rv", sun_power, sun_cosine)
            visible = visible + torch.einsum("s,rsv->rv", sun_power, sun_cosine * sun_seen)
        return torch.where(total > 1e-12, visible / total.clamp(min=1e-12), torch.ones_like(total))


def vertex_light_visibility(
    verts: torch.Tensor,
    faces: torch.Tensor,
    lighting: Lighting,
    directions: int = 64,
    resolution: int = 96,
) -> torch.Tensor:
    """Share [V] of each vertex's irradiance (luminance) from the light that the mesh does not
    block: sum over directions of cos x seen x radiance over the same without `seen`.

    The SH environment is sampled along `directions` Fibonacci directions (negative radiance
    clipped); each directional light adds its own direction. 1 for a convex mesh. No gradient.
    """
    with torch.no_grad():
        sphere, cosine, seen = sky_visibility(verts, faces, directions, resolution)
        sphere, cosine, seen = sphere.double(), cosine.double(), seen.double()
        weights = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64, device=verts.device)
        coefficients = lighting.sh_coefficients.detach().to(sphere)
        channels = coefficients.shape[-1]
        luminance = weights[:channels] / weights[:channels].sum()
        radiance = (sh_basis(sphere) @ coefficients).clamp(min=0.0) @ luminance  # [K]
        # Monte Carlo weight of a direction: 4 pi / K of solid angle.
        power = radiance * (4 * math.pi / directions)
        if lighting.directional:
            sun_directions = torch.nn.functional.normalize(
                torch.stack([light.direction_to_light.detach() for light in lighting.directional]),
                dim=-1,
            ).to(sphere)
            sun_power = torch.stack(
                [light.irradiance.detach().to(sphere) @ luminance for light in lighting.directional]
            )
            sun_cosine, sun_seen = vertex_direction_visibility(
                verts, faces, sun_directions, resolution
            )
            cosine = torch.cat([cosine, sun_cosine.double()])
            seen = torch.cat([seen, sun_seen.double()])
            power = torch.cat([power, sun_power])
        total = (cosine * power[:, None]).sum(dim=0)
        visible = (cosine * seen * power[:, None]).sum(dim=0)
        return torch.where(total > 1e-12, visible / total.clamp(min=1e-12), torch.ones_like(total))


class Interreflection(ModelEffect):
    """One diffuse bounce into concavities: delta = s occlusion albedo^2 E_mean / pi x alpha.

    occlusion: vertex_occlusion of the mesh (cached), interpolated to pixels; E_mean: the
    fitted light's sphere-averaged irradiance. A negative s darkens concavities instead (the
    environment they do not see), which the sign of the recovered strength reports.
    """

    name = "interreflection"
    diagnosis = DiagnosisFacts(
        family="light_transport",
        evidence=("fingerprint", "bounce"),
        fingerprint_side="bounced",
        confusable=("shadows",),
        identifiable_when="views under a second light, or concave regions that see each other",
    )
    stage = "shading"
    per_view = False
    default_learning_rate = 0.02
    default_lock_fraction = 0.3

    def __init__(
        self,
        view_count: int | None = None,
        directions: int = 64,
        map_resolution: int = 96,
        **options,
    ) -> None:
        super().__init__(view_count, **options)
        self.directions = int(directions)
        self.map_resolution = int(map_resolution)
        if self.directions < 4 or self.map_resolution < 8:
            raise ReconError(
                f"effect {self.name}: expected directions >= 4 and map_resolution >= 8, got "
                f"{self.directions} and {self.map_resolution}"
            )
        self.strength = torch.nn.Parameter(torch.zeros(()))
        self._cache: tuple[tuple, torch.Tensor, torch.Tensor] | None = None

    def occlusion(self, mesh: Mesh) -> torch.Tensor:
        """Per-vertex occlusion [V], cached: recomputed only for another topology or when a
        vertex moved by more than OCCLUSION_TOLERANCE of the bounding-box diagonal (a tenth of
        a depth-map texel), so a refit that nudges positions does not redraw 64 depth maps at
        every step."""
        verts = mesh.verts.detach()
        key = (_fingerprint(mesh.faces), self.directions, self.map_resolution)
        if self._cache is not None:
            cached_key, cached_verts, cached = self._cache
            if cached_key == key and cached_verts.shape == verts.shape:
                diagonal = float((verts.max(0).values - verts.min(0).values).norm())
                moved = float((verts - cached_verts).abs().max()) if verts.numel() else 0.0
                if moved <= OCCLUSION_TOLERANCE * diagonal:
                    return cached
        occlusion = vertex_occlusion(verts, mesh.faces, self.directions, self.map_resolution)
        self._cache = (key, verts.clone(), occlusion)
        return occlusion

    def forward(self, render_output: RenderOutput, context: EffectContext) -> RenderOutput:
        _check_shading_inputs(render_output, context, self.name)
        color = render_output.color
        mesh = context.mesh
        fragments = render_output.fragments
        occlusion = self.occlusion(mesh).to(device=color.device, dtype=mesh.verts.dtype)
        packed = interpolate_packed(occlusion[:, None], fragments, mesh.faces)
        batch = fragments.batch_size
        height, width = fragments.resolution
        occluded = scatter_to_image(packed, fragments.covered_index, batch, height, width).to(color)
        albedo = render_output.albedo.to(color)
        irradiance = mean_irradiance(context.lighting).to(color)
        bounce = self.strength.to(color) * occluded * albedo * albedo * irradiance / math.pi
        return replace(render_output, color=color + bounce * render_output.alpha.to(color))

    def parameters_summary(self) -> dict:
        summary = {"strength": to_float(self.strength.detach())}
        if self._cache is not None:
            summary["mean_vertex_occlusion"] = to_float(self._cache[2].mean())
        return summary
