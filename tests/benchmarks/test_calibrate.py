"""benchmarks/calibrate.py: allowances are twice the largest clean reduction, floored."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks import calibrate


def _run(
    folder: Path, pose: float, vignetting_absorption: float, share: float, relight: float
) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.resolved.yaml").write_text("name: clean\n")
    ranking = [
        {"effect": "pose_error", "heldout_reduction": pose, "absorption": None},
        {"effect": "vignetting", "heldout_reduction": 0.001, "absorption": vignetting_absorption},
        {
            "effect": "response_curve",
            "heldout_reduction": 0.0,
            "absorption": None,
            "relight_reduction": relight,
        },
    ]
    diagnosis = {"ranking": ranking, "gap": {"visibility_fingerprint": {"share": share}}}
    (folder / "diagnosis.json").write_text(json.dumps(diagnosis))
    return folder


def test_allowances_from_stored_diagnoses(tmp_path, capsys):
    runs = [
        _run(tmp_path / "a", pose=0.05, vignetting_absorption=0.004, share=0.03, relight=0.03),
        _run(tmp_path / "b", pose=0.08, vignetting_absorption=0.012, share=-0.02, relight=0.001),
    ]
    assert calibrate.main([str(run) for run in runs] + ["--stored"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["runs"] == 2
    assert printed["probe_allowance"]["pose_error"] == pytest.approx(0.16)
    # Below the floor: MINIMUM_SHARE.
    assert printed["probe_allowance"]["vignetting"] == pytest.approx(0.02)
    assert printed["absorption_allowance"]["vignetting"] == pytest.approx(0.024)
    assert printed["relight_allowance"]["response_curve"] == pytest.approx(0.06)
    assert printed["visibility_share_largest"] == pytest.approx(0.03)
