"""benchmarks/synth.py --quick (smoke test): both sections at toy size."""

from __future__ import annotations

import json

import torch

from benchmarks import synth


def test_quick_mode_runs(tmp_path, capsys):
    threads = torch.get_num_threads()
    try:
        report = synth.main(["--quick", "--out", str(tmp_path / "bench.json")])
    finally:
        torch.set_num_threads(threads)
    printed = json.loads(capsys.readouterr().out)
    assert printed == report == json.loads((tmp_path / "bench.json").read_text())
    own = report["own"]
    assert own["views"] == 3 and own["wall_s"] > 0 and own["runs"] == 1
    assert set(own["split_s_of_median_run"]) == {"render", "effects", "writing", "other"}
    assert own["split_s_of_median_run"]["render"] > 0
    assert own["split_s_of_median_run"]["effects"] > 0
    mitsuba = report["mitsuba"]
    if "skipped" not in mitsuba:
        assert mitsuba["render_s_per_view"] > 0 and mitsuba["sample"]["mitsuba_render_s"] > 0
        assert mitsuba["full_run"]["views"] == 2
