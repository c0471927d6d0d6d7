"""The how-far refit's settings: a response curve's exponent held at the relight probe's
estimate, and the vertices' step size by whether the switched-on effect bends the geometry."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from diagnose_scenes import patterned_torus

import recon.diagnose.diagnose as diagnose
import recon.diagnose.refit as refit
from recon.camera import orbit_cameras
from recon.config.run_config import RunConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.diagnose import (
    RefitBaseline,
    _position_learning_rate,
    _relight_exponent,
    measure_refit,
)
from recon.diagnose.which import CandidateResult
from recon.io.run_folder import RunPaths
from recon.optimize.scene_model import FitEffects
from recon.render.renderer import Renderer
from recon.render.shading import Lighting


class Captured(Exception):
    """Raised by the stand-in texture stage with what the refit handed it."""


def capture_refit(monkeypatch, names, **options):
    mesh = SimpleNamespace(verts=torch.zeros(3, 3), faces=torch.zeros(1, 3, dtype=torch.long))
    mesh.to = lambda device: mesh
    monkeypatch.setattr(refit, "read_captures", lambda *a: SimpleNamespace(cameras=[0] * 4))
    monkeypatch.setattr(refit, "load_mesh", lambda *a: mesh)
    monkeypatch.setattr(refit, "load_fitted_light", lambda *a: None)
    monkeypatch.setattr(refit.LightModel, "from_lighting", staticmethod(lambda lighting: None))

    def texture_stage(captures, geometry, fit_config, *arguments, effects, **keywords):
        raise Captured(fit_config, effects)

    monkeypatch.setattr(refit, "run_texture_stage", texture_stage)
    with pytest.raises(Captured) as caught:
        refit.refit_with(
            names, RunPaths(Path("run")), RunConfig(), torch.device("cpu"), 5, **options
        )
    return caught.value.args


def test_a_response_refit_holds_the_given_exponent(monkeypatch):
    fit_config, effects = capture_refit(monkeypatch, ["response_curve"], response_exponent=0.8)
    (curve,) = effects.modules
    assert float(curve.log_gamma.exp()) == pytest.approx(0.8)
    assert not curve.log_gamma.requires_grad and curve.lut.requires_grad
    assert fit_config.texture.steps == 5
    assert fit_config.texture.learning_rate == refit.POSITION_LEARNING_RATE
    _, effects = capture_refit(monkeypatch, ["response_curve"])
    assert (
        float(effects.modules[0].log_gamma.detach()) == 0.0
        and effects.modules[0].log_gamma.requires_grad
    )


def test_vertices_move_faster_only_where_the_effect_bends_the_geometry(monkeypatch):
    config = RunConfig()
    assert _position_learning_rate(["lens_distortion"], config) == config.fit.texture.learning_rate
    assert _position_learning_rate(["exposure", "lens_distortion"], config) > 0.002
    assert _position_learning_rate(["vignetting"], config) == refit.POSITION_LEARNING_RATE
    fit_config, _ = capture_refit(monkeypatch, ["lens_distortion"], position_learning_rate=0.01)
    assert fit_config.texture.learning_rate == 0.01


def test_the_relight_exponent_comes_from_the_response_candidate():
    other = CandidateResult("vignetting", 0.0, 0.0, (0.0, 0.0), False)
    response = CandidateResult("response_curve", 0.0, 0.0, (0.0, 0.0), False)
    assert _relight_exponent([other, response]) is None
    response.relight_parameters = {"gamma": 0.85}
    assert _relight_exponent([other, response]) == 0.85


def test_measure_refit_scores_a_refit_that_takes_the_effect_back(monkeypatch):
    """The observed views are 0.8 x the fitted scene's render (an exposure the fit missed in
    every view). A 'refit' that returns the same scene with an exposure module (its held-out
    gains fitted on half of each view's pixel blocks) closes nearly all of the held-out gap
    and is confirmed; one without it closes nothing and is not."""
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.8 * p + 0.1, 0.6 * p + 0.2])
    lighting = Lighting.constant(0.9)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")

    def views(elevation: float):
        cameras = orbit_cameras(4, (32, 32), distance=2.2, fov_x_deg=50, elevation_deg=elevation)
        output = renderer.render(mesh, cameras, lighting)
        observed = 0.8 * output.color + 0.002 * torch.randn(
            output.color.shape, generator=torch.Generator().manual_seed(1)
        )
        return build_diagnosis_data(observed, output.alpha, output, cameras, lighting, mesh)

    data, relight = views(30.0), views(-20.0)

    def refit_with(names, *arguments, **options):
        return mesh, lighting, FitEffects(names, 24, torch.device("cpu"))

    monkeypatch.setattr(diagnose, "refit_with", refit_with)
    baseline = RefitBaseline.measure(data, 0.002**2, (relight,))
    record, _ = measure_refit(["exposure"], baseline, Path("run"), None, torch.device("cpu"))
    assert record["closed_fraction"] > 0.9 and record["confirmed"], record
    # The relight split's gauge takes a global scale, so its gap was small to begin with.
    assert record["relight_before"] < 0.1 * record["before"]
    nothing, _ = measure_refit([], baseline, Path("run"), None, torch.device("cpu"))
    assert abs(nothing["closed_fraction"]) < 0.05 and not nothing["confirmed"], nothing
    assert baseline.after(record).before == record["after"]
