"""Local sweeps of tiny trials: tables, run folders, a failing trial, an interrupt and --resume."""

from __future__ import annotations

import json

from sweep_helpers import metrics_by_trial, records, three_trials

from recon.cli import main
from recon.config import load_config
from recon.config.run_config import RunConfig


def test_a_local_sweep_of_three_trials(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["sweep", str(three_trials(tmp_path, out))]) == 0
    assert "3 run, 0 kept, 0 failed" in capsys.readouterr().out
    found = records(out)
    assert [record["parameters"]["case"] for record in found] == [
        "fit.geometry.steps=1",
        "fit.geometry.steps=3",
        "fit.texture.steps=1",
    ]
    for record in found:
        assert record["status"] == "ok" and record["error"] is None
        run = out / "trials" / record["trial_id"] / "run"
        # An ordinary run folder, made with the trial's overrides ...
        config = load_config(run / "config.resolved.yaml", RunConfig)
        history = [json.loads(line) for line in (run / "history.jsonl").read_text().splitlines()]
        geometry_steps = [item for item in history if item["stage"] == "geometry"]
        assert geometry_steps[-1]["step"] == config.fit.geometry.steps - 1
        # ... whose fit's last record is the collected metric.
        assert record["metrics"]["fit.loss"] == history[-1]["loss"]
        assert (run / "mesh" / "model.obj").exists()
    steps = [
        load_config(out / "trials" / r["trial_id"] / "run" / "config.resolved.yaml", RunConfig)
        for r in found
    ]
    assert [config.fit.geometry.steps for config in steps] == [1, 3, 3]
    assert [config.fit.texture.steps for config in steps] == [2, 2, 1]
    # More geometry steps fit better (a real property of the trials, not of the tables).
    assert found[1]["metrics"]["fit.loss"] < found[0]["metrics"]["fit.loss"]
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert csv_lines[0].split(",")[:3] == ["trial_id", "status", "case"]
    assert len(csv_lines) == 4
    markdown = (out / "results.md").read_text()
    assert "3 trials, 0 failed" in markdown and markdown.count("| ok |") == 3
    html = (out / "summary.html").read_text()
    assert html.count("data:image/png;base64,") == 2  # fit.loss and fit.psnr_linear vs case
    manifest = json.loads((out / "sweep.json").read_text())
    assert [trial["trial_id"] for trial in manifest["trials"]] == [r["trial_id"] for r in found]


def test_a_failing_trial_is_recorded_and_the_sweep_goes_on(tmp_path, capsys):
    out = tmp_path / "sweep"
    sweep = three_trials(
        tmp_path,
        out,
        cases=[
            ["fit.geometry.steps=1"],
            ["fit.geometry.resolutions=[-4]"],
            ["fit.texture.steps=1"],
        ],
    )
    assert main(["sweep", str(sweep)]) == 1
    assert "0 kept, 1 failed" in capsys.readouterr().out
    statuses = [(record["status"], record["error"]) for record in records(out)]
    assert [status for status, _ in statuses] == ["ok", "failed", "ok"]
    assert "fit.geometry.resolutions" in statuses[1][1]
    failed_folder = out / "trials" / records(out)[1]["trial_id"]
    assert "Traceback" in (failed_folder / "error.txt").read_text()
    assert "1 failed" in (out / "results.md").read_text()


def test_an_interrupted_sweep_resumes_from_the_checkpoints(tmp_path, monkeypatch, capsys):
    whole = tmp_path / "whole"
    assert main(["sweep", str(three_trials(tmp_path, whole))]) == 0

    import recon.optimize.geometry_stage as geometry_stage

    real_sample_views = geometry_stage.sample_views
    calls = {"count": 0}

    def interrupt_in_the_second_trial(*args, **kwargs):
        # Trial 1 fits 1 geometry step; trial 2's third step is interrupted (Ctrl-C), after
        # its checkpoints of steps 1 and 2 (checkpoint_every: 1).
        calls["count"] += 1
        if calls["count"] == 4:
            raise KeyboardInterrupt
        return real_sample_views(*args, **kwargs)

    monkeypatch.setattr(geometry_stage, "sample_views", interrupt_in_the_second_trial)
    interrupted = tmp_path / "interrupted"
    sweep = three_trials(tmp_path, interrupted)
    assert main(["sweep", str(sweep)]) == 130
    assert "--resume" in capsys.readouterr().err
    first, second, third = json.loads((interrupted / "sweep.json").read_text())["trials"]
    assert [record["trial_id"] for record in records(interrupted)] == [first["trial_id"]]
    second_folder = interrupted / "trials" / second["trial_id"]
    assert (second_folder / "run" / "checkpoints" / "geometry.pt").exists()
    assert not (second_folder / "result.json").exists()
    assert not (interrupted / "trials" / third["trial_id"]).exists()
    kept = (interrupted / "trials" / first["trial_id"] / "result.json").stat().st_mtime_ns

    monkeypatch.setattr(geometry_stage, "sample_views", real_sample_views)
    # Without --resume the folder is refused (never overwritten).
    assert main(["sweep", str(sweep)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["sweep", str(sweep), "--resume"]) == 0
    assert "2 run, 1 kept, 0 failed" in capsys.readouterr().out
    assert (interrupted / "trials" / first["trial_id"] / "result.json").stat().st_mtime_ns == kept
    resumed = {record["trial_id"]: record["resumed"] for record in records(interrupted)}
    assert resumed == {first["trial_id"]: False, second["trial_id"]: True, third["trial_id"]: False}
    # The resumed sweep gives the numbers of the uninterrupted one.
    assert metrics_by_trial(interrupted) == metrics_by_trial(whole)


def test_a_killed_sweep_process_resumes(tmp_path, capsys):
    """SIGKILL (no clean-up at all) while the second trial fits, then --resume."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from sweep_helpers import REPO_ROOT

    cases = [["fit.geometry.steps=1"], ["fit.geometry.steps=20"]]
    killed = tmp_path / "killed"
    sweep = three_trials(tmp_path, killed, cases=cases)
    environment = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    process = subprocess.Popen(
        [sys.executable, "-m", "recon.cli", "sweep", str(sweep)],
        env=environment,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        checkpoint = None
        while time.monotonic() < deadline and process.poll() is None:
            manifest = killed / "sweep.json"
            if manifest.exists():
                second = json.loads(manifest.read_text())["trials"][1]["trial_id"]
                path = killed / "trials" / second / "run" / "checkpoints" / "geometry.pt"
                if path.exists():
                    checkpoint = path
                    break
            time.sleep(0.02)
        assert checkpoint is not None, "the second trial never wrote a checkpoint"
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    trial_folder = checkpoint.parents[2]
    assert not (trial_folder / "result.json").exists()
    assert len(records(killed)) == 1  # the first trial's record survived the kill intact

    assert main(["sweep", str(sweep), "--resume"]) == 0
    assert "1 run, 1 kept, 0 failed" in capsys.readouterr().out
    assert [record["resumed"] for record in records(killed)] == [False, True]
    whole = tmp_path / "whole"
    assert main(["sweep", str(three_trials(tmp_path, whole, cases=cases))]) == 0
    assert metrics_by_trial(killed) == metrics_by_trial(whole)
