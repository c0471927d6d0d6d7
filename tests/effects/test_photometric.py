"""Model effects exposure, white_balance, vignetting, response_curve: identity at zero,
gradients against central differences (float64), and recovery of their own parameters from a
render they produced (Adam on the effect's parameters only)."""

from __future__ import annotations

import math

import pytest
import torch

from recon.effects import Exposure, ResponseCurve, Vignetting, WhiteBalance
from recon.errors import ReconError


def _image(scene, background: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The scene's render (detached), optionally over a uniform background."""
    color, alpha = scene.output.color.detach(), scene.output.alpha.detach()
    return color + (1 - alpha) * background, alpha


@pytest.mark.parametrize("effect_class", [Exposure, WhiteBalance, Vignetting, ResponseCurve])
def test_identity_at_zero_is_exact(effect_class, sphere_scene):
    color, alpha = _image(sphere_scene, background=0.2)
    effect = effect_class(len(sphere_scene.cameras))
    assert effect.is_identity()
    for views in (sphere_scene.views, None):
        new_color, new_alpha = effect(color, alpha, sphere_scene.cameras, views)
        assert torch.equal(new_color, color) and torch.equal(new_alpha, alpha)


def _gradient_check(effect, color, alpha, cameras, views, parameter, indices, central_difference):
    """Autograd against central differences of a fixed random projection of the output."""
    effect.double()
    color, alpha = color.double(), alpha.double()
    weights = torch.rand(
        color.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64
    )

    def loss():
        return (effect(color, alpha, cameras, views)[0] * weights).sum()

    effect.zero_grad()
    loss().backward()
    for index in indices:
        expected = central_difference(loss, parameter, index)
        assert parameter.grad[index].item() == pytest.approx(expected, rel=1e-5, abs=1e-8)


def _exposure() -> Exposure:
    effect = Exposure(3)
    with torch.no_grad():
        effect.log_gain.copy_(torch.tensor([0.0, 0.2, -0.1]))
    return effect


def _vignetting() -> Vignetting:
    effect = Vignetting()
    effect.set_polynomial(-0.2, -0.1)
    return effect


def _response_curve() -> ResponseCurve:
    effect = ResponseCurve()
    with torch.no_grad():
        effect.log_gamma.fill_(0.3)
        effect.lut.copy_(torch.linspace(-0.3, 0.3, effect.lut.shape[0]))
    return effect


@pytest.mark.parametrize(
    "make, parameter_name, indices",
    [
        (_exposure, "log_gain", [(1,), (2,)]),
        (lambda: WhiteBalance(3), "log_red_blue", [(1, 0), (2, 1)]),
        (_vignetting, "coefficients", [(0,), (1,)]),
        (_response_curve, "log_gamma", [()]),
        (_response_curve, "lut", [(2,), (9,)]),
    ],
)
def test_gradients_match_central_differences(
    make, parameter_name, indices, sphere_scene, central_difference
):
    color, alpha = _image(sphere_scene, background=0.1)
    effect = make()
    _gradient_check(
        effect,
        color,
        alpha,
        sphere_scene.cameras,
        sphere_scene.views,
        getattr(effect, parameter_name),
        indices,
        central_difference,
    )


def test_pinned_view_stays_identity_and_gets_no_gradient(sphere_scene):
    color, alpha = _image(sphere_scene)
    for effect in (Exposure(3), WhiteBalance(3)):
        with torch.no_grad():
            for parameter in effect.parameters():
                parameter.fill_(0.3)
        output, _ = effect(color, alpha, sphere_scene.cameras, sphere_scene.views)
        assert torch.equal(output[0], color[0])
        output.sum().backward()
        parameter = next(effect.parameters())
        assert torch.all(parameter.grad[0] == 0) and torch.all(parameter.grad[1:] != 0)
    unpinned = Exposure(3, pinned_view=None)
    with torch.no_grad():
        unpinned.log_gain.fill_(0.3)
    output, _ = unpinned(color, alpha, sphere_scene.cameras, sphere_scene.views)
    torch.testing.assert_close(output[0], color[0] * math.exp(0.3))


def test_held_out_views_use_the_typical_view(sphere_scene):
    color, alpha = _image(sphere_scene)
    exposure = Exposure(3)
    with torch.no_grad():
        exposure.log_gain.copy_(torch.tensor([0.0, 0.3, 0.6]))
    output, _ = exposure(color, alpha, sphere_scene.cameras, None)
    torch.testing.assert_close(output, color * math.exp(0.3))


def test_exposure_recovers_per_view_ratios(sphere_scene, adam_fit):
    color, alpha = _image(sphere_scene)
    views = sphere_scene.views
    effect = Exposure(3)
    with torch.no_grad():
        effect.log_gain.copy_(torch.tensor([0.7, 0.3, -0.4]))  # view 0 is pinned: ignored
        target, _ = effect(color, alpha, sphere_scene.cameras, views)
    truth = torch.tensor([1.0, math.exp(0.3), math.exp(-0.4)])
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, sphere_scene.cameras, views)[0], target, 100)
    ratios = torch.tensor(effect.parameters_summary()["ratios"])
    assert ratios[0] == 1.0
    torch.testing.assert_close(ratios, truth, rtol=0.02, atol=0)


