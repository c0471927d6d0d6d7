"""The lens distortion measured on line-target frames (recon.diagnose.line_target) and its row in
the decision table."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from data_synth.effects.optics import undistort
from data_synth.line_target import line_target_capture
from recon.config.run_config import (
    CameraRigConfig,
    CaptureConfig,
    DecisionConfig,
    EffectConfig,
    LineTargetConfig,
)
from recon.diagnose.decision import decide
from recon.diagnose.line_target import card_exponent_allowance, measure_line_target
from recon.diagnose.records import Candidate, Evidence
from recon.errors import ReconError

SIZE = 48
CAPTURE = CaptureConfig(
    cameras=CameraRigConfig(rig="fibonacci", distance=3.0, fov_deg=40.0, resolution=[SIZE, SIZE]),
    line_target=LineTargetConfig(views=4),
)
CONFIG = DecisionConfig()


def measured(effects: list[EffectConfig], seed: int = 0) -> dict:
    capture, _, _ = line_target_capture(CAPTURE, effects, seed)
    return measure_line_target(capture.images.double(), capture.cameras.intrinsics)


def true_corner_shift(coefficients: tuple[float, ...]) -> float:
    """Mean distance (pixels) between each image corner and where the lens maps it from."""
    capture, _, _ = line_target_capture(CAPTURE, [], 0)
    fx, fy = (float(capture.cameras.intrinsics[0, i, i]) for i in (0, 1))
    corner = torch.tensor([0.0, SIZE], dtype=torch.float64) - SIZE / 2
    x_distorted = (corner[None, :] / fx).expand(2, 2).reshape(-1)
    y_distorted = (corner[:, None] / fy).expand(2, 2).reshape(-1)
    x, y, valid = undistort(x_distorted, y_distorted, coefficients)
    assert bool(valid.all())
    return float(torch.hypot(fx * (x - x_distorted), fy * (y - y_distorted)).mean())


@pytest.mark.parametrize("k1", [0.25, -0.25, 0.6])
def test_a_lens_is_recovered_from_the_bent_lines(k1):
    result = measured([EffectConfig("lens_distortion", {"k1": k1})], seed=1)
    expected = true_corner_shift((k1, 0.0, 0.0, 0.0, 0.0))
    assert expected > 1.0
    assert result["corner_shift_pixels"] == pytest.approx(expected, rel=0.1)
    assert result["parameters"]["k1"] == pytest.approx(k1, rel=0.1)
    assert result["standard_error"] < 0.1 * result["corner_shift_pixels"]
    # The undistortion straightens the lines to the edge finder's own precision (a tenth of a
    # pixel: linear interpolation of box-filtered edges).
    assert result["straightness_after_pixels"] < 0.1 < result["straightness_before_pixels"]
    assert result["lines"] >= 20 and result["frames_with_lines"] == 4


FOOLS = {
    "clean": [],
    "exposure": [EffectConfig("exposure", {"spread_stops": 0.6})],
    "white_balance": [EffectConfig("white_balance", {})],
    "vignetting": [EffectConfig("vignetting", {"strength": 0.4, "offset_x_px": 2.0})],
    "response_curve": [EffectConfig("response_curve", {})],
    "defocus_blur": [EffectConfig("defocus_blur", {"radius_px": 2.5})],
    "motion_blur": [EffectConfig("motion_blur", {})],
    "noise": [EffectConfig("noise", {})],
}


@pytest.mark.parametrize("name", sorted(FOOLS))
def test_effects_that_do_not_bend_lines_show_no_lens(name):
    """Levels, falloff, blur and noise change the stripes but not their straightness: the
    measured shift stays under the allowance or its own standard errors."""
    for seed in (0, 1):
        result = measured(FOOLS[name], seed)
        threshold = max(
            CONFIG.line_target_allowance, CONFIG.line_target_z * result["standard_error"]
        )
        assert result["corner_shift_pixels"] < threshold, (seed, result)


def test_unusable_frames_are_refused_by_name():
    flat = torch.full((2, SIZE, SIZE, 3), 0.4, dtype=torch.float64)
    intrinsics = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    with pytest.raises(ReconError, match=r"line_target.frames: 0 straight edges found in 2"):
        measure_line_target(flat, intrinsics)
    with pytest.raises(ReconError, match=r"expected shape \[N >= 1, H, W, 3\], got \(2, 48, 48\)"):
        measure_line_target(flat[..., 0], intrinsics)
    with pytest.raises(ReconError, match=r"line_target.intrinsics: expected shape \[2, 3, 3\]"):
        measure_line_target(flat, intrinsics[:1])


def lens_candidate(probe_low: float, shift: float, error: float) -> Candidate:
    candidate = Candidate("lens_distortion")
    candidate.add(
        Evidence(
            "probe",
            "lens_distortion",
            probe_low,
            math.nan,
            False,
            "probe: held-out reduction's lower bound",
            {"interval": [probe_low, probe_low + 0.1], "reduction": probe_low + 0.05},
        )
    )
    candidate.add(
        Evidence(
            "identifiability",
            "lens_distortion",
            0.05,
            0.2,
            False,
            "the object covers the centre only",
            {"settled_by": ["beyond_confusers", "line_target"], "confused_with": ["pose_error"]},
        )
    )
    candidate.add(
        Evidence(
            "line_target",
            "lens_distortion",
            shift,
            math.nan,
            False,
            "line-target frames: corner shift",
            {"standard_error": error, "parameters": {"k1": 0.2}},
        )
    )
    return candidate


def test_the_line_target_decides_alone_either_way():
    # The frames show a lens the object's views cannot: significant, with its parameters.
    found = decide(lens_candidate(probe_low=-0.01, shift=2.0, error=0.05), CONFIG)
    assert found.status == "significant" and found.decided_by == "line_target"
    assert found.parameters == {"k1": 0.2}
    # The frames show none: a probe that clears on the object is overruled, and the
    # identifiability condition the frames settle does not turn it into "not identifiable".
    absent = decide(lens_candidate(probe_low=0.5, shift=0.1, error=0.05), CONFIG)
    assert absent.status == "not_significant" and "line-target" in absent.why
    # Noisy frames: a shift above the allowance but within line_target_z standard errors.
    noisy = decide(lens_candidate(probe_low=-0.01, shift=0.8, error=0.3), CONFIG)
    assert noisy.status == "not_significant"
    assert f"{CONFIG.line_target_z * 0.3:.3f}" in noisy.why


# ---------------------------------------------------------------------------------------------
# The card's two levels: a response curve.
# ---------------------------------------------------------------------------------------------

CURVE = {"toe": 0.06, "shoulder": 0.7, "gamma": 2.0}


def test_the_two_levels_read_the_response_exponent_over_them():
    from data_synth.effects.registry import make_world_effect

    capture, _, _ = line_target_capture(CAPTURE, [EffectConfig("response_curve", CURVE)], 0)
    result = measure_line_target(capture.images.double(), capture.cameras.intrinsics, 0.1)
    world = make_world_effect("response_curve", CURVE)
    white = CAPTURE.line_target.radiance
    observed = world.observed_linear(torch.tensor([0.1 * white, white], dtype=torch.float64))
    expected = math.log(float(observed[0] / observed[1])) / math.log(0.1)
    assert abs(expected - 1) > 0.1
    assert result["levels"]["exponent"] == pytest.approx(expected, abs=0.01)
    assert result["levels"]["standard_error"] < 0.01
    assert len(result["levels"]["per_frame"]) == 4
    # Without the card's contrast, no levels are read.
    assert (
        measure_line_target(capture.images.double(), capture.cameras.intrinsics)["levels"] is None
    )


@pytest.mark.parametrize(
    "name", ["clean", "exposure", "white_balance", "vignetting", "defocus_blur", "noise"]
)
def test_levels_and_falloffs_keep_the_cards_ratio(name):
    effects = (
        FOOLS[name]
        if name != "defocus_blur"
        else [EffectConfig("defocus_blur", {"radius_px": 1.5})]
    )
    result = measured_levels(effects)
    # data_synth's card is exact: only the reading's guard and its standard errors allow for
    # a distance from 1.
    error = result["standard_error"]
    bar = max(
        CONFIG.line_target_levels_allowance,
        CONFIG.line_target_z * (math.inf if error is None else error),
    )
    assert abs(1 - result["exponent"]) <= bar, result
    assert len(result["per_frame"]) >= 3


@pytest.mark.parametrize("off_by", [-0.02, 0.02])
def test_a_card_off_its_data_sheet_reads_within_the_cards_allowance(off_by):
    """A card printed 2 % off the contrast its data sheet states, read with the stated one,
    moves the exponent by up to card_exponent_allowance(0.1, 0.02), and not by more."""
    printed = replace(CAPTURE, line_target=LineTargetConfig(views=4, dark_share=0.1 * (1 + off_by)))
    capture, _, _ = line_target_capture(printed, [], 0)
    result = measure_line_target(capture.images.double(), capture.cameras.intrinsics, 0.1)
    allowance = card_exponent_allowance(0.1, 0.02)
    assert 0.5 * allowance < abs(1 - result["levels"]["exponent"]) <= allowance + 1e-6, result
    assert card_exponent_allowance(0.1, 0.0) == 0.0


def test_a_blur_as_wide_as_the_stripes_leaves_no_level_to_read():
    """A 2.5 px defocus rounds the 6 px stripes' middles: their levels are no longer the card's,
    and no frame's ratio is read (rather than a wrong curve)."""
    result = measured_levels(FOOLS["defocus_blur"])
    assert result["exponent"] is None and result["per_frame"] == []
    assert result["standard_error"] is None


