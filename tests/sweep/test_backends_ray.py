"""The Ray backend on a local Ray instance this module starts with 2 CPUs (once: start-up takes
seconds): 3 tiny trials, the same numbers as the local backend for the same seeds."""

from __future__ import annotations

import pytest
from sweep_helpers import metrics_by_trial, records, three_trials

from recon.cli import main

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_a_ray_sweep_of_three_trials_matches_the_local_one(tmp_path, capsys, local_ray):
    on_ray = tmp_path / "ray"
    sweep = three_trials(tmp_path, on_ray, max_concurrent=2)
    assert main(["sweep", str(sweep), "--backend", "ray"]) == 0
    assert "3 run, 0 kept, 0 failed" in capsys.readouterr().out
    # The sweep used the test's Ray (2 CPUs) and left it running.
    assert local_ray.is_initialized()
    assert local_ray.cluster_resources()["CPU"] == 2
    found = records(on_ray)
    assert [record["status"] for record in found] == ["ok"] * 3
    # Written in trial order whatever order Ray finished them in.
    local = tmp_path / "local"
    assert main(["sweep", str(three_trials(tmp_path, local))]) == 0
    assert [record["trial_id"] for record in found] == [r["trial_id"] for r in records(local)]
    # Same seeds, same thread count: identical numbers, not merely close ones.
    assert metrics_by_trial(on_ray) == metrics_by_trial(local)
    for record in found:
        assert (on_ray / "trials" / record["trial_id"] / "run" / "mesh" / "model.obj").exists()


def test_ray_records_a_failing_trial_and_resumes(tmp_path, capsys, local_ray):
    out = tmp_path / "sweep"
    sweep = three_trials(
        tmp_path,
        out,
        cases=[["fit.geometry.steps=1"], ["fit.geometry.resolutions=[-4]"]],
    )
    assert main(["sweep", str(sweep), "--backend", "ray"]) == 1
    assert [record["status"] for record in records(out)] == ["ok", "failed"]
    assert "fit.geometry.resolutions" in records(out)[1]["error"]
    capsys.readouterr()
    # On --resume the finished trial is kept and the failed one runs again.
    assert main(["sweep", str(sweep), "--backend", "ray", "--resume"]) == 1
    assert "1 run, 1 kept, 1 failed" in capsys.readouterr().out


def test_a_killed_ray_worker_is_retried_and_resumes_the_trial(tmp_path, capsys, local_ray):
    """SIGKILL the worker process mid-fit: Ray retries the task, which resumes the trial from
    its checkpoint, and the sweep's numbers are those of an uninterrupted local run."""
    import json
    import os
    import signal
    import threading
    import time

    cases = [["fit.geometry.steps=20"]]
    out = tmp_path / "ray"
    sweep = three_trials(tmp_path, out, cases=cases)
    killed = {}

    def kill_the_worker_after_a_checkpoint():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            folders = list((out / "trials").glob("*")) if (out / "trials").exists() else []
            for folder in folders:
                running = folder / "running.json"
                if (folder / "run" / "checkpoints" / "geometry.pt").exists() and running.exists():
                    killed["pid"] = json.loads(running.read_text())["pid"]
                    os.kill(killed["pid"], signal.SIGKILL)
                    return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_the_worker_after_a_checkpoint)
    killer.start()
    try:
        assert main(["sweep", str(sweep), "--backend", "ray"]) == 0
    finally:
        killer.join()
    assert "pid" in killed, "the trial never wrote a checkpoint"
    (record,) = records(out)
    assert record["status"] == "ok" and record["resumed"] is True
    assert record["pid"] != killed["pid"]  # finished by the retry, in another worker
    local = tmp_path / "local"
    assert main(["sweep", str(three_trials(tmp_path, local, cases=cases))]) == 0
    assert metrics_by_trial(out) == metrics_by_trial(local)
