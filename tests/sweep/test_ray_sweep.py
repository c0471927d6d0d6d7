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
