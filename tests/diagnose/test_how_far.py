"""How far the gap shrinks: the refit's step size by whether the effect bends the geometry, the
relight exponent taken from the relight evidence, and a refit that takes an effect back scored
as closing the gap (and confirmed) where one without it is not."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from diagnose_scenes import patterned_torus
from diagnose_where_scene import SETTINGS, make_scene, noisy

import recon.diagnose.how_far as how_far
from recon.camera import orbit_cameras
from recon.config.run_config import RunConfig
from recon.diagnose.data import FittedModel, build_diagnosis_data
from recon.diagnose.how_far import (
    RefitBaseline,
    RefitInputs,
    measure_refit,
    position_learning_rate,
    relight_exponent,
)
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.refit import RefitSettings
from recon.effects import make_effect
from recon.optimize.scene_model import FitEffects
from recon.render.renderer import Renderer
from recon.render.shading import Lighting


def test_vertices_move_faster_only_where_the_effect_bends_the_geometry():
    config = RunConfig()
    assert position_learning_rate(["lens_distortion"], config) == config.fit.texture.learning_rate
    assert position_learning_rate(["exposure", "lens_distortion"], config) > 0.002
    default = config.diagnose.refit_position_learning_rate
    assert position_learning_rate(["vignetting"], config) == default


def test_the_relight_exponent_comes_from_the_relight_evidence():
    other = Candidate("vignetting")
    response = Candidate("response_curve")
    assert relight_exponent([other, response]) is None
    response.add(
        Evidence(
            "relight",
            "response_curve",
            0.1,
            math.nan,
            False,
            "relight",
            {"parameters": {"gamma": 0.85}},
        )
    )
    assert relight_exponent([other, response]) == 0.85


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
        return FittedModel(mesh, lighting), FitEffects(names, 24, torch.device("cpu"))

    monkeypatch.setattr(how_far, "refit_with", refit_with)
    config = RunConfig()
    baseline = RefitBaseline.measure(data, 0.002**2, relight, config.diagnose)
    inputs = RefitInputs(
        SimpleNamespace(), SimpleNamespace(), config, torch.device("cpu"), Path("scratch")
    )
    record, _ = measure_refit(["exposure"], baseline, inputs, RefitSettings(steps=1))
    assert record["closed_fraction"] > 0.9 and record["confirmed"], record
    # The relight split's gauge takes a global scale, so its gap was small to begin with.
    assert record["relight_before"] < 0.1 * record["before"]
    nothing, _ = measure_refit([], baseline, inputs, RefitSettings(steps=1))
    assert abs(nothing["closed_fraction"]) < 0.05 and not nothing["confirmed"], nothing
    assert baseline.after(record).before == record["after"]


@pytest.fixture(scope="module")
def scene():
    return make_scene()


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


def test_gap_closed_is_the_share_of_the_error_above_the_floor_a_refit_removes(monkeypatch):
    """A known answer: the observed views are 1.2 x the fitted render and the 'refit' (no
    effect) brightens the texture by 1.1, so the residual halves and its squared error drops to
    a quarter on every pixel. With the floor at an eighth of the error before, the refit
    removes (1 - 1/4) / (1 - 1/8) = 6/7 of the error above the floor."""
    mesh = patterned_torus((2, 3), 0.25, lambda p: [0.5 * p + 0.1, 0.4 * p + 0.1, 0.3 * p + 0.2])
    lighting = Lighting.constant(0.9)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    cameras = orbit_cameras(4, (32, 32), distance=2.2, fov_x_deg=50, elevation_deg=30.0)
    output = renderer.render(mesh, cameras, lighting)
    data = build_diagnosis_data(1.2 * output.color, output.alpha, output, cameras, lighting, mesh)
    brighter = replace(mesh, texture=1.1 * mesh.texture)

    def refit_with(names, *arguments, **options):
        return FittedModel(brighter, lighting), FitEffects(names, 4, torch.device("cpu"))

    monkeypatch.setattr(how_far, "refit_with", refit_with)
    config = RunConfig()
    before = how_far.heldout_gap(data, [], config.diagnose)
    baseline = RefitBaseline.measure(data, before / 8, None, config.diagnose)
    inputs = RefitInputs(
        SimpleNamespace(), SimpleNamespace(), config, torch.device("cpu"), Path("scratch")
    )
    record, _ = measure_refit([], baseline, inputs, RefitSettings(steps=1))
    assert record["after"] == pytest.approx(before / 4, rel=1e-4)
    assert record["closed_fraction"] == pytest.approx(6 / 7, rel=1e-3)