def test_white_balance_recovers_per_view_gains(sphere_scene, adam_fit):
    color, alpha = _image(sphere_scene)
    views = sphere_scene.views
    effect = WhiteBalance(3)
    truth_log = torch.tensor([[0.0, 0.0], [0.2, -0.1], [-0.15, 0.12]])
    with torch.no_grad():
        effect.log_red_blue.copy_(truth_log)
        target, _ = effect(color, alpha, sphere_scene.cameras, views)
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, sphere_scene.cameras, views)[0], target, 100)
    gains = torch.tensor(effect.parameters_summary()["gains"])
    truth = torch.stack([truth_log[:, 0], torch.zeros(3), truth_log[:, 1]], -1).exp()
    assert torch.all(gains[:, 1] == 1.0) and torch.all(gains[0] == 1.0)
    torch.testing.assert_close(gains, truth, rtol=0.02, atol=0)


def test_vignetting_recovers_corner_falloff(sphere_scene, adam_fit):
    # A uniform background behind the sphere: the whole frame carries the falloff.
    color, alpha = _image(sphere_scene, background=0.3)
    cameras = sphere_scene.cameras
    effect = Vignetting()
    effect.set_polynomial(-0.3, -0.1)
    with torch.no_grad():
        target, _ = effect(color, alpha, cameras, None)
    assert effect.parameters_summary()["corner_falloff"] == pytest.approx(0.6)
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, cameras, None)[0], target, 150)
    summary = effect.parameters_summary()
    assert summary["corner_falloff"] == pytest.approx(0.6, rel=0.03)
    assert summary["half_radius_falloff"] == pytest.approx(1 - 0.3 / 4 - 0.1 / 16, rel=0.01)


def test_vignetting_is_centred_on_the_principal_point(sphere_scene):
    color = torch.ones(1, 9, 9, 3)
    alpha = torch.ones(1, 9, 9, 1)
    cameras = sphere_scene.cameras[0].with_image_size((9, 9))
    effect = Vignetting()
    effect.set_polynomial(-0.5)
    output = effect(color, alpha, cameras, None)[0].detach()
    assert float(output[0, 4, 4, 0]) == pytest.approx(1.0, abs=1e-6)  # centre pixel
    # Corner pixel centres sit at r = hypot(4, 4) / hypot(4.5, 4.5) of the half diagonal.
    assert float(output[0, 0, 0, 0]) == pytest.approx(1 - 0.5 * (4 / 4.5) ** 2, abs=1e-6)
    with pytest.raises(ReconError, match="cameras"):
        effect(color, alpha, None, None)


def test_response_curve_is_monotone_with_fixed_ends():
    effect = ResponseCurve()
    with torch.no_grad():
        effect.log_gamma.fill_(0.4)
        effect.lut.copy_(
            torch.randn(effect.lut.shape[0], generator=torch.Generator().manual_seed(1))
        )
    values = torch.linspace(0, 1, 1001)
    curve = effect.curve(values).detach()
    assert float(curve[0]) == 0.0 and float(curve[-1]) == pytest.approx(1.0, abs=1e-6)
    assert torch.all(curve[1:] - curve[:-1] >= 0)
    with pytest.raises(ReconError, match="knots"):
        ResponseCurve(knots=1)


def test_response_curve_recovers_effective_gamma(sphere_scene, adam_fit):
    color, alpha = _image(sphere_scene)
    effect = ResponseCurve()
    with torch.no_grad():
        effect.log_gamma.fill_(math.log(1.6))
        target, _ = effect(color, alpha, None, None)
    assert effect.parameters_summary()["effective_gamma"] == pytest.approx(1.6, abs=1e-4)
    effect.reset_parameters()
    assert effect.parameters_summary()["effective_gamma"] == pytest.approx(1.0, abs=1e-6)
    adam_fit(effect, lambda: effect(color, alpha, None, None)[0], target, 150)
    summary = effect.parameters_summary()
    assert summary["effective_gamma"] == pytest.approx(1.6, abs=0.05)
    assert summary["mid_grey_observed"] == pytest.approx(0.18**1.6, rel=0.1)


def test_response_curve_holds_an_exponent_and_keeps_its_lut_free():
    curve = ResponseCurve()
    curve.hold_exponent(0.7)
    values = torch.tensor([0.04, 0.25, 0.81])
    assert torch.allclose(curve.curve(values), values.pow(0.7), rtol=1e-5)
    curve(values.view(1, 1, 3, 1).expand(1, 1, 3, 3), torch.ones(1, 1, 3, 1))[0].sum().backward()
    assert curve.log_gamma.grad is None
    assert curve.lut.grad is not None and curve.lut.grad.abs().sum() > 0
    with pytest.raises(ReconError, match="held exponent"):
        curve.hold_exponent(0.0)


def test_response_curve_reuses_its_segments_exactly_without_autograd():
    # The diagnosis' Jacobian moves one LUT entry at a time over the same image: x^gamma and
    # the segments are reused then, and the result is the one a fresh module computes.
    from recon.effects.photometric import ResponseCurve

    torch.manual_seed(0)
    cached, fresh = ResponseCurve(), ResponseCurve()
    with torch.no_grad():
        cached.lut.normal_(0, 0.3)
        cached.log_gamma.fill_(0.2)
    values = torch.rand(2, 8, 8, 3) * 1.2 - 0.1
    changes = [
        lambda: cached.lut.__setitem__(3, cached.lut[3] + 1e-3),  # reused
        lambda: cached.log_gamma.add_(1e-3),  # gamma moved: computed again
        lambda: values.mul_(0.9),  # other values (in place): computed again
    ]
    for change in [lambda: None, *changes]:
        with torch.no_grad():
            change()
            result = cached.curve(values)
            fresh.load_state_dict(cached.state_dict())
            fresh._segments = None
            assert torch.equal(result, fresh.curve(values))
    # With autograd the curve is computed afresh and keeps its gradient.
    cached.lut.grad = None
    cached.curve(values).sum().backward()
    assert cached.lut.grad is not None and torch.isfinite(cached.lut.grad).all()
