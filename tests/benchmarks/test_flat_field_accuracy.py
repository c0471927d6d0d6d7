"""benchmarks/flat_field_accuracy.py: the flat-field measurement against data_synth's realised
falloff, with and without sensor noise."""

from __future__ import annotations

import json

from benchmarks import flat_field_accuracy


def test_the_measured_corner_falloff_matches_the_world_s(capsys):
    assert flat_field_accuracy.main(["--draws", "2"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["noise_free"]["draws"]) == 2
    # The draws are real falloffs (the corner well below 1), read to within a fraction of 1 %.
    assert all(draw["corner_falloff"] < 0.9 for draw in summary["noise_free"]["draws"])
    assert summary["noise_free"]["corner_relative_error_max"] < 0.005
    assert summary["noisy"]["corner_relative_error_max"] < 0.05
