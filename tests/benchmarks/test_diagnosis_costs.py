"""benchmarks/diagnosis_costs.py: the diagnosis' pieces timed on a fitted run, and the lens
refit measured against its control and against the fit."""

from __future__ import annotations

import json

from benchmarks import diagnosis_costs
from recon.effects.registry import MODEL_EFFECTS


def test_every_probe_is_timed_and_the_lens_refit_is_measured_both_ways(tiny_run, capsys):
    assert diagnosis_costs.main([str(tiny_run), "--lens-control", "--threads", "1"]) == 0
    (record,) = json.loads(capsys.readouterr().out)
    assert set(record["probes"]) == set(MODEL_EFFECTS)
    # One column per parameter element, a per-view parameter counted once: the response curve
    # has its exponent and 16 LUT values, exposure one gain per view.
    assert record["probes"]["response_curve"]["columns"] == 17
    assert record["probes"]["exposure"]["columns"] == 1
    assert all(item["seconds"] > 0 for item in record["probes"].values())
    assert record["sky_visibility_seconds"] > 0
    control = record["lens_control"]
    for key in ("against_control", "against_fit", "control_against_fit"):
        low, high = control[key]["interval"]
        assert -10 < low <= high < 1 and -10 < control[key]["reduction"] < 1
    # The three are ratios of the same held-out errors: lens/fit = control/fit x lens/control.
    fit = 1 - control["against_fit"]["reduction"]
    chained = (1 - control["control_against_fit"]["reduction"]) * (
        1 - control["against_control"]["reduction"]
    )
    assert abs(fit - chained) < 2e-3
