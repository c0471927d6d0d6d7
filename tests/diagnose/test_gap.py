"""The gap and the noise floor: RMSE/PSNR by hand, the relight gauge, the floor of white and
Poisson-Gaussian noise, smooth model error not counted as noise."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from diagnose_where_scene import VIEWS, make_scene, noisy

from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.gap import gap_summary, noise_floor, relight_gap
from recon.render.renderer import Renderer


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def test_gap_summary_matches_a_hand_computation(scene):
    observed = noisy(scene.output.color, 0.01, seed=3)
    observed[2] *= 1.3  # one clearly worse view
    data = scene.data(observed)
    gap = gap_summary(data)
    residual = (observed - scene.output.color).double()
    region = data.region[..., 0] > 0.5
    squares = [float((residual[view][region[view]] ** 2).mean()) for view in range(VIEWS)]
    assert gap["per_view_rmse"] == pytest.approx([math.sqrt(value) for value in squares])
    assert gap["per_view_psnr"] == pytest.approx([-10 * math.log10(value) for value in squares])
    pooled = float((residual[region] ** 2).mean())
    assert gap["rmse"] == pytest.approx(math.sqrt(pooled))
    assert gap["psnr"] == pytest.approx(-10 * math.log10(pooled))
    assert gap["pixels"] == int(region.sum())
    assert max(range(VIEWS), key=lambda view: gap["per_view_rmse"][view]) == 2


# --------------------------------------------------------------------------------------------
# the noise floor
# --------------------------------------------------------------------------------------------


def test_relight_gap_fixes_the_albedo_light_gauge(scene):
    # The fitted albedo is 0.8 of the truth (its light carried the rest): under the relight
    # light the render is 0.8 of the observation, and the gauge gain takes it back.
    darker = replace(scene.mesh, texture=scene.mesh.texture * 0.8)
    output = Renderer(texture_filter="linear").render(darker, scene.cameras, scene.lighting)
    observed = noisy(scene.output.color, 0.002, seed=5)
    data = build_diagnosis_data(
        observed, scene.output.alpha, output, scene.cameras, scene.lighting, darker
    )
    relit = relight_gap(data)
    assert relit["gauge_gain"] == pytest.approx([1.25] * 3, rel=0.01)
    assert relit["rmse"] < 0.004 < gap_summary(data)["rmse"]


@pytest.mark.parametrize("sigma", [0.01, 0.04])
def test_noise_floor_recovers_white_noise(scene, sigma):
    data = scene.data(noisy(scene.output.color, sigma, seed=1))
    floor = noise_floor(data)
    assert floor["floor_rmse"] == pytest.approx(sigma, rel=0.2)
    assert math.sqrt(floor["b"]) == pytest.approx(sigma, rel=0.2)
    # The gap is all noise: nothing above the floor (up to the estimate's error).
    assert floor["gap_above_floor"] < 0.35 * sigma


def test_noise_floor_recovers_poisson_gaussian_noise(scene):
    slope, offset = 0.004, 4e-4
    rendered = scene.output.color
    variance = slope * rendered.clamp_min(0) + offset
    generator = torch.Generator().manual_seed(2)
    observed = rendered + variance.sqrt() * torch.randn(rendered.shape, generator=generator)
    floor = noise_floor(scene.data(observed))
    assert floor["a"] == pytest.approx(slope, rel=0.25)
    assert floor["b"] == pytest.approx(offset, rel=0.5)


def test_noise_floor_ignores_smooth_model_error(scene):
    """A smooth gain error raises the gap, not the floor: the gap above it is that error."""
    sigma = 0.01
    data = scene.data(noisy(scene.output.color * 1.1, sigma, seed=4))
    floor = noise_floor(data)
    assert floor["floor_rmse"] == pytest.approx(sigma, rel=0.2)
    assert floor["gap_above_floor"] > 2 * sigma
