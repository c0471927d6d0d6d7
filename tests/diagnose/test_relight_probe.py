"""The relight split's response-curve probe: a power-law tone curve that the albedo absorbed under
the first light shows under the second, the probe recovers its exponent, and a linear camera
leaves nothing to find."""

from __future__ import annotations

from dataclasses import replace

import torch
from diagnose_scenes import directions_to_camera, patterned_torus

from recon.camera import orbit_cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.gauss_newton import GaussNewtonProblem
from recon.diagnose.relight_probe import (
    RelightResponse,
    exponent_interval,
    off_terminator,
    relight_response_probe,
    render_laplacian,
    unshadowed,
)
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SETTINGS = DiagnoseConfig()
ALLOWANCE = SETTINGS.decision.relight_allowance

VIEWS, SIZE = 6, 40


def lit_by(direction: list[float]) -> Lighting:
    ambient = Lighting.constant(0.3)
    sun = DirectionalLight(
        torch.nn.functional.normalize(torch.tensor(direction), dim=0), torch.full((3,), 1.5)
    )
    return Lighting(sh_coefficients=ambient.sh_coefficients, directional=[sun])


def highlight_of(output, cameras, direction: list[float], strength: float, shininess: float):
    """[B, H, W, 1] a white Blinn-Phong highlight strength max(0, n.h)^shininess of a sun toward
    direction, seen by cameras in output (its depth and normals)."""
    to_camera = directions_to_camera(output, cameras)
    to_light = torch.nn.functional.normalize(torch.tensor(direction), dim=0)
    halfway = torch.nn.functional.normalize(to_camera + to_light, dim=-1)
    lit = (output.normals * to_light).sum(-1) > 0
    lobe = (output.normals * halfway).sum(-1).clamp_min(0) ** shininess * lit
    return (strength * lobe)[..., None] * output.alpha


def relight_case(gamma: float, noise: float = 0.002, highlight: float = 0.0):
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.8 * p + 0.1, 0.6 * p + 0.2], base=0.45)
    cameras = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.2, fov_x_deg=50, elevation_deg=30)
    renderer = Renderer(texture_filter="linear")
    first, second = lit_by([0.5, 0.8, 0.4]), lit_by([-0.7, 0.5, -0.3])
    under_first = renderer.render(mesh, cameras, first)
    under_second = renderer.render(mesh, cameras, second)
    # The camera's curve, applied to what it saw; the fit kept f(a s1) as its radiance.
    fitted_first = under_first.color.clamp_min(0).pow(gamma)
    ratio = under_second.color / under_first.color.clamp_min(1e-3)
    fitted_second = torch.where(under_first.color > 1e-3, fitted_first * ratio, under_second.color)
    generator = torch.Generator().manual_seed(0)
    observed = under_second.color.clamp_min(0).pow(gamma) * under_second.alpha
    if highlight:
        # A glossy surface: the second light's highlight, which the diffuse fit lacks.
        sun = [-0.7, 0.5, -0.3]
        observed = observed + highlight_of(under_second, cameras, sun, highlight, 30.0)
    observed = observed + noise * torch.randn(observed.shape, generator=generator)
    relight = build_diagnosis_data(
        observed,
        under_second.alpha,
        replace(under_second, color=fitted_second),
        cameras,
        second,
        mesh,
    )
    return relight, fitted_first, first


def test_a_tone_curve_shows_under_the_second_light():
    relight, under_fitted, fitted_light = relight_case(gamma=0.6)
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert record["interval"][0] > 0.3, record
    assert abs(record["parameters"]["gamma"] - 0.6) < 0.05, record
    # The evidence: the compression 1 - gamma, its lower bound well clear of the allowance.
    assert record["specific"] and record["lower_bound"] > 0.3, record


def test_a_highlight_under_the_second_light_is_not_a_tone_curve():
    # Built to fool it: a glossy surface under the relight sun adds light that the diffuse fit
    # lacks where n.h peaks, bright pixels brighter, which a curve could bend toward.
    relight, under_fitted, fitted_light = relight_case(gamma=1.0, highlight=0.4)
    assert float((relight.residual.abs() > 0.05).float().mean()) > 0.01  # the highlight is there
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert record["expanding"] and record["interval"][0] < ALLOWANCE
    assert record["lower_bound"] < 0, record
    # Credited both ways, the highlight would read as a (expanding) curve.
    both_ways = replace(SETTINGS, relight_compressive_only=False)
    record = relight_response_probe(relight, under_fitted, fitted_light, both_ways)
    assert record["interval"][0] > ALLOWANCE, record
    assert record["lower_bound"] > ALLOWANCE, record


