"""The metallic-roughness BRDF, its split-sum table and the pre-filtered environment, against
dense numerical integration; gradients against finite differences; the Lambertian limit."""

from __future__ import annotations

import math

import pytest
import torch

from recon.render.brdf import lookup_split_sum, specular_brdf, split_sum_table
from recon.render.environment import (
    latlong_directions,
    prefilter_environment,
    project_to_sh,
    sample_latlong,
)
from recon.render.pbr import PbrMaterial, pbr_shade
from recon.render.shading import DirectionalLight, Lighting, lambertian

NORMAL = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _viewer(n_dot_v: float) -> torch.Tensor:
    return torch.tensor([math.sqrt(1 - n_dot_v**2), 0.0, n_dot_v], dtype=torch.float64)


def _half_vector_grid(alpha: float, theta_count: int = 1500, phi_count: int = 128):
    """Midpoint quadrature over half vectors around +z: directions [T*P, 3] and weights
    dOmega_h. The polar grid is dense near the pole (theta = atan(alpha tan(pi/2 u))-like
    spacing through a substitution), so narrow lobes are resolved."""
    # Substitution theta = atan(alpha * tan(pi/2 s)): uniform s concentrates nodes in the lobe.
    s = (torch.arange(theta_count, dtype=torch.float64) + 0.5) / theta_count
    scale = max(alpha, 0.05)
    theta = torch.atan(scale * torch.tan(math.pi / 2 * s))
    dtheta_ds = (
        scale
        * (math.pi / 2)
        / (torch.cos(math.pi / 2 * s) ** 2 + (scale * torch.sin(math.pi / 2 * s)) ** 2)
    )
    phi = (torch.arange(phi_count, dtype=torch.float64) + 0.5) * 2 * math.pi / phi_count
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    weights = torch.sin(theta) * (dtheta_ds[:, None] / theta_count) * (2 * math.pi / phi_count)
    half = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)],
        -1,
    )
    return half.reshape(-1, 3), weights.reshape(-1)


def _specular_albedo(n_dot_v: float, roughness: float, f0: float) -> float:
    """integral f_s(l, v) (n.l) dl by quadrature over half vectors (dl = 4 (v.h) dh)."""
    viewer = _viewer(n_dot_v)
    half, weights = _half_vector_grid(roughness**2)
    v_dot_h = half @ viewer
    to_light = 2 * v_dot_h[:, None] * half - viewer
    count = half.shape[0]
    value = specular_brdf(
        NORMAL.expand(count, 3),
        to_light,
        viewer.expand(count, 3),
        torch.full((count, 1), roughness, dtype=torch.float64),
        torch.full((count, 1), f0, dtype=torch.float64),
    )[:, 0]
    jacobian = 4 * v_dot_h.clamp_min(0)
    return float((value * to_light[:, 2].clamp_min(0) * jacobian * weights).sum())


@pytest.mark.parametrize("roughness", [0.1, 0.3, 1.0])
@pytest.mark.parametrize("n_dot_v", [0.05, 0.4, 1.0])
def test_white_furnace_specular_lobe_never_creates_energy(n_dot_v, roughness):
    albedo = _specular_albedo(n_dot_v, roughness, f0=1.0)
    assert albedo <= 1.0 + 2e-3
    # Single-scattering Smith loses energy only at high roughness or grazing views.
    if roughness <= 0.3 and n_dot_v >= 0.3:
        assert albedo > 0.9


def test_white_furnace_split_sum_material_reflects_at_most_the_light():
    """A white (or metallic) material under a constant unit environment: outgoing <= 1 with
    the energy-weighted diffuse lobe."""
    environment = prefilter_environment(torch.ones(8, 16, 3, dtype=torch.float64), 4)
    grid = torch.linspace(0, 1, 11, dtype=torch.float64)
    n_dot_v, roughness, metalness = torch.meshgrid(grid.clamp_min(0.02), grid, grid, indexing="ij")
    n_dot_v, roughness, metalness = (t.reshape(-1, 1) for t in (n_dot_v, roughness, metalness))
    count = n_dot_v.shape[0]
    viewer = torch.cat([torch.sqrt(1 - n_dot_v**2), torch.zeros_like(n_dot_v), n_dot_v], -1)
    material = PbrMaterial(
        torch.ones(count, 3, dtype=torch.float64),
        roughness,
        metalness,
        diffuse_weighting="specular_albedo",
    )
    radiance = pbr_shade(material, NORMAL.expand(count, 3), viewer, environment)
    assert float(radiance.max()) <= 1.0 + 1e-3
    # Not black either: rough metals lose up to ~70 % to the single-scattering Smith model.
    assert float(radiance.min()) > 0.25


