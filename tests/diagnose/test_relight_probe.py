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
from recon.diagnose.relight_probe import relight_response_probe, unshadowed
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SETTINGS = DiagnoseConfig()

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


def test_a_highlight_under_the_second_light_is_not_a_tone_curve():
    # Built to fool it: a glossy surface under the relight sun adds light that the diffuse fit
    # lacks where n.h peaks, bright pixels brighter, which a curve could bend toward.
    relight, under_fitted, fitted_light = relight_case(gamma=1.0, highlight=0.4)
    assert float((relight.residual.abs() > 0.05).float().mean()) > 0.01  # the highlight is there
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert record["expanding"] and record["interval"][0] < SETTINGS.decision.relight_allowance
    # Credited both ways, the highlight would read as a (expanding) curve.
    both_ways = replace(SETTINGS, relight_compressive_only=False)
    record = relight_response_probe(relight, under_fitted, fitted_light, both_ways)
    assert record["interval"][0] > SETTINGS.decision.relight_allowance, record


def test_a_compressive_curve_on_a_glossy_surface_is_still_found():
    relight, under_fitted, fitted_light = relight_case(gamma=0.6, highlight=0.2)
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert not record["expanding"], record
    assert record["interval"][0] > SETTINGS.decision.relight_allowance, record


def test_a_linear_camera_leaves_nothing():
    relight, under_fitted, fitted_light = relight_case(gamma=1.0)
    record = relight_response_probe(relight, under_fitted, fitted_light, SETTINGS)
    assert abs(record["reduction"]) < 0.02, record
    assert abs(record["parameters"]["gamma"] - 1.0) < 0.05, record


def test_a_wrong_sun_to_ambient_balance_is_not_a_tone_curve():
    """The fit lit the first views with too weak a sun and too much ambient; its albedo absorbed
    the difference (a function of the normal). A linear camera: nothing to find."""
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.8 * p + 0.1, 0.6 * p + 0.2], base=0.45)
    cameras = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.2, fov_x_deg=50, elevation_deg=30)
    renderer = Renderer(texture_filter="linear")
    true_first, second = lit_by([0.5, 0.8, 0.4]), lit_by([-0.7, 0.5, -0.3])
    sun = true_first.directional[0]
    fitted_first = Lighting(
        sh_coefficients=Lighting.constant(0.45).sh_coefficients,
        directional=[DirectionalLight(sun.direction_to_light, 0.6 * sun.irradiance)],
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
    record = relight_response_probe(relight, under_true, fitted_first, SETTINGS)
    assert record["interval"][0] < 0.01, record


def test_cast_shadow_pixels_are_left_out():
    relight, _, fitted_light = relight_case(gamma=1.0)
    keep = unshadowed(relight, fitted_light, SETTINGS.relight_shadowed_share)
    covered = relight.triangle_id >= 0
    kept_share = float(keep[..., 0][covered].mean())
    # The torus hides part of each light from its inner side, not most of its surface.
    assert 0.3 < kept_share < 0.98, kept_share
