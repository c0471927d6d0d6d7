"""benchmarks/calibrate.py: allowances are twice the largest clean statistic (the probes' point
reduction, the absorption's and relight probe's lower bound), floored; the config fragment it
writes carries its provenance and loads as the diagnose section."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from benchmarks import calibrate
from recon.config import from_dict
from recon.config.run_config import DecisionConfig, RunConfig
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.errors import ReconError


def _candidate(name: str, **reductions) -> Candidate:
    candidate = Candidate(name)
    for kind, reduction in reductions.items():
        details = {"reduction": reduction, "interval": [reduction - 0.01, reduction + 0.01]}
        candidate.add(Evidence(kind, name, reduction - 0.01, math.nan, False, kind, details))
    return candidate


def _run(
    folder: Path, pose: float, vignetting_absorption: float, share: float, relight: float
) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.resolved.yaml").write_text("name: clean\n")
    candidates = [
        _candidate("pose_error", probe=pose),
        _candidate("vignetting", probe=0.001, absorption=vignetting_absorption),
        _candidate("response_curve", probe=0.0, relight=relight),
    ]
    diagnosis = Diagnosis(candidates=candidates, gap={"visibility_fingerprint": {"share": share}})
    (folder / "diagnosis.json").write_text(json.dumps(diagnosis.to_json()))
    return folder


def test_allowances_from_stored_diagnoses(tmp_path, capsys):
    runs = [
        _run(tmp_path / "a", pose=0.05, vignetting_absorption=0.004, share=0.03, relight=0.03),
        _run(tmp_path / "b", pose=0.08, vignetting_absorption=0.022, share=-0.02, relight=0.001),
    ]
    out = tmp_path / "calibration.yaml"
    assert calibrate.main([str(run) for run in runs] + ["--stored", "--write", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["runs"] == 2
    assert printed["probe_allowance"]["pose_error"] == pytest.approx(0.16)
    # Below the floor: minimum_share.
    assert printed["probe_allowance"]["vignetting"] == pytest.approx(0.02)
    # Absorption and relight: twice the largest lower bound (the reduction less 0.01 here).
    assert printed["absorption_allowance"]["vignetting"] == pytest.approx(0.024)
    assert printed["relight_allowance"]["response_curve"] == pytest.approx(0.04)
    assert printed["visibility_share_largest"] == pytest.approx(0.03)
    text = out.read_text()
    assert "# commit:" in text and "config_hash" in text and "seed 0" in text
    config = from_dict(yaml.safe_load(text), RunConfig)
    assert config.diagnose.decision.probe_allowance == {"pose_error": pytest.approx(0.16)}
    assert config.diagnose.decision.relight_allowance == pytest.approx(0.04)


def _evidence(kind: str, name: str, low: float, reduction: float) -> Evidence:
    details = {"reduction": reduction, "interval": [low, 2 * reduction - low]}
    return Evidence(kind, name, low, math.nan, False, f"{kind}: lower bound", details)


def _diagnosis(pose: tuple[float, float], relight: tuple[float, float]) -> dict:
    """A diagnosis with a pose probe and a relight split's response probe, each given as
    (lower bound, point reduction)."""
    pose_error = Candidate("pose_error")
    pose_error.add(_evidence("probe", "pose_error", *pose))
    response = Candidate("response_curve")
    response.add(_evidence("probe", "response_curve", -0.01, 0.001))
    response.add(_evidence("relight", "response_curve", *relight))
    return Diagnosis(candidates=[pose_error, response]).to_json()


# Clean calibration fits: a path-traced-like one whose pose probe removes 10 % at its point but
# whose bootstrap interval reaches down to 2 % (a misfit the rotations partly absorb), and one
# whose relight probe's point reduction is 4.5 % (the clean fit's baked shading) but whose lower
# bound is 1.2 %.
CLEAN = [
    _diagnosis(pose=(0.02, 0.10), relight=(0.002, 0.01)),
    _diagnosis((0.0, 0.01), (0.012, 0.045)),
]


def _named(diagnosis: dict, thresholds: dict) -> list[str]:
    from benchmarks.blind.decide import redecide_with, significant_effects

    return significant_effects(redecide_with(diagnosis, thresholds))


def test_each_rule_is_calibrated_on_the_statistic_it_is_compared_with():
    thresholds = calibrate.calibrate_thresholds(CLEAN)
    assert thresholds["relight"] == pytest.approx(2 * 0.012)  # the lower bound's
    assert thresholds["probe.pose_error"] == pytest.approx(2 * 0.10)  # the point reduction's
    # 'reduction' everywhere: the relight allowance from a point estimate.
    assert calibrate.calibrate_thresholds(CLEAN, statistic="reduction")["relight"] == (
        pytest.approx(0.09)
    )
    with pytest.raises(ReconError, match="calibration statistic.*'median'"):
        calibrate.calibrate_thresholds(CLEAN, statistic="median")


def test_an_injected_response_curve_with_a_relight_split_is_found():
    # The relight probe removes 8 % (lower bound 3.6 %): above twice the clean lower bounds,
    # below twice the clean point reductions (the rule that missed it).
    injected = _diagnosis(pose=(-0.01, 0.01), relight=(0.036, 0.08))
    assert _named(injected, calibrate.calibrate_thresholds(CLEAN)) == ["response_curve"]
    assert _named(injected, calibrate.calibrate_thresholds(CLEAN, statistic="reduction")) == []


def test_a_clean_path_traced_like_fit_gets_no_pose_error():
    # A held-out clean fit of the same kind: its pose lower bound (6 %) clears twice the clean
    # lower bounds (4 %), not twice the clean point reductions (20 %).
    clean = _diagnosis(pose=(0.06, 0.12), relight=(0.004, 0.02))
    assert _named(clean, calibrate.calibrate_thresholds(CLEAN)) == []
    assert _named(clean, calibrate.calibrate_thresholds(CLEAN, statistic="lower_bound")) == [
        "pose_error"
    ]


def _geometric(pose: tuple[float, float], on_top: tuple[float, float]) -> dict:
    """A diagnosis whose pose probe (lower bound, point) was compared with a motion blur's:
    on_top is what the pose probe keeps on top of the blur's probe (lower bound, point)."""

    def entry(low, point):
        return {"reduction": point, "interval": [low, 2 * point - low]}

    pose_error = Candidate("pose_error")
    pose_error.add(_evidence("probe", "pose_error", *pose))
    record = {
        "candidate": "pose_error",
        "confuser": "motion_blur",
        "alone": entry(*pose),
        "confuser_alone": entry(0.05, 0.09),
        "on_top_of_confuser": entry(*on_top),
        "confuser_on_top": entry(-0.02, 0.01),
        "allowance": 0.1,
        "confuser_allowance": 0.1,
    }
    details = {"pairs": [record], "margin": 0.0, "probe_lower_bound": pose[0]}
    pose_error.add(Evidence("specificity", "pose_error", on_top[0], 0.1, True, "", details))
    return Diagnosis(candidates=[pose_error]).to_json()


