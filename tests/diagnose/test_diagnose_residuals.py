"""Where the sim-to-real gap lies: the gap, the noise floor, the domain scores and figures.

Most tests need no run folder: a textured torus is rendered by recon's Renderer as the fitted
scene ("rendered"), and the "observed" images are that render with one known effect applied by
plain torch ops. Each domain must score high for the effect it is meant to catch, stay low for
the others, and stay near zero for white noise however many bins it has.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from data_synth.shapes import torus
from recon.camera import orbit_cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose import how_far
from recon.diagnose.data import DiagnosisData, build_diagnosis_data
from recon.diagnose.domains import DOMAINS, where_analysis
from recon.diagnose.figures import where_figures, worst_views_figure
from recon.diagnose.gap import gap_summary, noise_floor, relight_gap
from recon.effects import make_effect
from recon.effects.light_transport import view_directions
from recon.errors import ReconError
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import DirectionalLight, Lighting

REPO_ROOT = Path(__file__).resolve().parents[2]
SIZE = 48
SETTINGS = DiagnoseConfig()
VIEWS = 6
SUN_DIRECTION = (0.4, 0.8, 0.5)
# A little sensor noise on every "observed" image, so no test relies on an exact residual.
BACKGROUND_NOISE = 0.003
# Domains that localise an effect; frequency only says structured or white.
LOCATING = [domain for domain in DOMAINS if domain != "frequency"]


class Scene:
    """The 'fitted' scene: a textured torus under a sun, and its render from VIEWS cameras."""

    def __init__(self) -> None:
        mesh = torus(resolution=24)
        steps = torch.linspace(0, 1, 64)
        u, v = torch.meshgrid(steps, steps, indexing="xy")
        # A smooth pattern: texture edges exist but are not sharper than a pixel or two.
        pattern = 0.5 + 0.35 * torch.sin(2 * math.pi * 3 * u) * torch.sin(2 * math.pi * 2 * v)
        mesh.texture = torch.stack([pattern, 0.8 * pattern + 0.1, 0.6 * (1 - pattern) + 0.2], -1)
        self.mesh = mesh
        self.cameras = orbit_cameras(
            VIEWS, (SIZE, SIZE), distance=2.6, fov_x_deg=40, elevation_deg=30
        )
        self.lighting = sun_lighting(1.0)
        self.output = render(self)

    def data(self, observed: torch.Tensor, alpha: torch.Tensor | None = None) -> DiagnosisData:
        alpha = self.output.alpha if alpha is None else alpha
        return build_diagnosis_data(
            observed, alpha, self.output, self.cameras, self.lighting, self.mesh
        )


def sun_lighting(sun_scale: float) -> Lighting:
    lighting = Lighting.constant(0.35)
    irradiance = torch.tensor([1.6, 1.5, 1.4]) * sun_scale
    lighting.directional = [DirectionalLight(torch.tensor(SUN_DIRECTION), irradiance)]
    return lighting


def render(scene: Scene, lighting: Lighting | None = None) -> RenderOutput:
    lighting = scene.lighting if lighting is None else lighting
    return Renderer(texture_filter="linear").render(scene.mesh, scene.cameras, lighting)


@pytest.fixture(scope="module")
def scene() -> Scene:
    torch.set_num_threads(1)
    return Scene()


def noisy(image: torch.Tensor, sigma: float = BACKGROUND_NOISE, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return image + sigma * torch.randn(image.shape, generator=generator)


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """[B, H, W, C] blurred by a separable Gaussian (zero padding, like a lens on black)."""
    radius = math.ceil(3 * sigma)
    offsets = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-(offsets**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    planes = image.permute(0, 3, 1, 2)
    channels = planes.shape[1]
    horizontal = kernel.view(1, 1, 1, -1).repeat(channels, 1, 1, 1)
    vertical = kernel.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)
    planes = torch.nn.functional.conv2d(planes, horizontal, padding=(0, radius), groups=channels)
    planes = torch.nn.functional.conv2d(planes, vertical, padding=(radius, 0), groups=channels)
    return planes.permute(0, 2, 3, 1)


def radial_vignetting(height: int, width: int, strength: float = 0.6) -> torch.Tensor:
    """[1, H, W, 1] falloff 1 - strength r^2 (r = 1 at the image corner)."""
    rows, columns = torch.meshgrid(
        torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij"
    )
    radius_squared = ((columns - width / 2) ** 2 + (rows - height / 2) ** 2) / (
        (width / 2) ** 2 + (height / 2) ** 2
    )
    return (1 - strength * radius_squared)[None, :, :, None]


def scores(analysis: dict) -> dict[str, float]:
    return {domain: analysis[domain]["score"] for domain in DOMAINS}


# --------------------------------------------------------------------------------------------
# the data bundle and the gap
# --------------------------------------------------------------------------------------------


def test_region_is_the_object_plus_a_band(scene):
    data = scene.data(scene.output.color)
    covered = scene.output.alpha[..., 0] > 0.5
    region = data.region[..., 0] > 0.5
    assert bool(region[covered].all())
    # Chebyshev distance to the object: <= 3 pixels inside the band, farther outside it.
    distance = torch.full_like(covered, False)
    grown = covered.float()[:, None]
    for band in range(1, 6):
        grown = torch.nn.functional.max_pool2d(grown, 3, stride=1, padding=1)
        ring = (grown[:, 0] > 0.5) & ~distance & ~covered
        if band <= 3:
            assert bool(region[ring].all())
        else:
            assert not bool(region[ring].any())
        distance |= ring
    uv = data.texel_uv
    assert bool((uv[data.rendered_mask] >= 0).all()) and bool((uv[data.rendered_mask] <= 1).all())
    assert bool((uv[~data.rendered_mask] == -1).all())


def test_diagnosis_data_checks_shapes(scene):
    data = scene.data(scene.output.color)
    with pytest.raises(ReconError, match="diagnosis_data.rendered"):
        DiagnosisData(
            observed=data.observed,
            rendered=data.rendered[:, :-1],
            observed_alpha=data.observed_alpha,
            rendered_alpha=data.rendered_alpha,
            region=data.region,
            normals=data.normals,
            depth=data.depth,
            texel_uv=data.texel_uv,
            triangle_id=data.triangle_id,
            cameras=data.cameras,
            lighting=data.lighting,
            mesh=data.mesh,
        )


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


def test_relight_heldout_gap_fixes_the_gauge_through_a_response_curve(scene, monkeypatch):
    # The camera's curve x^0.6 on every relight view; the refit's albedo is 0.8 of the truth
    # (the gauge) and its module holds the curve. A texture gain g becomes g^0.6 after the
    # curve: one least-squares step leaves 0.8^0.4 = 0.91 of the gain missing, the secant
    # steps take it to the truth's error.
    curve = make_effect("response_curve")
    curve.hold_exponent(0.6)
    with torch.no_grad():
        observed = noisy(curve(scene.output.color, scene.output.alpha)[0], 0.002, seed=7)
    data = scene.data(observed)
    darker = replace(scene.mesh, texture=scene.mesh.texture * 0.8)
    truth_error = how_far.relight_heldout_gap(data, scene.mesh, [curve], SETTINGS)
    gauged_error = how_far.relight_heldout_gap(data, darker, [curve], SETTINGS)
    assert gauged_error == pytest.approx(truth_error, rel=0.01)
    assert (
        how_far.relight_heldout_gap(data, darker, [], SETTINGS) > 4 * gauged_error
    )  # the curve unmodelled
    monkeypatch.setattr(how_far, "GAUGE_ITERATIONS", 1)
    assert how_far.relight_heldout_gap(data, darker, [curve], SETTINGS) > 2 * gauged_error


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


def test_where_figures_are_written(scene, tmp_path):
    data = scene.data(noisy(scene.output.color * radial_vignetting(SIZE, SIZE)))
    paths = where_figures(data, where_analysis(data), tmp_path / "figures")
    assert set(paths) == set(DOMAINS) | {"worst_views"}
    for path in paths.values():
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 1000
    # Atomic writes leave no temporary files behind.
    assert sorted(tmp_path.joinpath("figures").iterdir()) == sorted(paths.values())
    single = worst_views_figure(data, tmp_path / "worst.png", count=1)
    assert single.stat().st_size > 1000


def test_covered_radius_is_the_farthest_object_pixel():
    """covered_radius: the largest normalised radius among covered pixels; a full frame reaches
    the corners (radius about 1), a centred square of half the side about half of that."""
    from types import SimpleNamespace

    from recon.camera import orbit_cameras
    from recon.diagnose.diagnose import covered_radius

    size = 32
    cameras = orbit_cameras(1, (size, size))
    alpha = torch.zeros(1, size, size, 1)
    alpha[:, 8:24, 8:24] = 1.0
    data = SimpleNamespace(
        observed=torch.zeros(1, size, size, 3), observed_alpha=alpha, cameras=cameras
    )
    half = covered_radius(data)
    assert abs(half - (7.5 / 16)) < 0.02, half  # the square's corner pixel centre
    data.observed_alpha = torch.ones(1, size, size, 1)
    assert covered_radius(data) > 0.95
    data.observed_alpha = torch.zeros(1, size, size, 1)
    assert covered_radius(data) == 0.0
