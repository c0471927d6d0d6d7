"""Full-lobe specular shading (recon.render.lobe_sampling): against a brute-force integral of the
GGX BRDF over a small environment, the split-sum table under a white furnace, and gradients
against finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from recon.render.brdf import integrate_split_sum, specular_brdf
from recon.render.environment import latlong_directions, prefilter_environment, sample_latlong
from recon.render.lobe_sampling import (
    SampledEnvironment,
    lattice_points,
    sample_visible_normals,
    tangent_frame,
)
from recon.render.pbr import PbrMaterial, pbr_shade


def _environment() -> torch.Tensor:
    """A small lat-long map [8, 16, 3] with a bright texel (a light) over a dim random room."""
    generator = torch.Generator().manual_seed(0)
    environment = torch.rand(8, 16, 3, generator=generator, dtype=torch.float64) * 0.5
    environment[2, 3] = torch.tensor([8.0, 6.0, 4.0], dtype=torch.float64)
    return environment


def _frame(n_dot_v: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A tilted unit normal [1, 3] and a viewer [1, 3] at the given n.v."""
    normal = torch.tensor([[0.3, 0.8, 0.52]], dtype=torch.float64)
    normal = normal / normal.norm()
    side = torch.linalg.cross(normal, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    side = side / side.norm()
    return normal, n_dot_v * normal + math.sqrt(1 - n_dot_v**2) * side


def _brute_force(environment, normal, viewer, roughness, f0) -> torch.Tensor:
    """integral f_s(l, v) L(l) (n.l) dl [C] by a dense midpoint rule over the sphere, L the
    bilinear look-up the sampled estimator makes too."""
    directions, solid_angle = latlong_directions(384, 768, dtype=torch.float64)
    directions, solid_angle = directions.reshape(-1, 3), solid_angle.reshape(-1)
    count = directions.shape[0]
    value = specular_brdf(
        normal.expand(count, 3),
        directions,
        viewer.expand(count, 3),
        torch.full((count, 1), roughness, dtype=torch.float64),
        f0.expand(count, 3),
    )
    cosine = (directions @ normal[0]).clamp_min(0)
    radiance = sample_latlong(environment, directions)
    return (value * radiance * (cosine * solid_angle)[:, None]).sum(0)


@pytest.mark.parametrize("n_dot_v, roughness", [(0.9, 0.5), (0.3, 0.5), (0.6, 0.3), (0.2, 0.7)])
def test_sampled_lobe_matches_brute_force_integral(n_dot_v, roughness):
    environment = _environment()
    normal, viewer = _frame(n_dot_v)
    f0 = torch.tensor([[0.04, 0.5, 0.9]], dtype=torch.float64)
    rough = torch.tensor([[roughness]], dtype=torch.float64)
    reference = _brute_force(environment, normal, viewer, roughness, f0)
    prefiltered = prefilter_environment(environment, 6)
    dense = SampledEnvironment(prefiltered, 1024, 0.0).specular_lobe(normal, viewer, rough, f0)
    torch.testing.assert_close(dense[0], reference, rtol=0.01, atol=1e-4)
    # A few filtered samples (what a fit uses): a few percent.
    few = SampledEnvironment(prefiltered, 64, 0.5).specular_lobe(normal, viewer, rough, f0)
    torch.testing.assert_close(few[0], reference, rtol=0.06, atol=1e-3)


@pytest.mark.parametrize("n_dot_v", [0.15, 0.5, 0.95])
@pytest.mark.parametrize("roughness", [0.2, 0.6])
def test_white_furnace_matches_split_sum_table(n_dot_v, roughness):
    """Under a uniform white light the lobe integral is the directional albedo F0 A + B."""
    environment = torch.ones(8, 16, 3, dtype=torch.float64)
    normal, viewer = _frame(n_dot_v)
    f0 = torch.tensor([[0.04, 0.3, 1.0]], dtype=torch.float64)
    sampled = SampledEnvironment(prefilter_environment(environment, 4), 512, 0.5).specular_lobe(
        normal, viewer, torch.tensor([[roughness]], dtype=torch.float64), f0
    )
    scale, bias = integrate_split_sum(
        torch.tensor(n_dot_v, dtype=torch.float64),
        torch.tensor(roughness, dtype=torch.float64),
        4096,
    ).unbind(-1)
    torch.testing.assert_close(sampled[0], f0[0] * scale + bias, rtol=0.01, atol=1e-4)


def test_visible_normals_face_the_viewer_and_spread_with_roughness():
    viewer = torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.0, 1.0]], dtype=torch.float64)
    points = lattice_points(256, torch.float64)
    spreads = []
    for alpha in (0.05, 0.3):
        half = sample_visible_normals(
            viewer, torch.full((2, 1), alpha, dtype=torch.float64), points
        )
        torch.testing.assert_close(half.norm(dim=-1), torch.ones(2, 256, dtype=torch.float64))
        assert bool((half[..., 2] >= 0).all())
        assert bool(((half * viewer[:, None]).sum(-1) >= -1e-9).all())
        spreads.append(float((1 - half[..., 2]).mean()))
    assert spreads[1] > 5 * spreads[0]


