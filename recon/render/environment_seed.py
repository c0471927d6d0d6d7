"""A sharp starting environment for the `pbr` fit: observed highlights back-projected along the
mirror-reflection directions into a lat-long map.

Why: with the environment unknown, a blurry start (the geometry stage's order-2 SH light) and
the roughness trade off, and the fit settles rougher than the surface
(docs/decisions/0180-pbr-roughness-gauge.md). Under the split-sum model a pixel's radiance is

    c = diffuse + s(n.v, r) L_r(R),   s = F0 A(n.v, r) + B(n.v, r),   R = reflect(v, n),

so the specular excess c - diffuse divided by s is a sample of the (pre-filtered) environment
along R. Every covered pixel of every training view votes for the texels around its R with its
bilinear weight w; per texel the least-squares estimate with a prior pull kappa toward the
starting map L_0 is

    L = (sum w s (c - diffuse) + kappa L_0) / (sum w s^2 + kappa),   clamped at 0,

the minimiser of sum w (s L - (c - diffuse))^2 + kappa (L - L_0)^2 for each texel when each
pixel's bilinear share w is taken as the texel's own (the diagonal of the normal equations).
Texels that no reflection reaches keep L_0. The estimate is the environment as pre-filtered at
the surface's roughness (a highlight is the light blurred by the lobe): sharp enough to start
the fit from a low roughness, which then rises toward the truth.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from recon.errors import ReconError
from recon.render.brdf import lookup_split_sum
from recon.render.environment import sample_latlong


def specular_weight(
    n_dot_v: torch.Tensor, roughness: float, specular_level: float = 0.5
) -> torch.Tensor:
    """s = F0 A + B [..., 1] of a dielectric (F0 = 0.08 specular_level) at n.v [..., 1]."""
    scale_bias = lookup_split_sum(n_dot_v, torch.full_like(n_dot_v, roughness))
    return 0.08 * specular_level * scale_bias[..., 0:1] + scale_bias[..., 1:2]


def backproject_highlights(
    observed: torch.Tensor,
    diffuse: torch.Tensor,
    normals: torch.Tensor,
    to_viewer: torch.Tensor,
    prior: torch.Tensor,
    roughness: float,
    specular_level: float = 0.5,
    prior_weight: float = 1e-3,
    minimum_cosine: float = 0.2,
) -> torch.Tensor:
    """The environment [h, w, C] that explains observed - diffuse as a dielectric's specular
    reflection (module docstring).

    observed, diffuse: [N, C] linear radiance of covered pixels and the diffuse part a model
    predicts for them; normals, to_viewer: [N, 3] unit shading normals and directions to the
    camera (in the environment's frame); prior: [h, w, C] the starting map L_0; roughness: the
    roughness the fit starts from (s's roughness); prior_weight: kappa, in units of one pixel's
    w s^2 at s = 1; pixels with n.v below minimum_cosine (silhouettes, where normals are least
    reliable and s is largest) do not vote.
    """
    if observed.shape != diffuse.shape or observed.ndim != 2:
        raise ReconError(
            f"backproject_highlights: observed {tuple(observed.shape)} and diffuse "
            f"{tuple(diffuse.shape)} must both be [N, C]"
        )
    if normals.shape != (observed.shape[0], 3) or to_viewer.shape != normals.shape:
        raise ReconError(
            f"backproject_highlights: normals {tuple(normals.shape)} and to_viewer "
            f"{tuple(to_viewer.shape)} must be [{observed.shape[0]}, 3]"
        )
    if prior.ndim != 3 or prior.shape[-1] != observed.shape[-1]:
        raise ReconError(
            f"backproject_highlights: prior {tuple(prior.shape)} must be [h, w, "
            f"{observed.shape[-1]}]"
        )
    n_dot_v = (normals * to_viewer).sum(-1, keepdim=True)
    voting = n_dot_v[:, 0] >= minimum_cosine
    n_dot_v, normals, to_viewer = n_dot_v[voting], normals[voting], to_viewer[voting]
    excess = (observed - diffuse)[voting]
    reflected = F.normalize(2 * n_dot_v * normals - to_viewer, dim=-1, eps=1e-12)
    weight = specular_weight(n_dot_v, roughness, specular_level)
    # The adjoint of the bilinear look-up splats each pixel's value onto its four texels: the
    # gradient of sum(value * sample(map, R)) with respect to the map.
    height, width, channels = prior.shape
    grid = torch.zeros(
        height, width, channels + 1, dtype=prior.dtype, device=prior.device, requires_grad=True
    )
    values = torch.cat([weight * excess, weight.square()], dim=-1).detach().to(prior.dtype)
    with torch.enable_grad():
        (sample_latlong(grid, reflected.to(prior.dtype)) * values).sum().backward()
    splat = grid.grad
    numerator, denominator = splat[..., :channels], splat[..., channels:]
    estimate = (numerator + prior_weight * prior) / (denominator + prior_weight)
    return estimate.clamp_min(0)
