"""SH irradiance against numerical integration, and Lambertian shading properties."""

from __future__ import annotations

import math

import pytest
import torch

from recon.errors import ReconError
from recon.render.shading import (
    DirectionalLight,
    Lighting,
    lambertian,
    sh_basis,
    sh_irradiance,
)


def _sphere_quadrature(count: int = 400) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions [N, 3] and solid-angle weights [N] on a latitude-longitude grid (float64)."""
    theta = (torch.arange(count, dtype=torch.float64) + 0.5) * math.pi / count
    phi = (torch.arange(2 * count, dtype=torch.float64) + 0.5) * math.pi / count
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1
    ).reshape(-1, 3)
    weights = (torch.sin(theta) * (math.pi / count) ** 2).reshape(-1)
    return directions, weights


def test_sh_basis_is_orthonormal():
    directions, weights = _sphere_quadrature(200)
    basis = sh_basis(directions)
    gram = basis.T @ (basis * weights[:, None])
    torch.testing.assert_close(gram, torch.eye(9, dtype=torch.float64), atol=2e-3, rtol=0)


def test_irradiance_matches_cosine_integral():
    generator = torch.Generator().manual_seed(0)
    coefficients = torch.randn(9, 2, generator=generator, dtype=torch.float64)
    directions, weights = _sphere_quadrature(300)
    radiance = sh_basis(directions) @ coefficients  # [N, 2]
    normals = torch.nn.functional.normalize(
        torch.randn(6, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    cosine = (normals @ directions.T).clamp_min(0)  # [6, N]
    expected = cosine @ (radiance * weights[:, None])
    torch.testing.assert_close(sh_irradiance(normals, coefficients), expected, atol=5e-3, rtol=5e-3)


def test_constant_environment_shades_albedo():
    lighting = Lighting.constant(1.0)
    normals = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    albedo = torch.rand(50, 3)
    torch.testing.assert_close(lambertian(albedo, normals, lighting), albedo, atol=1e-5, rtol=1e-5)


def test_directional_light_follows_cosine_law():
    lighting = Lighting(
        sh_coefficients=torch.zeros(9, 3),
        directional=[DirectionalLight(torch.tensor([0.0, 0.0, 2.0]), torch.tensor([math.pi] * 3))],
    )
    angles = torch.tensor([0.0, 0.5, 1.0, 2.0])
    normals = torch.stack([torch.sin(angles), torch.zeros(4), torch.cos(angles)], -1)
    radiance = lambertian(torch.ones(4, 3), normals, lighting)[:, 0]
    torch.testing.assert_close(radiance, torch.cos(angles).clamp_min(0))


def test_bad_sh_shape_is_rejected():
    with pytest.raises(ReconError, match=r"sh_coefficients: expected shape \[9, C\], got \(4, 3\)"):
        sh_irradiance(torch.zeros(2, 3), torch.zeros(4, 3))


def test_point_light_follows_inverse_square_and_emitter_cosine():
    from recon.render.shading import PointLight

    lighting = Lighting(
        sh_coefficients=torch.zeros(9, 1),
        points=[PointLight(torch.tensor([0.0, 0.0, 2.0]), torch.tensor([math.pi]))],
    )
    positions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 1.0]])
    normals = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    radiance = lambertian(torch.ones(3, 1), normals, lighting, positions)[:, 0]
    expected = torch.tensor([1.0, 0.25, (1 / math.sqrt(2)) / 2.0])
    torch.testing.assert_close(radiance, expected, atol=1e-5, rtol=1e-5)
    # A one-sided emitter facing away lights nothing.
    lighting.points[0].emitter_normal = torch.tensor([0.0, 0.0, 1.0])
    assert float(lambertian(torch.ones(3, 1), normals, lighting, positions).abs().max()) == 0.0
    with pytest.raises(ReconError, match="point lights need the shaded positions"):
        lambertian(torch.ones(3, 1), normals, lighting)