def test_tangent_frame_is_orthonormal():
    normals = torch.nn.functional.normalize(
        torch.randn(64, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64), dim=-1
    )
    tangent, bitangent = tangent_frame(normals)
    frame = torch.stack([tangent, bitangent, normals], dim=-2)
    identity = torch.eye(3, dtype=torch.float64).expand(64, 3, 3)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), identity)


def test_gradients_match_finite_differences():
    """Roughness, normal, viewer and map, unfiltered (the filtered look-up's level is
    detached: a filter choice, not part of the model); the map alone, filtered."""
    environment = _environment().requires_grad_(True)
    normal, viewer = _frame(0.6)
    normals = torch.cat([normal, viewer]).requires_grad_(True)
    viewers = torch.cat([viewer, normal]).requires_grad_(True)
    roughness = torch.tensor([[0.45], [0.6]], dtype=torch.float64, requires_grad=True)
    f0 = torch.tensor([[0.04, 0.5, 0.9]], dtype=torch.float64).expand(2, 3)
    offsets = torch.tensor([[0.1, 0.7], [0.4, 0.2]], dtype=torch.float64)

    def shade(environment, normals, viewers, roughness, filter_width=0.0):
        unit_normals = torch.nn.functional.normalize(normals, dim=-1)
        unit_viewers = torch.nn.functional.normalize(viewers, dim=-1)
        sampled = SampledEnvironment(
            prefilter_environment(environment, 4), 8, filter_width, offsets
        )
        return sampled.specular_lobe(unit_normals, unit_viewers, roughness, f0)

    assert torch.autograd.gradcheck(
        shade, (environment, normals, viewers, roughness), eps=1e-6, atol=1e-5, rtol=1e-3
    )
    assert torch.autograd.gradcheck(
        lambda environment: shade(environment, normals.detach(), viewers.detach(), roughness, 0.5),
        (environment,),
        eps=1e-6,
        atol=1e-5,
    )


def test_pbr_shade_takes_the_sampled_environment():
    """pbr_shade with a SampledEnvironment: the same diffuse term, the lobe integral as
    specular."""
    environment = _environment()
    normal, viewer = _frame(0.7)
    material = PbrMaterial(
        torch.tensor([[0.5, 0.4, 0.3]], dtype=torch.float64),
        torch.tensor([[0.4]], dtype=torch.float64),
        torch.tensor([[0.0]], dtype=torch.float64),
    )
    prefiltered = prefilter_environment(environment, 6)
    sampled = SampledEnvironment(prefiltered, 256, 0.5)
    shaded = pbr_shade(material, normal, viewer, sampled)
    diffuse = material.base_color / math.pi * prefiltered.irradiance(normal)
    specular = sampled.specular_lobe(normal, viewer, material.roughness, torch.full((1, 3), 0.04))
    torch.testing.assert_close(shaded, diffuse + specular.to(shaded.dtype))
