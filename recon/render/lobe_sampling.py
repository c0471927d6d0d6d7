"""Full-lobe specular shading: the GGX lobe integrated per pixel by a few visible-normal samples
that look the environment up pre-filtered at a small roughness (filtered importance sampling).

Why: the split-sum approximation (recon.render.pbr) assumes n = v = r when it pre-filters the
light, so the reflected lobe is the same round blur at every view angle. A blurrier light and
a rougher surface then give the same image and the fit trades one for the other
(docs/decisions/0180-pbr-roughness-gauge.md). The true lobe stretches and leaves the mirror
direction at grazing angles, by an amount that grows with the roughness; views that see the
same light at different n.v then tell the two apart (docs/decisions/0193-pbr-roughness-lobe.md).

Written from the published descriptions: Heitz 2018 ("Sampling the GGX Distribution of Visible
Normals") for the samples and their weight F G2 / G1(v), Colbert and Krivanek 2007 ("GPU-Based
Importance Sampling", GPU Gems 3) for the filtered look-ups, Duff et al. 2017 for the tangent
frame. For S samples h_s of the visible normals at the view v and l_s = reflect(v, h_s),

    integral f_s(l, v) L(l) (n.l) dl  ~  1/S sum_s F(v.h_s) G2(l_s, v) / G1(v) L~(l_s),

L~ the environment pre-filtered at roughness r_f with alpha_f = filter_width times the angular
radius of the solid angle one sample stands for, 1 / (S pdf(l_s)), pdf(l) = D_v(h) / (4 v.h).
The sample points are fixed (a Fibonacci lattice in [0, 1)^2), optionally shifted per pixel
(Cranley-Patterson rotation): everything is a smooth function of the normal, the view, the
roughness and the map, so gradients reach all of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from recon.render.brdf import MINIMUM_COSINE, fresnel_schlick, ggx_distribution, roughness_to_alpha
from recon.render.environment import PrefilteredEnvironment

GOLDEN_RATIO = (1 + math.sqrt(5)) / 2


def lattice_points(count: int, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """A Fibonacci lattice [count, 2] in [0, 1)^2: ((i + 0.5) / count, frac(i / golden ratio)),
    stratified in both coordinates."""
    index = torch.arange(count, dtype=torch.float64)
    points = torch.stack([(index + 0.5) / count, torch.frac(index / GOLDEN_RATIO)], dim=-1)
    return points.to(device, dtype)


def tangent_frame(normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit tangent and bitangent [..., 3] orthogonal to unit normals [..., 3] (Duff et al.
    2017: continuous except across the z = 0 plane, where the frame turns; the lobe integral
    does not depend on the frame, only the sample pattern's orientation does)."""
    x, y, z = normals.unbind(-1)
    sign = torch.where(z >= 0, 1.0, -1.0).to(normals.dtype)
    a = -1 / (sign + z)
    b = x * y * a
    tangent = torch.stack([1 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    bitangent = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return tangent, bitangent


def smith_masking(cosine: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith's G1 for GGX: 2 cos / (cos + sqrt(alpha^2 + (1 - alpha^2) cos^2)), cos clamped."""
    cosine = cosine.clamp_min(MINIMUM_COSINE)
    alpha_squared = alpha * alpha
    return 2 * cosine / (cosine + torch.sqrt(alpha_squared + (1 - alpha_squared) * cosine**2))


def sample_visible_normals(
    to_viewer: torch.Tensor, alpha: torch.Tensor, points: torch.Tensor
) -> torch.Tensor:
    """Microfacet normals [N, S, 3] distributed as GGX's visible normals D_v(h) = G1(v)
    max(0, v.h) D(h) / (n.v) (Heitz 2018), in the local frame (z = normal).

    to_viewer: [N, 3] local unit view directions (z > 0); alpha: [N, 1] GGX widths;
    points: [S, 2] or [N, S, 2] in [0, 1)^2.
    """
    alpha = alpha[..., None, :]  # [N, 1, 1]
    view = to_viewer[..., None, :]  # [N, 1, 3]
    # The view in the hemisphere configuration (the lobe stretched to alpha = 1).
    stretched = F.normalize(
        torch.cat([alpha * view[..., :2], view[..., 2:]], dim=-1), dim=-1, eps=1e-12
    )
    length_squared = stretched[..., :1] ** 2 + stretched[..., 1:2] ** 2
    length = torch.sqrt(length_squared.clamp_min(1e-24))
    along_x = torch.cat([torch.ones_like(length), torch.zeros_like(length)], dim=-1)
    first = torch.where(
        length_squared > 1e-20,
        torch.cat([-stretched[..., 1:2], stretched[..., 0:1]], dim=-1) / length,
        along_x,
    )
    first = torch.cat([first, torch.zeros_like(length)], dim=-1)
    second = torch.linalg.cross(stretched.expand_as(first), first, dim=-1)
    radius = torch.sqrt(points[..., 0:1])
    angle = 2 * math.pi * points[..., 1:2]
    t1 = radius * torch.cos(angle)
    t2 = radius * torch.sin(angle)
    # Warp the disk toward the projected hemisphere the view sees.
    s = 0.5 * (1 + stretched[..., 2:])
    t2 = (1 - s) * torch.sqrt((1 - t1 * t1).clamp_min(0)) + s * t2
    up = torch.sqrt((1 - t1 * t1 - t2 * t2).clamp_min(0))
    hemisphere = t1 * first + t2 * second + up * stretched
    # Back to the ellipsoid configuration.
    return F.normalize(
        torch.cat([alpha * hemisphere[..., :2], hemisphere[..., 2:].clamp_min(0)], dim=-1),
        dim=-1,
        eps=1e-12,
    )


@dataclass
class SampledEnvironment:
    """A pre-filtered environment shaded with the full GGX lobe (module docstring) instead of
    the split-sum approximation; pbr_shade takes it where it takes a PrefilteredEnvironment.

    prefiltered: the environment and its roughness chain (the diffuse irradiance comes from its
    SH as before). sample_count: S, samples per pixel. filter_width: alpha_f per radian of a
    sample's footprint (0: every sample looks level 0 up, bilinear). offsets: [N, 2] per-pixel
    shifts of the sample points (None: the same points everywhere).
    """

    prefiltered: PrefilteredEnvironment
    sample_count: int = 16
    filter_width: float = 0.5
    offsets: torch.Tensor | None = None

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """Diffuse irradiance E(n) [..., C] at unit normals [..., 3]."""
        return self.prefiltered.irradiance(normals)

    def specular_lobe(
        self,
        normals: torch.Tensor,
        to_viewer: torch.Tensor,
        roughness: torch.Tensor,
        f0: torch.Tensor,
    ) -> torch.Tensor:
        """integral f_s(l, v) L(l) (n.l) dl [N, C] for unit normals and directions to the
        viewer [N, 3], roughness [N, 1] and F0 [N, C]; the viewer is clamped to n.v >=
        MINIMUM_COSINE (silhouettes of smoothed normals)."""
        alpha = roughness_to_alpha(roughness)
        tangent, bitangent = tangent_frame(normals)
        local_view = torch.stack(
            [
                (to_viewer * tangent).sum(-1),
                (to_viewer * bitangent).sum(-1),
                (to_viewer * normals).sum(-1).clamp_min(MINIMUM_COSINE),
            ],
            dim=-1,
        )
        local_view = F.normalize(local_view, dim=-1, eps=1e-12)
        points = lattice_points(self.sample_count, normals.dtype, normals.device)
        if self.offsets is not None:
            points = torch.frac(points + self.offsets.to(normals.dtype)[:, None, :])
        half = sample_visible_normals(local_view, alpha, points)  # [N, S, 3]
        view = local_view[:, None, :]
        v_dot_h = (view * half).sum(-1, keepdim=True).clamp_min(0)  # [N, S, 1]
        local_light = 2 * v_dot_h * half - view
        n_dot_l = local_light[..., 2:]
        n_dot_v = view[..., 2:]
        alpha_sample = alpha[:, None, :]
        # G2 / G1(v) of the height-correlated Smith model: (1 + Lambda_v) / (1 + Lambda_v +
        # Lambda_l) with G1 = 1 / (1 + Lambda).
        lambda_v = 1 / smith_masking(n_dot_v, alpha_sample) - 1
        lambda_l = 1 / smith_masking(n_dot_l, alpha_sample) - 1
        weight = (1 + lambda_v) / (1 + lambda_v + lambda_l)
        weight = torch.where(n_dot_l > 0, weight, torch.zeros_like(weight))
        fresnel = fresnel_schlick(f0[:, None, :], v_dot_h)  # [N, S, C]
        light = (
            local_light[..., 0:1] * tangent[:, None, :]
            + local_light[..., 1:2] * bitangent[:, None, :]
            + local_light[..., 2:3] * normals[:, None, :]
        )
        lookup = torch.zeros_like(alpha_sample.expand_as(n_dot_l))
        if self.filter_width > 0:
            # pdf(l) = G1(v) D(h) / (4 n.v); a sample stands for 1 / (S pdf) steradians.
            density = (
                smith_masking(n_dot_v, alpha_sample)
                * ggx_distribution(half[..., 2:], alpha_sample)
                / (4 * n_dot_v)
            )
            footprint = 1 / (self.sample_count * density.clamp_min(1e-6))
            radius = torch.sqrt(footprint / math.pi).clamp(max=math.pi)
            # alpha_f = roughness_f^2; detached: the level is a filter choice, not a model
            # parameter (its gradient would push toward whichever blur fits the noise).
            lookup = torch.sqrt(self.filter_width * radius).clamp(0, 1).detach()
        radiance = self.prefiltered.specular(light.reshape(-1, 3), lookup.reshape(-1, 1))
        radiance = radiance.reshape(*light.shape[:-1], -1)
        return (fresnel * weight * radiance).mean(1)