def test_a_motion_blur_that_smears_the_stripes_is_not_read_as_a_curve():
    """A long path reaches into the stripes' plateaus differently per frame: the frames disagree,
    and the exponent's distance from 1 stays within its standard errors."""
    result = measured_levels([EffectConfig("motion_blur", {"length_px": 4.0})])
    error = result["standard_error"]
    bar = max(
        CONFIG.line_target_levels_allowance,
        CONFIG.line_target_z * (math.inf if error is None else error),
    )
    assert result["exponent"] is None or abs(1 - result["exponent"]) < bar, result


def measured_levels(effects: list[EffectConfig], seed: int = 0) -> dict:
    capture, _, _ = line_target_capture(CAPTURE, effects, seed)
    return measure_line_target(capture.images.double(), capture.cameras.intrinsics, 0.1)["levels"]


def curve_candidate(
    exponent: float, error: float, probe_low: float, relight=None, card: dict | None = None
) -> Candidate:
    candidate = Candidate("response_curve")
    candidate.add(
        Evidence(
            "probe",
            "response_curve",
            probe_low,
            math.nan,
            False,
            "probe",
            {"interval": [probe_low, probe_low + 0.1], "reduction": probe_low + 0.05},
        )
    )
    if relight is not None:
        low, specific = relight
        candidate.add(
            Evidence(
                "relight",
                "response_curve",
                low,
                math.nan,
                False,
                "relight",
                {"interval": [low, low + 0.1], "specific": specific, "parameters": {"gamma": 1.3}},
            )
        )
    candidate.add(
        Evidence(
            "line_target_levels",
            "response_curve",
            abs(1 - exponent),
            math.nan,
            False,
            "levels",
            {"standard_error": error, "parameters": {"effective_gamma": exponent}, **(card or {})},
        )
    )
    return decide(candidate, CONFIG)


