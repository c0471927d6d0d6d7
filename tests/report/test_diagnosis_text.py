"""What `recon diagnose` prints (recon.report.diagnosis_text): ambiguous candidates are flagged
and the capture-metadata comparison is shown under its candidate."""

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