def test_the_beyond_allowance_is_calibrated_on_what_a_probe_keeps_over_its_confusers():
    # A poor clean fit (the path-traced teapot): its pose probe removes 10.5 % alone, 2.2 % on
    # top of the motion blur's probe; a good one removes little either way.
    clean = [_geometric((0.044, 0.105), (-0.031, 0.022)), _geometric((0.0, 0.02), (-0.01, 0.0))]
    thresholds = calibrate.calibrate_thresholds(clean)
    assert thresholds["probe.pose_error"] == pytest.approx(0.21)
    assert thresholds["beyond.pose_error"] == pytest.approx(0.044)
    # A pose error below the poor fit's bar alone (16.8 % < 21 %) but 12.5 % beyond the blur.
    assert _named(_geometric((0.168, 0.263), (0.125, 0.168)), thresholds) == ["pose_error"]
    # Another poor clean fit, scored on these thresholds: nothing beyond its confusers.
    assert _named(_geometric((0.06, 0.12), (-0.02, 0.03)), thresholds) == []
    # The section a config takes carries the allowance.
    section = calibrate.calibration_record(thresholds, [], {})["diagnose"]["decision"]
    assert section["beyond_confusers_allowance"]["pose_error"] == pytest.approx(0.044)


def _bounce(excess: float, p_value: float, strength: float) -> dict:
    """A diagnosis whose interreflection candidate holds only bounce evidence."""
    interreflection = Candidate("interreflection")
    details = {"p_value": p_value, "strength": strength, "correlation": excess + 0.1}
    interreflection.add(Evidence("bounce", "interreflection", excess, 0.02, False, "", details))
    return Diagnosis(candidates=[interreflection]).to_json()