def test_a_compressive_curve_on_a_glossy_surface_is_still_found():
    relight, under_fitted, fitted_light = relight_case(gamma=0.6, highlight=0.2)
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert not record["expanding"], record
    assert record["interval"][0] > ALLOWANCE, record
    assert record["lower_bound"] > ALLOWANCE, record


def test_a_linear_camera_leaves_nothing():
    relight, under_fitted, fitted_light = relight_case(gamma=1.0)
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert abs(record["reduction"]) < 0.02, record
    assert abs(record["parameters"]["gamma"] - 1.0) < 0.05, record
    assert record["lower_bound"] < ALLOWANCE, record


def balance_case(ambient: float, sun_scale: float):
    """A linear camera; the fit lit the first views with the true sun times sun_scale over a
    constant ambient; its albedo absorbed the difference (a function of the normal). Returns
    the relight data, the fitted scene under the first light and that light."""
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.8 * p + 0.1, 0.6 * p + 0.2], base=0.45)
    cameras = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.2, fov_x_deg=50, elevation_deg=30)
    renderer = Renderer(texture_filter="linear")
    true_first, second = lit_by([0.5, 0.8, 0.4]), lit_by([-0.7, 0.5, -0.3])
    sun = true_first.directional[0]
    fitted_first = Lighting(
        sh_coefficients=Lighting.constant(ambient).sh_coefficients,
        directional=[DirectionalLight(sun.direction_to_light, sun_scale * sun.irradiance)],
    )
    under_true = renderer.render(mesh, cameras, true_first).color
    under_fitted = renderer.render(mesh, cameras, fitted_first).color
    under_second = renderer.render(mesh, cameras, second)
    # The fitted albedo is the true one times S_true1 / S_fit1, so the fitted scene renders the
    # first views exactly and the second ones off by that factor.
    absorbed = torch.where(under_fitted > 1e-3, under_true / under_fitted.clamp_min(1e-3), 1.0)
    generator = torch.Generator().manual_seed(0)
    observed = under_second.color + 0.002 * torch.randn(
        under_second.color.shape, generator=generator
    )
    relight = build_diagnosis_data(
        observed * under_second.alpha,
        under_second.alpha,
        replace(under_second, color=under_second.color * absorbed),
        cameras,
        second,
        mesh,
    )
    return relight, under_true, fitted_first


def test_a_wrong_sun_to_ambient_balance_is_not_a_tone_curve():
    """Too weak a sun and too much ambient: the ratio reads expanded, nothing credited."""
    record = relight_response_probe(*balance_case(0.45, 0.6), SETTINGS)
    assert record["interval"][0] < 0.01, record
    assert record["lower_bound"] < ALLOWANCE, record


def test_too_strong_a_fitted_sun_is_not_a_tone_curve():
    """Built to fool the exponent: too strong a sun and too little ambient make the predicted
    ratio too steep, which an exponent below 1 flattens (it reads 0.63). The exponent removes
    no held-out error beyond the fitted light's balance, so nothing is credited."""
    record = relight_response_probe(*balance_case(0.15, 1.4), SETTINGS)
    assert record["compression_interval"][0] > 0.2, record  # the exponent alone is fooled
    assert not record["specific"] and record["lower_bound"] <= 0, record


def test_cast_shadow_pixels_are_left_out():
    relight, _, fitted_light = relight_case(gamma=1.0)
    keep = unshadowed(relight, fitted_light, SETTINGS.relight_shadowed_share)
    covered = relight.triangle_id >= 0
    kept_share = float(keep[..., 0][covered].mean())
    # The torus hides part of each light from its inner side, not most of its surface.
    assert 0.3 < kept_share < 0.98, kept_share


