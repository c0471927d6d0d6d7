"""Specificity of the geometric and blur candidates, each on a case built to fool it.

A torus rendered by recon's renderer, with one data_synth camera effect applied to the
"captured" views and the exact model as the fit. A motion blur makes the lens-distortion and
pose probes clear too (their warps resample, and so blur, the render); the check must veto
them and keep the motion blur. A real lens distortion must pass its check, and a response
curve must not pass a lens-distortion check.
"""

from __future__ import annotations

import copy
import json

import pytest
from diagnose_scenes import camera_effect_torus_views as torus_with

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.decision import decide, decide_all, redecide
from recon.diagnose.geometric_specificity import (
    CONFUSERS,
    dominated,
    geometric_evidence,
    geometric_specificity,
)
from recon.diagnose.records import Diagnosis, Evidence
from recon.diagnose.which import EffectProbe, rank_candidates

GEOMETRIC = ["lens_distortion", "motion_blur", "defocus_blur", "pose_error"]
SETTINGS = DiagnoseConfig(bootstrap_samples=200)


def probed(data, names=GEOMETRIC):
    probe = EffectProbe(data, SETTINGS)
    return probe, rank_candidates(data, names, probe=probe, settings=SETTINGS)


def by_candidate(evidence):
    return {item.candidate: item for item in evidence}


@pytest.fixture(scope="module")
def motion_blurred():
    data = torus_with("motion_blur", {"length_px": 2.0, "length_spread": 0.3, "curvature_deg": 30})
    return probed(data)


def test_a_motion_blur_is_not_named_lens_distortion(motion_blurred):
    probe, ranked = motion_blurred
    significant = {item.name for item in ranked if item.significant}
    # The case fools the probes: the lens distortion and the pose correction clear as well.
    assert {"motion_blur", "lens_distortion", "pose_error"} <= significant
    evidence = by_candidate(geometric_specificity(probe, ranked, SETTINGS))
    assert set(evidence) == significant
    for name in ("lens_distortion", "pose_error"):
        item = evidence[name]
        assert item.kind == "specificity" and not item.passed, item.reason
        assert item.details["alternative"] in ("motion_blur", "defocus_blur")
        assert f"not {name}'s" in item.reason
        # What it adds on top of the blur does not clear its allowance.
        assert item.statistic < item.threshold
    blur = evidence["motion_blur"]
    assert blur.passed, blur.reason
    for record in blur.details["pairs"]:
        assert not dominated(record, 0.0)
        assert record["confuser"] in CONFUSERS["motion_blur"]
    json.dumps([item.to_json() for item in evidence.values()])


def test_a_real_lens_distortion_passes_and_takes_the_others_place():
    probe, ranked = probed(torus_with("lens_distortion", {"k1": -0.25}))
    top = ranked[0]
    assert top.name == "lens_distortion" and top.significant
    evidence = by_candidate(geometric_specificity(probe, ranked, SETTINGS))
    lens = evidence["lens_distortion"]
    assert lens.passed, lens.reason
    assert lens.statistic > lens.threshold  # it clears its allowance on top of every confuser
    assert {record["confuser"] for record in lens.details["pairs"]} == {
        "motion_blur",
        "defocus_blur",
        "pose_error",
    }
    # The blurs and the pose correction that the distortion's displacements also fool are
    # vetoed in its favour.
    for name in ("motion_blur", "defocus_blur", "pose_error"):
        if name in evidence:
            assert not evidence[name].passed
            assert evidence[name].details["alternative"] == "lens_distortion"


def test_a_response_curve_does_not_pass_a_lens_distortion_check():
    data = torus_with("response_curve", {"toe": 0.05, "shoulder": 0.5, "gamma": 2.2})
    probe, ranked = probed(data, ["lens_distortion", "response_curve"])
    curve = next(item for item in ranked if item.name == "response_curve")
    assert curve.significant
    lens = geometric_evidence("lens_distortion", probe, SETTINGS, ["response_curve"])
    assert not lens.passed, lens.reason
    assert lens.details["alternative"] == "response_curve"


