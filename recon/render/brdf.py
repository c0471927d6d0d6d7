"""A metallic-roughness microfacet BRDF (GGX / Smith / Schlick) and its split-sum lookup table.

Written from the published descriptions: Walter et al. 2007 (GGX distribution and its importance
sampling), Heitz 2014 (height-correlated Smith masking), Karis 2013 ("Real Shading in Unreal
Engine 4": Schlick Fresnel, the split-sum approximation and its pre-integrated BRDF table).

Conventions: roughness r in [0, 1] is perceptual; the GGX width is alpha = r^2. All cosines are
with respect to the shading normal n. The specular BRDF is

    f_s(l, v) = D(h) V(l, v) F(v.h),   V = G2 / (4 (n.l) (n.v)),

with D the GGX distribution, G2 the height-correlated Smith masking-shadowing term and F
Schlick's Fresnel F0 + (1 - F0) (1 - v.h)^5. The reflectance at normal incidence is
F0 = mix(0.08 specular_level, base_colour, metalness) (specular_level 0.5 gives the usual 0.04).

The split-sum table holds, for each (n.v, roughness), the two scale factors (A, B) with

    integral over the hemisphere of f_s(l, v) (n.l) dl = F0 A + B,

computed here by GGX importance sampling with deterministic Hammersley points, cached per
device and dtype. Everything is torch and differentiable; the device follows the inputs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# The smallest GGX width used: alpha = 0 is a mirror whose D is a delta function.
MINIMUM_ALPHA = 1e-3
# Cosines are clamped away from 0 where they divide.
MINIMUM_COSINE = 1e-4

_LUT_CACHE: dict[tuple, torch.Tensor] = {}


def roughness_to_alpha(roughness: torch.Tensor) -> torch.Tensor:
    """GGX width alpha = r^2 of perceptual roughness r (Karis 2013), kept above MINIMUM_ALPHA."""
    return (roughness * roughness).clamp_min(MINIMUM_ALPHA)


def ggx_distribution(n_dot_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution D(h) = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2); 0 for
    n.h <= 0. Integrates (times n.h) to 1 over the hemisphere."""
    alpha_squared = alpha * alpha
    cosine = n_dot_h.clamp_min(0)
    denominator = cosine * cosine * (alpha_squared - 1) + 1
    value = alpha_squared / (math.pi * denominator * denominator)
    return torch.where(n_dot_h > 0, value, torch.zeros_like(value))


def smith_visibility(n_dot_l: torch.Tensor, n_dot_v: torch.Tensor, alpha: torch.Tensor):
    """Height-correlated Smith visibility V = G2 / (4 (n.l) (n.v)) for GGX (Heitz 2014):
    0.5 / (n.l sqrt((n.v)^2 (1 - a^2) + a^2) + n.v sqrt((n.l)^2 (1 - a^2) + a^2))."""
    alpha_squared = alpha * alpha
    cos_l = n_dot_l.clamp_min(MINIMUM_COSINE)
    cos_v = n_dot_v.clamp_min(MINIMUM_COSINE)
    lambda_v = cos_l * torch.sqrt(cos_v * cos_v * (1 - alpha_squared) + alpha_squared)
    lambda_l = cos_v * torch.sqrt(cos_l * cos_l * (1 - alpha_squared) + alpha_squared)
    return 0.5 / (lambda_v + lambda_l)


def fresnel_schlick(f0: torch.Tensor, v_dot_h: torch.Tensor) -> torch.Tensor:
    """Schlick's Fresnel F0 + (1 - F0) (1 - v.h)^5 (broadcasts f0 [..., C] with v.h [..., 1])."""
    weight = (1 - v_dot_h.clamp(0, 1)) ** 5
    return f0 + (1 - f0) * weight


def specular_f0(
    base_color: torch.Tensor, metalness: torch.Tensor, specular_level: float = 0.5
) -> torch.Tensor:
    """Normal-incidence reflectance [..., C] = mix(0.08 specular_level, base_color, metalness)."""
    dielectric = 0.08 * specular_level
    return dielectric * (1 - metalness) + base_color * metalness


def specular_brdf(
    normals: torch.Tensor,
    to_light: torch.Tensor,
    to_viewer: torch.Tensor,
    roughness: torch.Tensor,
    f0: torch.Tensor,
) -> torch.Tensor:
    """f_s(l, v) [..., C] for unit normals, directions to light and to viewer [..., 3],
    roughness [..., 1] and F0 [..., C]; 0 where the light or the viewer is below the surface."""
    alpha = roughness_to_alpha(roughness)
    half = F.normalize(to_light + to_viewer, dim=-1, eps=1e-12)
    n_dot_l = (normals * to_light).sum(-1, keepdim=True)
    n_dot_v = (normals * to_viewer).sum(-1, keepdim=True)
    n_dot_h = (normals * half).sum(-1, keepdim=True)
    v_dot_h = (to_viewer * half).sum(-1, keepdim=True)
    value = (
        ggx_distribution(n_dot_h, alpha)
        * smith_visibility(n_dot_l, n_dot_v, alpha)
        * fresnel_schlick(f0, v_dot_h)
    )
    visible = (n_dot_l > 0) & (n_dot_v > 0)
    return torch.where(visible, value, torch.zeros_like(value))


