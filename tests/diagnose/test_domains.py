"""Where the gap lies: each domain scores high for the effect it is meant to catch, low for the
others, and near zero for white noise however many bins it has."""

from __future__ import annotations

import json

import pytest
import torch
from diagnose_where_scene import (
    LOCATING,
    SIZE,
    SUN_DIRECTION,
    VIEWS,
    gaussian_blur,
    make_scene,
    noisy,
    radial_vignetting,
    scores,
)

from recon.diagnose.domains import DOMAINS, where_analysis
from recon.effects.light_transport import view_directions


@pytest.fixture(scope="module")
def scene():
    return make_scene()


# --------------------------------------------------------------------------------------------
# domain scores
# --------------------------------------------------------------------------------------------


def test_white_noise_scores_near_zero_however_many_bins(scene):
    data = scene.data(noisy(scene.output.color, 0.02, seed=5))
    analysis = where_analysis(data, grid_size=32, texel_grid_size=64)
    assert set(analysis) == set(DOMAINS)
    for domain in DOMAINS:
        assert set(analysis[domain]) == {"score", "score_in_sample", "summary"}
        assert analysis[domain]["score"] < 0.05, domain
    # Many bins fit noise in sample; the split-half score is not fooled.
    assert analysis["surface"]["score_in_sample"] > 0.1
    assert analysis["image_position"]["score_in_sample"] > 0.03
    autocorrelation = analysis["frequency"]["summary"]["autocorrelation"]
    assert all(abs(value) < 0.1 for value in autocorrelation.values())
    power = [value for value in analysis["frequency"]["summary"]["power"] if value is not None]
    assert 0.7 < min(power) and max(power) < 1.3  # flat spectrum


def test_per_view_gain_lights_up_the_view_domain(scene):
    """Exposure and white balance per view (per channel)."""
    gains = torch.tensor(
        [
            [1.15, 1.1, 1.05],
            [0.9, 0.9, 0.9],
            [1.05, 1.0, 0.95],
            [0.85, 0.9, 0.95],
            [1.1, 1.1, 1.1],
            [0.95, 1.0, 1.05],
        ]
    )
    observed = noisy(scene.output.color * gains[:, None, None, :])
    analysis = where_analysis(scene.data(observed))
    result = scores(analysis)
    assert result["view"] > 0.8
    assert result["image_position"] < 0.15
    assert result["intensity"] < 0.15
    recovered = torch.tensor(analysis["view"]["summary"]["gain"], dtype=torch.float64)
    assert torch.allclose(recovered, gains.double(), atol=0.02)


def test_vignetting_lights_up_image_position(scene):
    falloff = radial_vignetting(SIZE, SIZE)
    analysis = where_analysis(scene.data(noisy(scene.output.color * falloff)))
    result = scores(analysis)
    assert result["image_position"] > 0.6
    assert result["image_position"] == max(result[domain] for domain in LOCATING)
    # The radial gain profile falls from the centre outwards.
    ratio = [row for row in analysis["image_position"]["summary"]["radial_ratio"] if row[1]]
    assert ratio[0][1] > ratio[-1][1] + 0.1


def test_gamma_lights_up_intensity_only(scene):
    observed = noisy(scene.output.color.clamp_min(0) ** 1.3)
    analysis = where_analysis(scene.data(observed))
    result = scores(analysis)
    assert result["intensity"] > 0.8
    for domain in ("image_position", "surface", "view", "light_geometry", "edges"):
        assert result[domain] < 0.15, domain
    gamma = analysis["intensity"]["summary"]["gamma"]
    assert gamma == pytest.approx([1.3] * 3, abs=0.08)


def test_blur_lights_up_edges(scene):
    observed = noisy(gaussian_blur(scene.output.color, 1.0))
    alpha = gaussian_blur(scene.output.alpha, 1.0)
    analysis = where_analysis(scene.data(observed, alpha))
    result = scores(analysis)
    assert result["edges"] > 0.6
    assert result["edges"] == max(result[domain] for domain in LOCATING)
    # Darker just inside the silhouette, brighter just outside.
    profile = analysis["edges"]["summary"]["distance_mean_residual"]
    bins = analysis["edges"]["summary"]["distance_bins"]
    assert profile[bins.index(-1)][1] < 0 < profile[bins.index(1)][1]


def test_sub_pixel_shift_is_found_per_view(scene):
    """A misregistered camera: every view sampled half a pixel to the right."""
    batch = VIEWS
    theta = torch.tensor([[1.0, 0.0, 2 * 0.5 / SIZE], [0.0, 1.0, 0.0]]).repeat(batch, 1, 1)
    grid = torch.nn.functional.affine_grid(theta, (batch, 4, SIZE, SIZE), align_corners=False)
    image = torch.cat([scene.output.color, scene.output.alpha], -1).permute(0, 3, 1, 2)
    shifted = torch.nn.functional.grid_sample(image, grid, align_corners=False)
    shifted = shifted.permute(0, 2, 3, 1)
    analysis = where_analysis(scene.data(noisy(shifted[..., :3]), shifted[..., 3:]))
    assert scores(analysis)["edges"] > 0.5
    shifts = torch.tensor(analysis["edges"]["summary"]["shift_pixels"], dtype=torch.float64)
    assert torch.allclose(
        shifts, torch.tensor([[0.5, 0.0]] * batch, dtype=torch.float64), atol=0.05
    )


def test_specular_lights_up_light_geometry(scene):
    direction = torch.nn.functional.normalize(torch.tensor(SUN_DIRECTION), dim=0)
    to_camera = view_directions(scene.cameras, SIZE, SIZE, scene.output.normals)
    half_vector = torch.nn.functional.normalize(direction + to_camera, dim=-1)
    cosine = (scene.output.normals * half_vector).sum(-1, keepdim=True).clamp_min(0)
    highlight = 0.4 * cosine**40 * scene.output.mask
    analysis = where_analysis(scene.data(noisy(scene.output.color + highlight)))
    result = scores(analysis)
    assert result["light_geometry"] > 0.6
    assert result["light_geometry"] == max(result[domain] for domain in LOCATING)
    # Fixed on the light and the view, not on the surface: it moves across texels.
    assert analysis["surface"]["summary"]["view_dependent_score"] > 0.2


def test_where_analysis_is_json_ready(scene):
    analysis = where_analysis(scene.data(noisy(scene.output.color * 1.05)))
    json.dumps(analysis, allow_nan=False)
