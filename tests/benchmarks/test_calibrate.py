"""benchmarks/calibrate.py: allowances are twice the largest clean reduction, floored, and the
config fragment it writes carries its provenance and loads as the diagnose section."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from benchmarks import calibrate
from recon.config import from_dict
from recon.config.run_config import RunConfig
from recon.diagnose.records import Candidate, Diagnosis, Evidence


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
        _run(tmp_path / "b", pose=0.08, vignetting_absorption=0.012, share=-0.02, relight=0.001),
    ]
    out = tmp_path / "calibration.yaml"
    assert calibrate.main([str(run) for run in runs] + ["--stored", "--write", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["runs"] == 2
    assert printed["probe_allowance"]["pose_error"] == pytest.approx(0.16)
    # Below the floor: minimum_share.
    assert printed["probe_allowance"]["vignetting"] == pytest.approx(0.02)
    assert printed["absorption_allowance"]["vignetting"] == pytest.approx(0.024)
    assert printed["relight_allowance"]["response_curve"] == pytest.approx(0.06)
    assert printed["visibility_share_largest"] == pytest.approx(0.03)
    text = out.read_text()
    assert "# commit:" in text and "config_hash" in text and "seed 0" in text
    config = from_dict(yaml.safe_load(text), RunConfig)
    assert config.diagnose.decision.probe_allowance == {"pose_error": pytest.approx(0.16)}
    assert config.diagnose.decision.relight_allowance == pytest.approx(0.06)