def test_the_levels_clear_a_curve_even_where_the_relight_split_shows_none():
    found = curve_candidate(1.2, 0.01, probe_low=-0.01, relight=(0.01, False))
    assert found.status == "significant" and found.decided_by == "line_target_levels"
    assert found.parameters == {"effective_gamma": 1.2}
    noisy = curve_candidate(1.2, 0.06, probe_low=-0.01)
    assert noisy.status == "not_significant"


def test_precise_levels_without_a_curve_veto_what_only_the_residual_cleared():
    misfit = curve_candidate(1.004, 0.002, probe_low=0.5)
    assert misfit.status == "vetoed" and "printed ratio" in misfit.why
    # Imprecise levels say nothing against it.
    assert curve_candidate(1.004, 0.05, probe_low=0.5).status == "significant"
    # The card measures the camera on two known radiances; a relight split infers a curve
    # through the fitted surface's shading, which shadows and a pose error bend too: precise
    # levels outweigh it, imprecise ones leave its verdict standing.
    relit = curve_candidate(1.004, 0.002, probe_low=0.5, relight=(0.3, True))
    assert relit.status == "vetoed" and "printed ratio" in relit.why
    assert curve_candidate(1.004, 0.05, probe_low=0.5, relight=(0.3, True)).status == "significant"


def test_the_cards_contrast_tolerance_sets_the_levels_allowance():
    """The same reading (exponent 1.004, frames agreeing to 0.0002) is a curve on an exact card
    and within what a card known to 2 % leaves unknown (allowance 0.0088)."""
    exact = {"dark_share": 0.1, "contrast_tolerance": 0.0}
    printed = {"dark_share": 0.1, "contrast_tolerance": 0.02}
    found = curve_candidate(1.004, 0.0002, probe_low=-0.01, card=exact)
    assert found.status == "significant" and found.decided_by == "line_target_levels"
    within = curve_candidate(1.004, 0.0002, probe_low=0.5, card=printed)
    assert within.status == "vetoed" and "printed ratio" in within.why
    # 0.004 + 4 standard errors (0.0008) + the card's 0.0088: within the relight split's least.
    assert "no curve beyond 0.0136 of 1" in within.why
    assert within.evidence_of("line_target_levels").threshold == pytest.approx(
        card_exponent_allowance(0.1, 0.02)
    )
    # An exactly linear reading on an exact card is precise, and vetoes.
    assert curve_candidate(1.0, 0.0, probe_low=0.5, card=exact).status == "vetoed"


def test_levels_read_exactly_say_so_in_their_reason(monkeypatch):
    # Noise-free frames that agree exactly: a standard error of 0, not an unknown one.
    from recon.config.run_config import DiagnoseConfig
    from recon.diagnose import diagnose

    def measured(frames, intrinsics, dark_share):
        return {
            "corner_shift_pixels": 0.01,
            "standard_error": 0.002,
            "parameters": {},
            "straightness_before_pixels": 0.1,
            "straightness_after_pixels": 0.1,
            "lines": 30,
            "frames": 4,
            "levels": {"exponent": 1.0, "standard_error": 0.0, "per_frame": [1.0] * 4},
        }

    monkeypatch.setattr(diagnose, "measure_line_target", measured)
    curve = Candidate("response_curve")
    card = LineTargetConfig(views=4, contrast_tolerance=0.02)
    diagnose.line_target_evidence([curve], torch.zeros(1), torch.zeros(1), DiagnoseConfig(), card)
    levels = curve.evidence_of("line_target_levels")
    assert "standard errors of 0.0000" in levels.reason and "inf" not in levels.reason
    # The card's specification travels with the evidence, so a stored diagnosis decides again.
    assert levels.details["dark_share"] == 0.1 and levels.details["contrast_tolerance"] == 0.02
    assert "known to 2 %" in levels.reason and "the card's 0.0088" in levels.reason