def binomial_blur(images: torch.Tensor, passes: int) -> torch.Tensor:
    """[B, H, W, 3] images blurred by passes of the 3 x 3 binomial kernel (edges replicated)."""
    kernel = torch.tensor([1.0, 2.0, 1.0])
    kernel = (kernel[:, None] * kernel[None, :]) / 16
    planes = images.permute(0, 3, 1, 2).reshape(-1, 1, *images.shape[1:3])
    for _ in range(passes):
        padded = torch.nn.functional.pad(planes, (1, 1, 1, 1), mode="replicate")
        planes = torch.nn.functional.conv2d(padded, kernel[None, None])
    return planes.reshape(images.shape[0], 3, *images.shape[1:3]).permute(0, 2, 3, 1)


def test_a_blur_is_not_read_as_compression():
    """Built to fool it: a defocused relight split (no curve) smooths the observed shading
    ratio, which a lone exponent reads as compression; the blur's first-order change (the
    render's Laplacian, one strength per view) takes it."""
    relight, under_fitted, fitted_light = relight_case(gamma=1.0)
    blurred = replace(relight, observed=binomial_blur(relight.observed, 3))
    without = replace(SETTINGS, relight_blur_nuisance=False)
    fooled = relight_response_probe(blurred, under_fitted, fitted_light, without)
    record = relight_response_probe(blurred, under_fitted, fitted_light, SETTINGS)
    assert fooled["compression"] > 0.05, fooled
    assert record["compression"] < 0.5 * fooled["compression"], record
    assert record["lower_bound"] < ALLOWANCE, record
    # A curve behind the same blur is still found.
    relight, under_fitted, fitted_light = relight_case(gamma=0.8)
    blurred = replace(relight, observed=binomial_blur(relight.observed, 1))
    record = relight_response_probe(blurred, under_fitted, fitted_light, SETTINGS)
    assert record["lower_bound"] > 0.1 and abs(record["parameters"]["gamma"] - 0.8) < 0.03


def test_pixels_near_the_relight_terminator_are_left_out():
    relight, _, _ = relight_case(gamma=1.0)
    keep = off_terminator(relight, [-0.1, 0.3])[..., 0]
    direction = torch.nn.functional.normalize(torch.tensor([-0.7, 0.5, -0.3]), dim=0)
    cosine = (relight.normals * direction).sum(-1)
    covered = relight.triangle_id >= 0
    grazing = covered & (cosine > -0.1) & (cosine < 0.3)
    assert bool((keep[grazing] == 0).all()) and bool((keep[~grazing] == 1).all())
    assert 0.05 < float(grazing.float().sum() / covered.float().sum()) < 0.5
    # An empty band keeps every pixel.
    assert bool((off_terminator(relight, [0.0, 0.0]) == 1).all())


def test_the_linearised_interval_matches_refits():
    """The exponent's bootstrap takes one linearised step per resample instead of a refit:
    its interval agrees with refitting every resample (tile weights) on a noisy curve."""
    settings = replace(SETTINGS, bootstrap_samples=30)
    relight, under_fitted, _ = relight_case(gamma=0.8, noise=0.05)
    basis = torch.zeros(*relight.observed.shape[:3], 0)
    laplacian = render_laplacian(relight.rendered)
    fitted = RelightResponse(basis, image_basis=laplacian)

    def fit(module: RelightResponse, weight: torch.Tensor) -> float:
        render = lambda: module(under_fitted, relight.rendered)  # noqa: E731
        GaussNewtonProblem([module], render, relight.observed, weight).fit(8)
        return float(module.response.log_gamma.detach().exp())

    fit(fitted, relight.region)
    low, high = exponent_interval(fitted, under_fitted, relight, settings)
    batch, height, width, _ = relight.observed.shape
    tile = settings.relight_tile_pixels
    rows, columns = -(-height // tile), -(-width // tile)
    generator = torch.Generator().manual_seed(1)
    refits = []
    for _ in range(settings.bootstrap_samples):
        picks = torch.randint(
            0, batch * rows * columns, (batch * rows * columns,), generator=generator
        )
        counts = torch.bincount(picks, minlength=batch * rows * columns).float()
        counts = counts.reshape(batch, rows, columns)
        weight = counts.repeat_interleave(tile, 1).repeat_interleave(tile, 2)
        weight = weight[:, :height, :width, None] * relight.region
        refits.append(fit(RelightResponse(basis, image_basis=laplacian), weight))
    refits = torch.tensor(refits)
    assert low < 0.8 < high
    assert abs(low - float(refits.quantile(0.05))) < 0.015, (low, refits)
    assert abs(high - float(refits.quantile(0.95))) < 0.015, (high, refits)