def test_clean_data_and_disabled_checks_give_no_evidence():
    probe, ranked = probed(torus_with(None, {}, size=32), ["lens_distortion", "motion_blur"])
    assert not any(item.significant for item in ranked)
    assert geometric_specificity(probe, ranked, SETTINGS) == []
    blurred = torus_with("defocus_blur", {"radius_px": 1.5}, size=32)
    probe, ranked = probed(blurred, ["defocus_blur", "lens_distortion"])
    options = DiagnoseConfig(bootstrap_samples=200)
    options.geometric_specificity.enabled = False
    assert geometric_specificity(probe, ranked, options) == []


def _decided(candidates, settings):
    """Copies of the candidates decided with settings' allowances, by name."""
    return {item.name: item for item in decide_all(copy.deepcopy(candidates), settings.decision)}


def test_a_candidate_its_probe_does_not_clear_is_not_judged_by_the_probes(motion_blurred):
    probe, ranked = motion_blurred
    candidates = copy.deepcopy(ranked)
    lens = next(item for item in candidates if item.name == "lens_distortion")
    # Significant through other evidence (an absorption refit sees a distortion the fit bent
    # into the geometry, which the probes cannot).
    lens.add(Evidence("absorption", "lens_distortion", 0.5, 0.0, True, "absorbed", {}))
    gather_checks(probe, candidates)
    # Where its probe clears, the probes' comparison vetoes it (the blur takes its place) ...
    assert _decided(candidates, SETTINGS)["lens_distortion"].status == "vetoed"
    # ... under allowances its probe does not clear, the check does not speak to it; but beside
    # the motion blur its probe makes significant, the absorption measured alone does not count
    # either (the distortion refit takes back part of the blur the fit bent into the geometry).
    high = DiagnoseConfig(bootstrap_samples=200)
    high.decision.probe_allowance = {**high.decision.probe_allowance, "lens_distortion": 0.95}
    decided = _decided(candidates, high)
    assert decided["motion_blur"].significant, decided["motion_blur"].why
    assert not decided["lens_distortion"].significant
    assert "void beside motion_blur" in decided["lens_distortion"].evidence_of("absorption").void
    # Where no confuser is significant (the blurs' and the pose's allowances out of reach too),
    # the absorption decides, unjudged by the probes.
    confusers = {name: 0.95 for name in ("motion_blur", "defocus_blur", "pose_error")}
    high.decision.probe_allowance = {**high.decision.probe_allowance, **confusers}
    high.decision.beyond_confusers_allowance = {
        **high.decision.beyond_confusers_allowance,
        **confusers,
    }
    decided = _decided(candidates, high)["lens_distortion"]
    assert decided.significant and decided.decided_by == "absorption", decided.why
    check = decided.evidence_of("specificity")
    assert check.passed and check.details.get("not_judged"), check.reason


def gather_checks(probe, candidates, settings=SETTINGS):
    for item in geometric_specificity(probe, candidates, settings):
        next(candidate for candidate in candidates if candidate.name == item.candidate).add(item)


def test_a_candidate_named_only_under_another_calibration_is_checked(motion_blurred):
    """The case built to fool the gate: diagnosed with a pose allowance its probe does not
    clear, the pose imitation of a motion blur is not significant; a calibration with a lower
    allowance (a leave-one-scene-out one) names it, and must find its check in the stored
    evidence, judged with its own allowances."""
    probe, ranked = motion_blurred
    strict = DiagnoseConfig(bootstrap_samples=200)
    strict.decision.probe_allowance = {**strict.decision.probe_allowance, "pose_error": 0.95}
    candidates = copy.deepcopy(ranked)
    for candidate in candidates:
        decide(candidate, strict.decision)
    pose = next(item for item in candidates if item.name == "pose_error")
    assert not pose.significant
    gather_checks(probe, candidates, strict)
    # Stored as diagnosis.json stores it, and re-decided from the JSON.
    stored = Diagnosis(candidates=candidates).to_json()
    lenient = DiagnoseConfig(bootstrap_samples=200)
    lenient.decision.probe_allowance = {**lenient.decision.probe_allowance, "pose_error": 0.02}
    redecided = {item.name: item for item in redecide(stored, lenient).candidates}
    pose = redecided["pose_error"]
    check = pose.evidence_of("specificity")
    assert check is not None and not check.passed, check.reason
    assert check.threshold == pytest.approx(0.02)
    assert pose.status == "vetoed" and "motion_blur" in pose.why
    assert redecided["motion_blur"].significant