@pytest.mark.parametrize(
    ("n_dot_v", "roughness"), [(0.13, 0.23), (0.41, 0.37), (0.66, 0.52), (0.93, 0.81), (0.5, 1.0)]
)
def test_split_sum_table_matches_numerical_integration(n_dot_v, roughness):
    scale_bias = lookup_split_sum(
        torch.tensor([[n_dot_v]], dtype=torch.float64),
        torch.tensor([[roughness]], dtype=torch.float64),
    )[0]
    # F0 = 0 isolates the Fresnel bias B, F0 = 1 the sum A + B.
    assert float(scale_bias[1]) == pytest.approx(
        _specular_albedo(n_dot_v, roughness, 0.0), abs=0.01
    )
    assert float(scale_bias.sum()) == pytest.approx(
        _specular_albedo(n_dot_v, roughness, 1.0), abs=0.015
    )


def test_split_sum_table_matches_random_monte_carlo():
    """Plain uniform-hemisphere Monte Carlo (seeded, no importance sampling) at a rough lobe."""
    generator = torch.Generator().manual_seed(0)
    count = 400_000
    u1, u2 = torch.rand(2, count, generator=generator, dtype=torch.float64)
    cos_theta = u1
    sin_theta = torch.sqrt(1 - cos_theta**2)
    phi = 2 * math.pi * u2
    to_light = torch.stack([sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta], -1)
    n_dot_v, roughness = 0.6, 0.7
    value = specular_brdf(
        NORMAL.expand(count, 3),
        to_light,
        _viewer(n_dot_v).expand(count, 3),
        torch.full((count, 1), roughness, dtype=torch.float64),
        torch.ones(count, 1, dtype=torch.float64),
    )[:, 0]
    estimate = float((value * cos_theta).mean() * 2 * math.pi)
    table = lookup_split_sum(
        torch.tensor([[n_dot_v]], dtype=torch.float64),
        torch.tensor([[roughness]], dtype=torch.float64),
    )
    assert float(table.sum()) == pytest.approx(estimate, abs=0.01)


def test_split_sum_table_is_cached_per_device_and_dtype():
    assert split_sum_table("cpu", torch.float32) is split_sum_table("cpu", torch.float32)
    assert split_sum_table("cpu", torch.float64).dtype == torch.float64


def _analytic_environment(directions: torch.Tensor) -> torch.Tensor:
    """A smooth radiance field [..., 3] of unit directions (a brighter sky, a reddish side)."""
    x, y, z = directions.unbind(-1)
    return torch.stack([1 + 0.6 * y + 0.4 * x, 1 + 0.6 * y - 0.2 * z, 0.8 + 0.5 * y * y], -1)