def hammersley(count: int, dtype=torch.float64) -> torch.Tensor:
    """Hammersley points [count, 2] in [0, 1)^2: (i / count, radical inverse of i in base 2)."""
    index = torch.arange(count, dtype=torch.int64)
    reversed_bits = torch.zeros(count, dtype=torch.float64)
    scale = 0.5
    bits = index.clone()
    while bool((bits > 0).any()):
        reversed_bits += (bits & 1).double() * scale
        bits = bits >> 1
        scale *= 0.5
    return torch.stack([index.double() / count, reversed_bits], dim=-1).to(dtype)


def sample_ggx_half_vectors(points: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX-distributed half vectors around +z (Walter et al. 2007, pdf D(h) n.h).

    points: [S, 2] in [0, 1)^2; alpha: [..., 1]. Returns [..., S, 3] (local frame, z = normal).
    """
    phi = 2 * math.pi * points[:, 0]
    xi = points[:, 1]
    alpha_squared = (alpha * alpha)[..., None, :]  # [..., 1, 1]
    cos_theta = torch.sqrt((1 - xi[:, None]) / (1 + (alpha_squared - 1) * xi[:, None]))
    sin_theta = torch.sqrt((1 - cos_theta * cos_theta).clamp_min(0))
    return torch.cat(
        [
            sin_theta * torch.cos(phi)[:, None],
            sin_theta * torch.sin(phi)[:, None],
            cos_theta,
        ],
        dim=-1,
    )


def integrate_split_sum(
    n_dot_v: torch.Tensor, roughness: torch.Tensor, sample_count: int = 1024
) -> torch.Tensor:
    """The split-sum factors (A, B) [..., 2] at n.v [...] and roughness [...] (broadcast), by
    importance sampling the GGX half vector with Hammersley points (Karis 2013, eq. 8): the
    estimate of integral f_s (n.l) dl for each sample is 4 V (n.l)(v.h) / (n.h), split by the
    Fresnel weight Fc = (1 - v.h)^5 into A (times 1 - Fc) and B (times Fc)."""
    n_dot_v, roughness = torch.broadcast_tensors(n_dot_v, roughness)
    dtype = n_dot_v.dtype
    cos_v = n_dot_v.clamp(MINIMUM_COSINE, 1)[..., None]
    # Viewer in the local frame (normal = +z), in the x-z plane.
    viewer = torch.cat([torch.sqrt(1 - cos_v * cos_v), torch.zeros_like(cos_v), cos_v], -1)
    alpha = roughness_to_alpha(roughness)[..., None]
    half = sample_ggx_half_vectors(hammersley(sample_count, dtype).to(n_dot_v.device), alpha)
    v_dot_h = (viewer[..., None, :] * half).sum(-1)  # [..., S]
    n_dot_h = half[..., 2]
    n_dot_l = 2 * v_dot_h * n_dot_h - cos_v  # l = 2 (v.h) h - v, its z component
    visibility = smith_visibility(n_dot_l, cos_v.expand_as(n_dot_l), alpha)
    weight = 4 * visibility * n_dot_l * v_dot_h.clamp_min(0) / n_dot_h.clamp_min(MINIMUM_COSINE)
    weight = torch.where(n_dot_l > 0, weight, torch.zeros_like(weight))
    fresnel_weight = (1 - v_dot_h.clamp(0, 1)) ** 5
    scale = ((1 - fresnel_weight) * weight).mean(-1)
    bias = (fresnel_weight * weight).mean(-1)
    return torch.stack([scale, bias], dim=-1)


def split_sum_table(
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    size: int = 32,
    sample_count: int = 1024,
) -> torch.Tensor:
    """The split-sum BRDF table [size (n.v), size (roughness), 2 (A, B)] on nodes
    linspace(0, 1, size) of both axes, computed once in float64 and cached per device/dtype."""
    key = (str(torch.device(device)), dtype, size, sample_count)
    table = _LUT_CACHE.get(key)
    if table is None:
        nodes = torch.linspace(0, 1, size, dtype=torch.float64)
        n_dot_v, roughness = torch.meshgrid(nodes, nodes, indexing="ij")
        table = integrate_split_sum(n_dot_v, roughness, sample_count).to(device, dtype)
        _LUT_CACHE[key] = table
    return table


def lookup_split_sum(n_dot_v: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """(A, B) [..., 2] at n.v [..., 1] and roughness [..., 1], bilinear in the cached table;
    differentiable in both arguments (grid_sample's gradient with respect to the grid)."""
    table = split_sum_table(n_dot_v.device, n_dot_v.dtype)
    leading = n_dot_v.shape[:-1]
    # grid_sample: x runs along the width (roughness), y along the height (n.v).
    grid = torch.stack(
        [roughness.reshape(-1).clamp(0, 1) * 2 - 1, n_dot_v.reshape(-1).clamp(0, 1) * 2 - 1], -1
    )
    sampled = F.grid_sample(
        table.permute(2, 0, 1)[None],
        grid[None, None],
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )  # [1, 2, 1, N]
    return sampled[0, :, 0].transpose(0, 1).reshape(*leading, 2)