def test_the_bounce_floor_rises_only_for_clean_cases_the_floor_alone_keeps_silent():
    # The path-traced bunny's clean case follows the predicted bounce (excess 0.072) with a
    # strength no bounce can have (4.2): silent at any floor, it does not raise the floor. A
    # clean case that passes the placebo level and the strength does: twice its excess.
    floor = DecisionConfig().bounce_minimum
    refused = _bounce(0.072, 0.006, 4.2)
    assert calibrate.calibrate_thresholds([refused])["bounce"] == pytest.approx(floor)
    assert calibrate.calibrate_thresholds([_bounce(0.045, 0.3, 0.5)])["bounce"] == floor
    passing = _bounce(0.045, 0.006, 0.5)
    thresholds = calibrate.calibrate_thresholds([refused, passing])
    assert thresholds["bounce"] == pytest.approx(max(floor, 0.09))
    # A held-out case at 0.07 is named under the floor, not under the raised threshold.
    held_out = _bounce(0.07, 0.006, 0.6)
    assert _named(held_out, calibrate.calibrate_thresholds([refused])) == ["interreflection"]
    assert _named(held_out, thresholds) == []
    # Interreflection present in a calibration case: its evidence measures the effect.
    present = [("interreflection",)]
    assert calibrate.calibrate_thresholds([passing], present)["bounce"] == floor
    section = calibrate.calibration_record(thresholds, [], {})["diagnose"]["decision"]
    assert section["bounce_minimum"] == pytest.approx(0.09)


def _blur(reduction: float, edge_ratio: float) -> dict:
    """A clean diagnosis whose defocus probe removes `reduction` (lower bound 0.01 less) and
    whose edge null (recon.diagnose.edge_width) reads `edge_ratio` of the probe's widening in
    the data's edges (it passes at 0.5)."""
    defocus = Candidate("defocus_blur")
    defocus.add(_evidence("probe", "defocus_blur", reduction - 0.01, reduction))
    defocus.add(Evidence("edge_blur", "defocus_blur", edge_ratio, 0.5, edge_ratio >= 0.5, "", {}))
    return Diagnosis(candidates=[defocus]).to_json()


def test_a_blur_allowance_rests_on_the_clean_probes_its_null_lets_clear():
    # The path-traced teapot's clean silhouette misfit: a blur probe removes 10 %, but the
    # data's edges show only 0.24 of the widening (the null vetoes it at any allowance). The
    # path-traced bob's clean edges pass the null with a 2 % reduction: that bounds the bar.
    misfit, sharp_pass = _blur(0.10, 0.24), _blur(0.02, 0.9)
    thresholds = calibrate.calibrate_thresholds([misfit, sharp_pass])
    assert thresholds["probe.defocus_blur"] == pytest.approx(0.04)
    # A defocus of the held-out scene at 18 % (lower bound 17 %), its edges widened: found
    # under this bar, missed under twice the misfit's.
    blurred = _blur(0.18, 0.7)
    assert _named(blurred, thresholds) == ["defocus_blur"]
    assert _named(blurred, {**thresholds, "probe.defocus_blur": 2 * 0.10}) == []
    # Where the null vetoes every clean probe, nothing says how high the bar must be: all of
    # them count, as before.
    assert calibrate.calibrate_thresholds([misfit])["probe.defocus_blur"] == pytest.approx(0.2)
    assert calibrate.probe_vetoed_by_null(Diagnosis.from_json(misfit).candidates[0])


def test_the_command_follows_the_same_null_rule(tmp_path, capsys):
    runs = []
    for name, diagnosis in (("misfit", _blur(0.10, 0.24)), ("sharp", _blur(0.02, 0.9))):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "config.resolved.yaml").write_text("name: clean\n")
        stored = {**diagnosis, "gap": {"visibility_fingerprint": {"share": 0.0}}}
        (folder / "diagnosis.json").write_text(json.dumps(stored))
        runs.append(str(folder))
    assert calibrate.main(runs + ["--stored"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["probe_allowance"]["defocus_blur"] == pytest.approx(0.04)
    assert calibrate.main(runs[:1] + ["--stored"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["probe_allowance"]["defocus_blur"] == pytest.approx(0.2)
