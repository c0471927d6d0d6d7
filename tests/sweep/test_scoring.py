"""recon.sweep.scoring: a blind diagnosis scored against the withheld truth."""

from __future__ import annotations

from pathlib import Path

import pytest

from recon.sweep.scoring import NONE, BenchCase, parameter_errors, score_case


def test_parameter_errors_compare_like_with_like():
    true_train = [1.0, 2.0, 0.5, 1.0]
    truth = {
        "realised": {
            "train": [{"name": "exposure", "parameters": {"ratios": true_train}}],
            "test": [
                {
                    "name": "vignetting",
                    "parameters": {"corner_falloff": [0.6, 0.6], "half_radius_falloff": [0.9, 0.9]},
                },
                {"name": "response_curve", "parameters": {"effective_exponent": 0.8}},
            ],
        }
    }
    # The refit's ratios are the truth up to a common scale (the fit absorbed it) and one view
    # 10 % off; the probe's vignetting and gamma come from the held-out views.
    refit_ratios = [3 * value for value in true_train]
    refit_ratios[1] *= 1.1
    diagnosis = {
        "candidates": [
            {
                "name": "exposure",
                "significant": False,
                "parameters": {"ratios": [9.0, 9.0, 9.0, 9.0]},
            },
            {
                "name": "vignetting",
                "significant": False,
                "parameters": {"corner_falloff": 0.63, "half_radius_falloff": 0.891},
            },
            {
                "name": "response_curve",
                "significant": False,
                "parameters": {"effective_gamma": 0.85},
            },
        ],
        "refits": [
            {
                "effects": ["exposure", "response_curve"],
                # Under one light the refit cannot pin a curve: its exponent is not scored.
                "parameters": {
                    "exposure": {"ratios": refit_ratios},
                    "response_curve": {"effective_gamma": 1.0},
                },
            }
        ],
    }
    errors = parameter_errors(diagnosis, truth)
    # Normalised by the geometric mean, the 10 % view error spreads to ~2.4 % on the others.
    assert errors["exposure_ratio_max"] == pytest.approx(1.1**0.75 - 1, rel=1e-6)
    assert errors["exposure_ratio_median"] == pytest.approx(1 - 1.1**-0.25, rel=1e-6)
    assert errors["vignetting_corner_falloff"] == pytest.approx(0.05)
    assert errors["vignetting_half_radius_falloff"] == pytest.approx(0.01)
    assert errors["response_gamma_absolute"] == pytest.approx(0.05)


def _diagnosis(significant: list[str], others: list[str] = ()) -> dict:
    ranking = [{"name": name, "significant": True} for name in significant]
    ranking += [{"name": name, "significant": False} for name in others]
    refits = [{"closed_fraction": 0.8, "relight_closed_fraction": 0.5, "parameters": {}}]
    timings = {"diagnose_seconds": 2.0, "refit_seconds": 3.0}
    return {"candidates": ranking, "refits": refits if significant else [], "timings": timings}


def test_a_case_is_labelled_by_what_it_withholds():
    assert (BenchCase((), 100).label, BenchCase((), 100).kind) == (NONE, "clean")
    assert (BenchCase(("exposure",), 0).label, BenchCase(("exposure",), 0).kind) == (
        "exposure",
        "single",
    )
    pair = BenchCase(("exposure", "vignetting"), 1)
    assert (pair.label, pair.kind) == ("exposure+vignetting", "pair")


def test_score_case_reads_top1_pairs_and_false_positives():
    paths = Path("run")
    single = score_case(
        BenchCase(("vignetting",), 0),
        _diagnosis(["exposure", "vignetting"]),
        {"withheld": []},
        10.0,
        5.0,
        paths,
    )
    # Named, but not first: top-1 counts the first significant effect only.
    assert single["predicted_top"] == "exposure" and single["top1_correct"] is False
    assert single["both_found"] is None and single["false_positive"] is None
    assert single["closed_fraction"] == 0.8 and single["relight_closed_fraction"] == 0.5
    assert single["diagnosis_share_of_fit"] == pytest.approx(0.2)
    assert single["refit_share_of_fit"] == pytest.approx(0.3)
    assert single["run_folder"] == "run"
    pair = score_case(
        BenchCase(("exposure", "vignetting"), 1),
        _diagnosis(["white_balance", "vignetting", "exposure"]),
        {"withheld": []},
        10.0,
        5.0,
        paths,
    )
    assert pair["both_found"] is True and pair["top1_correct"] is False
    clean = score_case(
        BenchCase((), 100), _diagnosis([], ["exposure"]), {"withheld": []}, 10.0, 5.0, paths
    )
    assert clean["predicted_top"] == NONE and clean["top1_correct"] is True
    assert clean["false_positive"] is False and clean["closed_fraction"] is None
    noisy = score_case(
        BenchCase((), 101), _diagnosis(["exposure"]), {"withheld": []}, 10.0, 5.0, paths
    )
    assert noisy["false_positive"] is True and noisy["top1_correct"] is False


def test_white_balance_blur_and_motion_parameters_are_scored_like_for_like():
    true_gains = [[1.1, 1.0, 0.9], [0.95, 1.0, 1.05], [1.0, 1.0, 1.0], [0.9, 1.0, 1.1]]
    truth = {
        "realised": {
            "test": [
                {"name": "white_balance", "parameters": {"gains": true_gains}},
                {"name": "defocus_blur", "parameters": {"radius_px": 2.0}},
                {
                    "name": "motion_blur",
                    "parameters": {
                        "lengths_px": [2.0, 4.0, 3.0],
                        "angles_deg": [10.0, 175.0, 90.0],
                    },
                },
            ]
        }
    }
    # The probe's gains carry a common cast (the albedo's to the fit: not an error) and one
    # view's red 10 % off; the blur's disk radius is 1.8; the motion lines point the same way
    # modulo 180 degrees but for 5 degrees in one view and one length 25 % long.
    found_gains = [[1.2 * red, 1.0, 0.8 * blue] for red, _, blue in true_gains]
    found_gains[0][0] *= 1.1
    diagnosis = {
        "candidates": [
            {"name": "white_balance", "significant": False, "parameters": {"gains": found_gains}},
            {
                "name": "defocus_blur",
                "significant": False,
                "parameters": {"equivalent_disk_radius_px": 1.8, "sigma_px": 0.9},
            },
            {
                "name": "motion_blur",
                "significant": False,
                "parameters": {"lengths_px": [2.0, 5.0, 3.0], "angles_deg": [190.0, 0.0, 95.0]},
            },
        ]
    }
    errors = parameter_errors(diagnosis, truth)
    # Normalised by the geometric mean, the one 10 % red error spreads over the four views.
    assert errors["white_balance_gain_max"] == pytest.approx(1.1**0.75 - 1, rel=1e-6)
    assert errors["white_balance_gain_median"] == pytest.approx(0.0, abs=1e-9)
    assert errors["defocus_radius_relative"] == pytest.approx(0.1)
    assert errors["motion_length_relative_median"] == pytest.approx(0.0)
    assert errors["motion_angle_deg_median"] == pytest.approx(5.0)
    # Nothing recovered, nothing scored.
    assert parameter_errors({"candidates": []}, truth) == {}
