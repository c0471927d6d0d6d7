"""The warm-started refit's settings: a response curve's exponent held at the relight probe's
estimate, the steps and step size handed to the texture stage, and the fit's own effects
switched on at their fitted parameters."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import recon.diagnose.refit as refit
from recon.config.run_config import RunConfig
from recon.diagnose.refit import RefitSettings
from recon.effects.registry import make_effect


class Captured(Exception):
    """Raised by the stand-in texture stage with what the refit handed it."""


def capture_refit(monkeypatch, names, settings, model_effects=()):
    mesh = SimpleNamespace(verts=torch.zeros(3, 3), faces=torch.zeros(1, 3, dtype=torch.long))
    mesh.to = lambda device: mesh
    lighting = SimpleNamespace(to=lambda device: None)
    model = SimpleNamespace(
        mesh=mesh,
        lighting=lighting,
        effects=list(model_effects),
        effect_names=[module.name for module in model_effects],
    )
    monkeypatch.setattr(refit.LightModel, "from_lighting", staticmethod(lambda lighting: None))

    def texture_stage(captures, geometry, fit_config, *arguments, effects, **keywords):
        raise Captured(fit_config, effects)

    monkeypatch.setattr(refit, "run_texture_stage", texture_stage)
    training = SimpleNamespace(cameras=[0] * 4)
    with pytest.raises(Captured) as caught:
        refit.refit_with(
            names, training, model, RunConfig(), torch.device("cpu"), Path("scratch"), settings
        )
    return caught.value.args


def test_a_response_refit_holds_the_given_exponent(monkeypatch):
    settings = RefitSettings(steps=5, response_exponent=0.8)
    fit_config, effects = capture_refit(monkeypatch, ["response_curve"], settings)
    (curve,) = effects.modules
    assert float(curve.log_gamma.exp()) == pytest.approx(0.8)
    assert not curve.log_gamma.requires_grad and curve.lut.requires_grad
    assert fit_config.texture.steps == 5
    default_rate = RunConfig().diagnose.refit_position_learning_rate
    assert fit_config.texture.learning_rate == default_rate
    _, effects = capture_refit(monkeypatch, ["response_curve"], RefitSettings(steps=5))
    assert (
        float(effects.modules[0].log_gamma.detach()) == 0.0
        and effects.modules[0].log_gamma.requires_grad
    )


def test_the_given_step_size_reaches_the_texture_stage(monkeypatch):
    settings = RefitSettings(steps=5, position_learning_rate=0.01)
    fit_config, _ = capture_refit(monkeypatch, ["lens_distortion"], settings)
    assert fit_config.texture.learning_rate == 0.01


def test_the_fits_own_effects_are_switched_on_at_their_fitted_parameters(monkeypatch):
    fitted = make_effect("vignetting")
    with torch.no_grad():
        fitted.coefficients.fill_(-0.3)
    _, effects = capture_refit(
        monkeypatch, ["exposure"], RefitSettings(steps=5), model_effects=[fitted]
    )
    assert [module.name for module in effects.modules] == ["vignetting", "exposure"]
    assert torch.equal(effects.modules[0].coefficients, fitted.coefficients)
    assert effects.modules[1].is_identity()
