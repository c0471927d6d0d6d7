"""recon-bench time-diagnosis: the fit and the diagnosis back to back, with the ratio the
issue's cost target reads, the stage timings and the load average they were measured at."""

from __future__ import annotations

import json

from benchmarks.time_diagnosis import main


def test_time_diagnosis_prints_the_ratio_stages_and_load(tiny_run, tmp_path, capsys):
    assert main([str(tiny_run), "--out", str(tmp_path), "--threads", "1", "--refit", "none"]) == 0
    (result,) = json.loads(capsys.readouterr().out)
    assert result["refit"] == "none" and result["refit_seconds"] is None
    assert result["fit_seconds"] > 0 and result["diagnose_seconds"] > 0
    # Both printed times are rounded to 0.01 s, which matters for a fit this tiny: the share
    # computed from the unrounded times lies between the extremes the roundings allow.
    fit, diagnosis, half = result["fit_seconds"], result["diagnose_seconds"], 0.005
    low, high = (diagnosis - half) / (fit + half), (diagnosis + half) / max(fit - half, 1e-9)
    assert low - 0.001 <= result["diagnosis_share_of_fit"] <= high + 0.001
    assert {"probes", "gap", "where"} <= set(result["stage_seconds"])
    assert set(result["load_average"]) == {"before_fit", "after_fit", "after_diagnosis"}
    # the copy was fitted and diagnosed, the source left alone
    copy = tmp_path / tiny_run.parent.name / tiny_run.name
    assert (copy / "diagnosis.json").exists() and (copy / "mesh").is_dir()


def test_time_diagnosis_repeats_report_the_median_of_the_runs(tiny_run, tmp_path, capsys):
    arguments = [str(tiny_run), "--out", str(tmp_path), "--threads", "1", "--refit", "none"]
    assert main([*arguments, "--repeats", "3"]) == 0
    (result,) = json.loads(capsys.readouterr().out)
    runs = result["diagnose_seconds_runs"]
    assert len(runs) == 3 and all(seconds > 0 for seconds in runs)
    assert result["diagnose_seconds"] == sorted(runs)[1]
    assert result["stage_seconds"]["probes"] >= 0