@pytest.mark.parametrize("roughness", [0.25, 0.5, 0.75, 1.0])
def test_prefiltered_environment_matches_brute_force_convolution(roughness):
    """The pre-filtered level (a 16 x 32 map) against a dense quadrature of the continuous
    environment: integral L(l) D(h) (r.l) dl / integral D(h) (r.l) dl with n = v = r."""
    directions, _ = latlong_directions(16, 32, dtype=torch.float64)
    environment = prefilter_environment(_analytic_environment(directions), level_count=4)
    generator = torch.Generator().manual_seed(1)
    outputs = torch.nn.functional.normalize(
        torch.randn(6, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    found = environment.specular(outputs, torch.full((6, 1), roughness, dtype=torch.float64))
    half, weights = _half_vector_grid(roughness**2, theta_count=600, phi_count=128)
    for direction, value in zip(outputs, found, strict=True):
        # A frame whose z axis is the output direction.
        helper = torch.tensor([1.0, 0, 0], dtype=torch.float64)
        if abs(float(direction[0])) > 0.9:
            helper = torch.tensor([0, 1.0, 0], dtype=torch.float64)
        tangent = torch.nn.functional.normalize(torch.linalg.cross(helper, direction), dim=0)
        frame = torch.stack([tangent, torch.linalg.cross(direction, tangent), direction], -1)
        world_half = half @ frame.T
        n_dot_h = world_half @ direction
        to_light = 2 * n_dot_h[:, None] * world_half - direction
        cosine = (to_light @ direction).clamp_min(0)
        alpha = roughness**2
        distribution = alpha**2 / (math.pi * (n_dot_h**2 * (alpha**2 - 1) + 1) ** 2)
        weight = distribution * cosine * 4 * n_dot_h * weights
        expected = (weight[:, None] * _analytic_environment(to_light)).sum(0) / weight.sum()
        torch.testing.assert_close(value, expected, rtol=0.03, atol=0.0)


def test_prefiltered_environment_keeps_a_constant_and_the_map_at_roughness_zero():
    environment = prefilter_environment(torch.full((8, 16, 3), 0.7, dtype=torch.float64), 4)
    directions = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    roughness = torch.rand(50, 1, dtype=torch.float64)
    torch.testing.assert_close(
        environment.specular(directions, roughness), torch.full((50, 3), 0.7, dtype=torch.float64)
    )
    texel_map = torch.rand(8, 16, 3, dtype=torch.float64)
    centres, _ = latlong_directions(8, 16, dtype=torch.float64)
    torch.testing.assert_close(sample_latlong(texel_map, centres), texel_map)


def _gradient_scene():
    generator = torch.Generator().manual_seed(3)
    count = 5
    normals = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    to_viewer = torch.nn.functional.normalize(
        normals + 0.5 * torch.randn(count, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    # One colour channel keeps gradcheck's perturbation count small.
    base = torch.rand(count, 1, generator=generator, dtype=torch.float64)
    # Away from the roughness knots (0, 0.25, ...) where the level blend has kinks.
    roughness = torch.tensor([[0.11], [0.33], [0.58], [0.71], [0.92]], dtype=torch.float64)
    metalness = torch.rand(count, 1, generator=generator, dtype=torch.float64)
    environment = 0.2 + torch.rand(4, 8, 1, generator=generator, dtype=torch.float64)
    return normals, to_viewer, base, roughness, metalness, environment


def test_gradients_match_finite_differences():
    normals, to_viewer, base, roughness, metalness, environment = _gradient_scene()

    def shade(base, roughness, metalness, environment):
        light = DirectionalLight(
            torch.tensor([0.3, 0.8, 0.5], dtype=torch.float64),
            torch.tensor([0.9], dtype=torch.float64),
        )
        material = PbrMaterial(base, roughness, metalness)
        return pbr_shade(
            material, normals, to_viewer, prefilter_environment(environment, 4), [light]
        )

    inputs = tuple(
        t.clone().requires_grad_(True) for t in (base, roughness, metalness, environment)
    )
    assert torch.autograd.gradcheck(shade, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)
    # Every input really receives gradient (the environment's texels through the pre-filter).
    shade(*inputs).sum().backward()
    for tensor in inputs:
        assert tensor.grad is not None and float(tensor.grad.abs().sum()) > 0


def test_rough_dielectric_without_specular_is_close_to_lambertian():
    directions, _ = latlong_directions(16, 32, dtype=torch.float64)
    environment_map = _analytic_environment(directions)
    environment = prefilter_environment(environment_map, 4)
    generator = torch.Generator().manual_seed(4)
    normals = torch.nn.functional.normalize(
        torch.randn(200, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    to_viewer = torch.nn.functional.normalize(
        normals + 0.3 * torch.randn(200, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    base = 0.2 + 0.8 * torch.rand(200, 3, generator=generator, dtype=torch.float64)
    ones = torch.ones(200, 1, dtype=torch.float64)
    material = PbrMaterial(base, ones, 0 * ones, specular_level=0.0)
    found = pbr_shade(material, normals, to_viewer, environment)
    lighting = Lighting(sh_coefficients=project_to_sh(environment_map))
    expected = lambertian(base, normals, lighting)
    relative = ((found - expected) / expected).abs()
    assert float(relative.mean()) < 0.05
    assert float(relative.max()) < 0.25


def test_shading_follows_the_input_device(device):
    """The table, the pre-filter weights and the shading live on the inputs' device and agree
    with the CPU result."""
    normals, to_viewer, base, roughness, metalness, environment = (
        tensor.float() for tensor in _gradient_scene()
    )

    def shade(on):
        material = PbrMaterial(base.to(on), roughness.to(on), metalness.to(on))
        prefiltered = prefilter_environment(environment.to(on), 4)
        return pbr_shade(material, normals.to(on), to_viewer.to(on), prefiltered)

    found = shade(device)
    assert found.device.type == device.type
    torch.testing.assert_close(found.cpu(), shade(torch.device("cpu")), rtol=1e-4, atol=1e-5)
