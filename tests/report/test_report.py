"""The report's text pieces: one-line parameter summaries."""

from __future__ import annotations

from recon.report.report import summarise_parameters


def test_parameter_summaries_keep_numbers_and_ranges():
    line = summarise_parameters(
        {
            "ratios": [1.0, 0.5, 2.0],
            "gamma": 0.81234,
            "pinned_view": None,
            "model": "x_distorted = x (1 + k1 r^2 + k2 r^4), normalised coordinates",
            "rows": [[1.0, 2.0]],
            "unit": "stops",
            "held": True,
        }
    )
    assert line == "ratios 0.5..2 (3), gamma 0.812, unit stops"
