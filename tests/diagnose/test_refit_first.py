"""A leading per-view gain is refitted into the model before the rest is measured
(diagnose.refit_first): a fit without the gain the views carry keeps an albedo bent against the
texture's ceiling, and the other evidence would read the bend as effects of its own."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from diagnose_scenes import patterned_torus

from recon.camera import orbit_cameras
from recon.config.run_config import RunConfig
from recon.diagnose.data import FittedModel
from recon.diagnose.diagnose import DiagnosisInputs, diagnose_run, refits_first
from recon.io.datasets import CaptureSet
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SIZE, TRAIN, TEST = 32, 10, 8
CANDIDATES = ["exposure", "white_balance", "response_curve", "vignetting"]


@pytest.mark.parametrize(
    ("effect", "expected"),
    [("exposure", True), ("white_balance", True), ("vignetting", False), ("pose_error", False)],
)
def test_only_a_per_view_gain_is_refitted_first(effect, expected):
    model = FittedModel(mesh=patterned_torus((2, 2), 0.2, lambda p: [p, p, p]), lighting=None)
    assert refits_first(effect, model, RunConfig().diagnose) is expected


def test_nothing_is_refitted_first_when_switched_off_or_for_a_pbr_model():
    model = FittedModel(mesh=patterned_torus((2, 2), 0.2, lambda p: [p, p, p]), lighting=None)
    off = replace(RunConfig().diagnose, refit_first=False)
    assert not refits_first("exposure", model, off)
    assert not refits_first("exposure", replace(model, pbr=object()), RunConfig().diagnose)
    assert not refits_first(None, model, RunConfig().diagnose)


def exposed_views(seed: int = 0) -> tuple[DiagnosisInputs, torch.Tensor]:
    """Training and held-out views of a bright textured torus, each view scaled by its own
    exposure (1.2 stops apart at most), and the model a fit without the gain keeps: the
    albedo scaled to the brighter views and stopped at the texture's ceiling of 1. Returns the
    inputs and the true albedo."""
    torch.manual_seed(seed)
    truth = patterned_torus((3, 2), 0.25, lambda p: [p + 0.15, 0.9 * p + 0.1, 0.7 * p + 0.05])
    light = Lighting.constant(0.35)
    light.directional.append(DirectionalLight(torch.tensor([0.3, 0.8, 0.5]), torch.full((3,), 1.0)))
    cameras = orbit_cameras(
        TRAIN + TEST, (SIZE, SIZE), distance=2.4, fov_x_deg=45, elevation_deg=30
    )
    output = Renderer(texture_filter="linear").render(truth, cameras, light)
    generator = torch.Generator().manual_seed(seed)
    stops = torch.linspace(-0.6, 0.6, TRAIN + TEST)[
        torch.randperm(TRAIN + TEST, generator=generator)
    ]
    images = output.color * (2.0**stops)[:, None, None, None]
    images = images + 0.002 * torch.randn(images.shape, generator=generator)
    bent = replace(truth, texture=(truth.texture * 1.5).clamp(max=1.0))
    splits = [slice(0, TRAIN), slice(TRAIN, TRAIN + TEST)]
    training, heldout = (
        CaptureSet(
            cameras[views],
            images[views],
            output.alpha[views],
            [str(index) for index in range(TRAIN + TEST)][views],
            split,
        )
        for views, split in zip(splits, ("train", "test"), strict=True)
    )
    inputs = DiagnosisInputs(
        heldout, training, FittedModel(bent, light), RunConfig(), torch.device("cpu"), None
    )
    return inputs, truth.texture


@pytest.fixture(scope="module")
def diagnosed():
    torch.set_num_threads(1)
    inputs, truth = exposed_views()
    with_refit, _ = diagnose_run(inputs, "none", CANDIDATES)
    off = replace(inputs.config, diagnose=replace(inputs.config.diagnose, refit_first=False))
    without, _ = diagnose_run(replace(inputs, config=off), "none", CANDIDATES)
    return with_refit, without


def test_the_others_are_measured_on_the_model_refitted_with_the_gain(diagnosed):
    with_refit, _ = diagnosed
    assert with_refit.candidates[0].name == "exposure" and with_refit.candidates[0].significant
    on_top = with_refit.gap["on_top_of"]
    assert on_top["effect"] == "exposure" and on_top["steps"] > 0
    # The bent albedo sat at the ceiling where the bright views needed more; the refit with
    # the gain takes it off there, and leaves a fraction of the held-out error.
    fit, refit = on_top["ceiling_share"]["fit"], on_top["ceiling_share"]["refit"]
    assert fit[0] > 0.2 and refit[0] < 0.25 * fit[0], on_top["ceiling_share"]
    assert on_top["heldout_rmse"] < 0.5 * with_refit.gap["rmse"], on_top
    # Every other candidate is measured again on that model, exposure not among them.
    assert sorted(item.name for item in with_refit.candidates) == sorted(CANDIDATES)
    assert "on_top_probes" in with_refit.timings["stages"]
    assert "visibility_fingerprint" in on_top


def test_the_second_pass_removes_what_the_bent_albedo_leaves_for_the_others(diagnosed):
    with_refit, without = diagnosed
    assert "on_top_of" not in without.gap
    for name in ("white_balance", "response_curve", "vignetting"):
        found = next(item for item in with_refit.candidates if item.name == name)
        assert not found.significant, (name, found.why)

    # On the bent model the other probes see part of the bend: more than on the refitted one.
    def probe_reduction(diagnosis, name):
        evidence = next(item for item in diagnosis.candidates if item.name == name)
        return evidence.evidence_of("probe").details["reduction"]

    bent = max(probe_reduction(without, name) for name in ("white_balance", "response_curve"))
    relaxed = max(probe_reduction(with_refit, name) for name in ("white_balance", "response_curve"))
    assert relaxed < bent, (relaxed, bent)
