"""The backdrop check (recon.diagnose.backdrop): the camera's per-view gains read off a static
backdrop, and a gain recovered on the object vetoed where the backdrop does not show it.

Synthetic frames first (a textured backdrop under known per-view gains, an object in the
middle whose colour changes on its own), then the decision row, then the real capture in
../shared/captures (skipped without it): its untouched frames and the same frames under a known
exposure."""

from __future__ import annotations

import math

import pytest
import torch

from recon.config.run_config import BackdropConfig, DecisionConfig
from recon.diagnose.backdrop import (
    backdrop_condition,
    backdrop_evidence,
    gain_components,
    object_log_gains,
    read_backdrop,
)
from recon.diagnose.decision import decide
from recon.diagnose.records import Candidate, Evidence
from recon.io.datasets import read_captures

SETTINGS = BackdropConfig()
VIEWS, SIZE = 8, 48


def centred(values: torch.Tensor) -> torch.Tensor:
    return values - values.mean(0)


def frames_with(
    log_gains: torch.Tensor, moving: bool = False, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames [V, S, S, 3] of a textured backdrop (the same in every view unless moving) times
    exp(log_gains [V, 3]), with a disc in the middle whose colour is random per view; its
    masks [V, S, S, 1]."""
    generator = torch.Generator().manual_seed(seed)
    texture = 0.1 + 0.7 * torch.rand(SIZE, SIZE, 3, generator=generator, dtype=torch.float64)
    if moving:
        texture = 0.1 + 0.7 * torch.rand(VIEWS, SIZE, SIZE, 3, generator=generator).double()
    frames = (texture * torch.exp(log_gains)[:, None, None, :]).clone()
    rows, columns = torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij")
    disc = ((rows - SIZE / 2) ** 2 + (columns - SIZE / 2) ** 2) < (SIZE / 4) ** 2
    object_colour = 0.2 + 0.6 * torch.rand(VIEWS, 3, generator=generator, dtype=torch.float64)
    frames[:, disc] = object_colour[:, None, :]
    masks = disc[None, :, :, None].expand(VIEWS, -1, -1, 1).double()
    return frames, masks


def cleared_exposure(parameters: dict | None = None) -> Candidate:
    """An exposure candidate whose probe clears the default allowance (lower bound 0.1), with
    the probe's parameters."""
    exposure = Candidate("exposure")
    details = {"interval": [0.1, 0.2], "reduction": 0.15}
    if parameters is not None:
        details["parameters"] = parameters
    exposure.add(Evidence("probe", "exposure", 0.1, math.nan, False, "probe", details))
    return exposure


def exposure_log_gains(seed: int = 1, spread: float = 0.3) -> torch.Tensor:
    stops = spread * torch.randn(VIEWS, generator=torch.Generator().manual_seed(seed))
    return stops.double()[:, None].expand(-1, 3)


def test_a_static_backdrop_gives_the_cameras_per_view_gains():
    truth = exposure_log_gains()
    truth = (
        truth + torch.tensor([0.05, 0.0, -0.04]).double() * torch.linspace(-1, 1, VIEWS)[:, None]
    )
    reading = read_backdrop(*frames_with(truth), SETTINGS)
    assert reading is not None and reading.pixels >= SETTINGS.minimum_pixels
    assert torch.allclose(reading.log_gains, centred(truth), atol=1e-9)
    assert float(reading.noise.abs().max()) < 1e-9


def test_no_reading_without_a_static_backdrop():
    truth = exposure_log_gains()
    assert read_backdrop(*frames_with(truth, moving=True), SETTINGS) is None
    frames, masks = frames_with(truth)
    frames[masks[..., 0] == 0] = 0.0  # rendered RGBA: nothing behind the object
    assert read_backdrop(frames, masks, SETTINGS) is None
    assert read_backdrop(*(part[:2] for part in frames_with(truth)), SETTINGS) is None


def test_a_gain_the_backdrop_shows_passes_and_one_it_does_not_is_vetoed():
    truth = exposure_log_gains()
    reading = read_backdrop(*frames_with(truth), SETTINGS)
    noise = 0.02 * torch.randn(VIEWS, 1, generator=torch.Generator().manual_seed(5)).double()
    camera = backdrop_evidence("exposure", truth + noise, reading, SETTINGS)
    assert camera is not None and camera.passed and camera.statistic > 0.8
    assert "camera's gain" in camera.reason
    own = 0.3 * torch.randn(VIEWS, 1, generator=torch.Generator().manual_seed(9)).double()
    vetoed = backdrop_evidence("exposure", own.expand(-1, 3), reading, SETTINGS)
    assert vetoed is not None and not vetoed.passed
    assert vetoed.statistic < SETTINGS.minimum_explained
    assert "not the camera's" in vetoed.reason and "backdrop" in vetoed.reason


def test_a_change_the_backdrop_could_not_see_is_no_evidence():
    truth = exposure_log_gains(spread=0.2)
    frames, masks = frames_with(truth)
    noisy = frames * torch.exp(
        0.05 * torch.randn(frames.shape, generator=torch.Generator().manual_seed(3)).double()
    )
    noisy[masks[..., 0] > 0] = frames[masks[..., 0] > 0]
    reading = read_backdrop(noisy, masks, SETTINGS)
    assert reading is not None
    tiny = 1e-4 * torch.linspace(-1, 1, VIEWS).double()[:, None].expand(-1, 3)
    assert backdrop_evidence("exposure", tiny, reading, SETTINGS) is None


def test_white_balance_is_compared_on_colour_ratios_not_brightness():
    brightness = exposure_log_gains()
    colour = torch.zeros(VIEWS, 3).double()
    colour[:, 2] = 0.1 * torch.linspace(-1, 1, VIEWS).double()
    reading = read_backdrop(*frames_with(brightness + colour), SETTINGS)
    # The object's gains: the backdrop's colour change without its brightness change.
    same_colour = backdrop_evidence("white_balance", colour, reading, SETTINGS)
    assert same_colour is not None and same_colour.passed
    components = gain_components("white_balance", reading.log_gains)
    assert torch.allclose(components[:, 1], centred(colour[:, 2]), atol=1e-9)
    assert torch.allclose(components[:, 0], torch.zeros(VIEWS).double(), atol=1e-9)


def test_recovered_parameters_read_as_log_gains():
    ratios = [1.0, 2.0, 0.5]
    exposure = object_log_gains("exposure", {"ratios": ratios})
    assert exposure.shape == (3, 3) and math.isclose(float(exposure[1, 2]), math.log(2.0))
    gains = [[1.1, 1.0, 0.9], [1.0, 1.0, 1.2], [0.95, 1.0, 1.05]]
    assert torch.allclose(
        object_log_gains("white_balance", {"gains": gains}).exp().float(), torch.tensor(gains)
    )
    assert object_log_gains("exposure", {}) is None


def test_a_backdrop_veto_keeps_a_cleared_gain_from_being_named():
    exposure = cleared_exposure()
    assert decide(exposure, DecisionConfig()).significant
    reason = "exposure: the static backdrop ... not the camera's"
    exposure.add(Evidence("backdrop", "exposure", 0.02, 0.5, False, reason))
    decided = decide(exposure, DecisionConfig())
    assert decided.status == "vetoed" and not decided.significant and decided.why == reason
    agreeing = cleared_exposure()
    agreeing.add(Evidence("backdrop", "exposure", 0.9, 0.5, True, "the camera's gain"))
    assert decide(agreeing, DecisionConfig()).significant


def test_a_backdrop_that_shows_the_gain_keeps_a_residual_pattern_from_vetoing_it():
    # A real turntable capture with an injected exposure (the blind check's draw 7): the probe
    # clears, but the gain's own signature removes no held-out error with confidence (interval
    # from -0.3 %) and the specificity check calls it the diffuse model's mismatch. The backdrop
    # around the object, other pixels than the residual's, shows 79 % of the object's change:
    # the camera's gain. It is named.
    reason = "exposure: its signature's gain removes no held-out error; not specific"
    details = {"tested": False, "heldout_reduction": 0.2}
    pattern = Evidence("specificity", "exposure", math.nan, 0.01, False, reason, details)
    vetoed = cleared_exposure()
    vetoed.add(pattern)
    assert decide(vetoed, DecisionConfig()).status == "vetoed"
    shown = cleared_exposure()
    shown.add(pattern)
    shown.add(Evidence("backdrop", "exposure", 0.79, 0.5, True, "the camera's gain"))
    decided = decide(shown, DecisionConfig())
    assert decided.significant and decided.decided_by == "probe"
    # A backdrop that does not show it vetoes as before.
    hidden = cleared_exposure()
    hidden.add(pattern)
    hidden.add(Evidence("backdrop", "exposure", 0.2, 0.5, False, "the object's own change"))
    assert decide(hidden, DecisionConfig()).status == "vetoed"


@pytest.mark.shared
def test_the_real_captures_backdrop_reads_an_injected_exposure(shared_captures):
    from recon.config.run_config import DatasetConfig

    options = DatasetConfig(max_resolution=96)
    heldout = read_captures(shared_captures / "ethiopian_head", "test", options, keep_frames=True)
    assert heldout.frames is not None and heldout.frames.shape == heldout.images.shape
    # The frames keep the backdrop the fit's images leave out.
    outside = heldout.masks[..., 0] < 0.01
    assert float(heldout.frames[outside].mean()) > 0.05
    assert float(heldout.images[outside].max()) <= 0.01  # premultiplied by a coverage below it
    untouched = read_backdrop(heldout.frames, heldout.masks, SETTINGS)
    assert untouched is not None
    # The capture's exposure is fixed; the room and the camera's automatic white balance still
    # change the frames by a few per cent (measured: about 4 % RMS).
    assert float(untouched.log_gains.pow(2).mean().sqrt()) < 0.1
    stops = 0.5 * torch.randn(len(heldout), generator=torch.Generator().manual_seed(2)).double()
    exposed = heldout.frames.double() * torch.exp(stops)[:, None, None, None]
    reading = read_backdrop(exposed.clamp(max=1.0), heldout.masks, SETTINGS)
    assert reading is not None
    found = gain_components("exposure", reading.log_gains - untouched.log_gains)[:, 0]
    assert float((found - centred(stops)).abs().max()) < 0.05


def test_rendered_captures_have_no_frames(tiny_run):
    from recon.io.run_folder import RunPaths

    heldout = read_captures(RunPaths(tiny_run).dataset, "test", keep_frames=True)
    assert len(heldout) > 0 and heldout.frames is None


def test_a_backdrop_that_changes_itself_makes_a_vetoed_gain_not_identifiable():
    # The frames change by a few per cent (the backdrop shows it), the object's gains by far
    # more and not with it: the camera's gain is there but the object hides it.
    camera = 0.05 * torch.linspace(-1, 1, VIEWS).double()[:, None].expand(-1, 3)
    reading = read_backdrop(*frames_with(camera), SETTINGS)
    own = 0.3 * torch.randn(VIEWS, 1, generator=torch.Generator().manual_seed(4)).double()
    veto = backdrop_evidence("exposure", own.expand(-1, 3), reading, SETTINGS)
    condition = backdrop_condition(veto, reading, SETTINGS)
    assert condition is not None and condition.kind == "identifiability" and not condition.passed
    assert "hides that gain on the object" in condition.reason
    assert "grey card" in condition.details["capture"]
    exposure = cleared_exposure()
    exposure.add(veto)
    exposure.add(condition)
    decided = decide(exposure, DecisionConfig())
    assert decided.status == "not_identifiable" and not decided.significant
    assert decided.why.startswith("not identifiable from this data, because the static backdrop")
    # A backdrop that stays the same: the veto is the whole answer.
    still = read_backdrop(*frames_with(torch.zeros(VIEWS, 3).double()), SETTINGS)
    quiet = backdrop_evidence("exposure", own.expand(-1, 3), still, SETTINGS)
    assert not quiet.passed and backdrop_condition(quiet, still, SETTINGS) is None


def test_a_confirmed_gain_reports_the_backdrops_reading():
    truth = exposure_log_gains()
    reading = read_backdrop(*frames_with(truth), SETTINGS)
    noisy = (
        truth + 0.03 * torch.randn(VIEWS, 1, generator=torch.Generator().manual_seed(6)).double()
    )
    camera = backdrop_evidence("exposure", noisy, reading, SETTINGS)
    ratios = torch.tensor(camera.details["parameters"]["ratios"]).double()
    assert torch.allclose(torch.log(ratios), centred(truth[:, 0]), atol=1e-9)
    exposure = cleared_exposure({"ratios": torch.exp(noisy[:, 0]).tolist()})
    exposure.add(camera)
    decided = decide(exposure, DecisionConfig())
    assert decided.significant and decided.parameters["estimator"] == "backdrop"
    # A vetoed gain reports no backdrop parameters.
    own = 0.3 * torch.randn(VIEWS, 1, generator=torch.Generator().manual_seed(9)).double()
    assert (
        "parameters"
        not in backdrop_evidence("exposure", own.expand(-1, 3), reading, SETTINGS).details
    )


def test_the_backdrop_figure_draws_each_checked_gain(tmp_path):
    from PIL import Image

    from recon.diagnose.figures import backdrop_figure

    colour = torch.zeros(VIEWS, 3).double()
    colour[:, 2] = 0.1 * torch.linspace(-1, 1, VIEWS).double()
    reading = read_backdrop(*frames_with(exposure_log_gains() + colour), SETTINGS)
    own = 0.3 * torch.randn(VIEWS, 3, generator=torch.Generator().manual_seed(8)).double()
    records = [
        backdrop_evidence("exposure", exposure_log_gains(), reading, SETTINGS),
        backdrop_evidence("white_balance", own, reading, SETTINGS),
    ]
    assert [len(record.details["components"]) for record in records] == [1, 2]
    assert len(records[1].details["object_components"]) == VIEWS
    path = backdrop_figure([record.to_json() for record in records], tmp_path / "backdrop.png")
    with Image.open(path) as image:
        assert image.format == "PNG" and image.width > image.height > 100
