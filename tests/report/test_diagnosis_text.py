"""What `recon diagnose` prints (recon.report.diagnosis_text): ambiguous candidates are flagged,
the capture-metadata comparison is shown under its candidate, and a refit-first pass says what
the others were measured on."""

from __future__ import annotations

import math

from recon.config.run_config import DecisionConfig
from recon.diagnose.decision import decide_all, verdict_of
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.report.diagnosis_text import diagnosis_lines


def probed(name: str, low: float, high: float) -> Candidate:
    candidate = Candidate(name)
    details = {"reduction": (low + high) / 2, "interval": [low, high]}
    candidate.add(Evidence("probe", name, low, math.nan, False, "probe", details))
    return candidate


def test_ambiguous_and_metadata_lines():
    exposure = probed("exposure", 0.2, 0.3)
    metadata = (
        "recovered exposure agrees with the capture's metadata: the images were divided by "
        "their EXIF exposure on load (dataset.exposure: exif)"
    )
    exposure.add(Evidence("metadata", "exposure", 0.004, 0.01, True, metadata))
    curve = probed("response_curve", 0.3, 0.4)
    condition = {"confused_with": ["exposure"]}
    curve.add(
        Evidence(
            "identifiability", "response_curve", math.nan, math.nan, False, "one light", condition
        )
    )
    ranked = decide_all([exposure, curve], DecisionConfig())
    lines = diagnosis_lines(Diagnosis(candidates=ranked, verdict=verdict_of(ranked)))
    assert any(line.startswith("response_curve") and line.endswith("ambiguous") for line in lines)
    assert f"  capture metadata: {metadata}" in lines
    assert lines[-1].startswith(
        "verdict: significant unmodelled effects: response_curve or exposure, exposure"
    )


def test_the_refit_first_line_says_what_the_others_were_measured_on():
    exposure = probed("exposure", 0.5, 0.7)
    ranked = decide_all([exposure], DecisionConfig())
    on_top = {
        "effect": "exposure",
        "steps": 300,
        "heldout_rmse": 0.0321,
        "ceiling_share": {"fit": [0.33, 0.12, 0.0], "refit": [0.01, 0.0, 0.0]},
    }
    gap = {"rmse": 0.1234, "on_top_of": on_top}
    lines = diagnosis_lines(Diagnosis(gap=gap, candidates=ranked, verdict=verdict_of(ranked)))
    assert (
        "the others measured on the model refitted with exposure (300 steps): held-out RMSE "
        "0.1234 -> 0.0321; albedo at its ceiling (r/g/b % of pixels) 33/12/0 -> 1/0/0"
    ) in lines
    assert not any("refitted with" in line for line in diagnosis_lines(Diagnosis()))
