"""Recovered exposure against EXIF exposure: ratio error, correlation, the all-equal baseline.

Built to fool a check that only asks whether exposure was "found": gains that vary as much as
the EXIF ones but in the wrong pattern (the issue's real photos: r = 0.38, and equal exposure
would have done better), a constant-exposure capture whose mismatch was absorbed as exposure,
and a real exposure recovered from views of a glossy object.
"""

from __future__ import annotations

import json

import pytest
import torch
from diagnose_scenes import glossy_torus_views

from recon.diagnose.metadata_check import (
    MetadataOptions,
    exif_exposure_gains,
    metadata_evidence,
)
from recon.diagnose.which import rank_candidates
from recon.errors import ReconError

OPTIONS = MetadataOptions(permutations=500)


def exposure_ratios(data) -> torch.Tensor:
    probe = next(item for item in rank_candidates(data, ["exposure"])).evidence_of("probe")
    return torch.tensor(probe.details["parameters"]["ratios"])


def test_recovered_gains_that_follow_exif_agree():
    generator = torch.Generator().manual_seed(0)
    known = torch.exp(0.25 * torch.randn(16, generator=generator))
    recovered = 1.7 * known * torch.exp(0.02 * torch.randn(16, generator=generator))
    evidence = metadata_evidence(recovered, known, options=OPTIONS)
    assert evidence.kind == "metadata" and evidence.passed, evidence.reason
    assert evidence.details["median_ratio_error"] < 0.03  # the common scale is the gauge's
    assert evidence.details["correlation"] > 0.95
    assert evidence.statistic < evidence.threshold
    json.dumps(evidence.to_json())


def test_a_spread_in_the_wrong_pattern_loses_to_equal_exposure():
    # As on the real photos: EXIF spans 0.63-1.25, the recovered gains vary by as much
    # but mostly with something else.
    generator = torch.Generator().manual_seed(1)
    known = torch.linspace(0.63, 1.25, 20)[torch.randperm(20, generator=generator)]
    mismatch = torch.exp(0.15 * torch.randn(20, generator=generator))
    recovered = known**0.15 * mismatch
    evidence = metadata_evidence(recovered, known, options=OPTIONS)
    assert not evidence.passed, evidence.reason
    assert evidence.details["baseline_error"] < evidence.details["median_ratio_error"]
    assert "does not agree" in evidence.reason and "equal exposure" in evidence.reason


def test_probe_exposure_on_glossy_views_against_the_true_exposure():
    real, gains = glossy_torus_views(exposure_sigma=0.3, size=32)
    assert metadata_evidence(exposure_ratios(real), gains, options=OPTIONS).passed
    # Constant exposure (as an untouched capture's EXIF says): the gains the probe absorbed
    # from the highlight are an error against the metadata.
    constant, ones = glossy_torus_views(exposure_sigma=0.0, size=32)
    evidence = metadata_evidence(exposure_ratios(constant), ones, options=OPTIONS)
    assert not evidence.passed and "same in all" in evidence.reason
    assert evidence.details["median_ratio_error"] > 0.01


def test_exif_gains_need_all_three_values_in_every_view():
    records = [
        {"exposure_time": 1 / 100, "f_number": 4.0, "iso": 100},
        {"exposure_time": 1 / 50, "f_number": 4.0, "iso": 100},
        {"exposure_time": 1 / 100, "f_number": 4.0, "iso": 200},
    ]
    gains = exif_exposure_gains(records)
    torch.testing.assert_close(gains, torch.tensor([0.5, 1.0, 1.0], dtype=torch.float64))
    records[1] = {"exposure_time": 1 / 50, "f_number": None, "iso": 100}
    assert exif_exposure_gains(records) is None
    assert exif_exposure_gains(None) is None


def test_mismatched_views_are_refused_by_name():
    with pytest.raises(ReconError, match="recovered gains for 3 views, known .* for 4"):
        metadata_evidence([1.0, 1.1, 0.9], [1.0, 1.0, 1.2, 0.8])
    with pytest.raises(ReconError, match="at least 3 positive gains"):
        metadata_evidence([1.0, -1.0, 0.9], [1.0, 1.0, 1.2])
