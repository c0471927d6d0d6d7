"""scripts/flat_field_accuracy.py: the flat-field measurement against data_synth's realised
falloff, with and without sensor noise."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_the_measured_corner_falloff_matches_the_world_s(capsys):
    path = REPO_ROOT / "scripts" / "flat_field_accuracy.py"
    spec = importlib.util.spec_from_file_location("flat_field_accuracy", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--draws", "2"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["noise_free"]["draws"]) == 2
    # The draws are real falloffs (the corner well below 1), read to within a fraction of 1 %.
    assert all(draw["corner_falloff"] < 0.9 for draw in summary["noise_free"]["draws"])
    assert summary["noise_free"]["corner_relative_error_max"] < 0.005
    assert summary["noisy"]["corner_relative_error_max"] < 0.05
