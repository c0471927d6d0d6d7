"""The GGX microfacet pieces of recon.render.brdf against their defining integrals: the
distribution projects to unit area, and Smith masking passes the weak white furnace (Heitz 2014:
integral of G1(v, m) D(m) max(0, v.m) dm = n.v), which ties D and the visibility term together
independently of Fresnel."""

from __future__ import annotations

import math

import pytest
import torch

from recon.render.brdf import ggx_distribution, roughness_to_alpha, smith_visibility


def _sphere_grid(theta_count: int = 4000, phi_count: int = 256):
    """Midpoint quadrature over the upper hemisphere: directions [T*P, 3] and dOmega, the polar
    nodes crowded toward the pole (theta = pi/2 s^2) where narrow lobes live."""
    s = (torch.arange(theta_count, dtype=torch.float64) + 0.5) / theta_count
    theta = math.pi / 2 * s * s
    dtheta = math.pi * s / theta_count
    phi = (torch.arange(phi_count, dtype=torch.float64) + 0.5) * 2 * math.pi / phi_count
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    weights = torch.sin(theta) * dtheta[:, None] * (2 * math.pi / phi_count)
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)],
        -1,
    )
    return directions.reshape(-1, 3), weights.reshape(-1)


@pytest.mark.parametrize("roughness", [0.15, 0.4, 0.8, 1.0])
def test_ggx_distribution_projects_to_unit_area(roughness):
    half, weights = _sphere_grid()
    alpha = roughness_to_alpha(torch.tensor(roughness, dtype=torch.float64))
    cosine = half[:, 2]
    assert float((ggx_distribution(cosine, alpha) * cosine * weights).sum()) == pytest.approx(
        1.0, abs=2e-3
    )


@pytest.mark.parametrize("roughness", [0.2, 0.5, 1.0])
@pytest.mark.parametrize("n_dot_v", [0.2, 0.6, 0.95])
def test_smith_masking_passes_the_weak_white_furnace(roughness, n_dot_v):
    """G1(v) from the height-correlated visibility at l = n (Lambda(n) = 0, so G2 = G1(v)):
    G1(v) = 4 (n.v) V(n, v). The visible microfacet area must equal the projected area n.v."""
    half, weights = _sphere_grid()
    alpha = roughness_to_alpha(torch.tensor(roughness, dtype=torch.float64))
    cos_v = torch.tensor(n_dot_v, dtype=torch.float64)
    viewer = torch.stack([torch.sqrt(1 - cos_v * cos_v), torch.zeros(()), cos_v])
    masking = 4 * cos_v * smith_visibility(torch.ones(()), cos_v, alpha)
    visible = (half @ viewer).clamp_min(0)
    integral = masking * (ggx_distribution(half[:, 2], alpha) * visible * weights).sum()
    assert float(integral) == pytest.approx(n_dot_v, rel=3e-3)
    # Masking hides part of the microsurface except at normal incidence of a smooth one.
    assert 0 < float(masking) <= 1
