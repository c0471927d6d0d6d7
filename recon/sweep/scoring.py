"""Scoring of a blind diagnosis against the withheld truth, read only after the diagnosis.

One case is a dataset with some effects withheld (none = clean) and a seed; its record says
whether the diagnosis named the withheld effect first (top-1), found both of a pair, stayed
silent on clean data, how much of the gap the refit closed, and how close the recovered
parameters came to the true ones. recon's diagnosis sweeps score every trial with it
(recon/sweep/trial.py), and so does the blind benchmark (benchmarks/diagnose_blind.py): it
lives here, below both, because recon never imports benchmarks.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

import torch

from recon.report.report import recovered_parameters

# The label of a case with nothing withheld, and the prediction of a diagnosis that names
# nothing significant.
NONE = "none"

# Each parameter error of parameter_errors and the effect whose cases it is scored on.
PARAMETER_OWNER = {
    "exposure_ratio_median": "exposure",
    "exposure_ratio_max": "exposure",
    "vignetting_corner_falloff": "vignetting",
    "vignetting_half_radius_falloff": "vignetting",
    "response_gamma_absolute": "response_curve",
    "white_balance_gain_median": "white_balance",
    "white_balance_gain_max": "white_balance",
    "defocus_radius_relative": "defocus_blur",
    "motion_length_relative_median": "motion_blur",
    "motion_angle_deg_median": "motion_blur",
}


@dataclass
class BenchCase:
    """One dataset of the benchmark: the withheld effects (empty = clean) and a seed."""

    effects: tuple[str, ...]
    seed: int

    @property
    def label(self) -> str:
        return "+".join(self.effects) if self.effects else NONE

    @property
    def kind(self) -> str:
        return {0: "clean", 1: "single"}.get(len(self.effects), "pair")


def score_case(
    case: BenchCase,
    diagnosis: dict,
    truth: dict,
    fit_seconds: float,
    diagnose_seconds: float,
    run_folder: Path,
) -> dict:
    significant = [item["name"] for item in diagnosis["candidates"] if item["significant"]]
    top = significant[0] if significant else NONE
    record = {
        "case": case.label,
        "kind": case.kind,
        "seed": case.seed,
        "truth": list(case.effects),
        "predicted_top": top,
        "significant": significant,
        "top1_correct": (top in case.effects) if case.effects else top == NONE,
        "both_found": set(case.effects) <= set(significant[:3]) if len(case.effects) == 2 else None,
        "false_positive": bool(significant) if not case.effects else None,
        "closed_fraction": diagnosis["refits"][0]["closed_fraction"]
        if diagnosis["refits"]
        else None,
        "relight_closed_fraction": diagnosis["refits"][0].get("relight_closed_fraction")
        if diagnosis["refits"]
        else None,
        "fit_seconds": round(fit_seconds, 1),
        "diagnose_seconds": round(diagnose_seconds, 1),
        # Diagnosis alone (where + which) and the refit, as shares of the fit's time.
        "diagnosis_share_of_fit": diagnosis["timings"]["diagnose_seconds"] / max(fit_seconds, 1e-9),
        "refit_share_of_fit": diagnosis["timings"].get("refit_seconds", 0.0)
        / max(fit_seconds, 1e-9),
        "run_folder": str(run_folder),
    }
    record["parameter_error"] = parameter_errors(diagnosis, truth)
    return record


def parameter_errors(diagnosis: dict, truth: dict) -> dict:
    """Recovered vs true parameters where the two are comparable (keys: PARAMETER_OWNER):
    exposure ratios and white-balance red/blue gains per view (relative, normalised by their
    geometric mean over the views: the fit absorbed the overall scale and cast), the vignetting
    corner falloff and the falloff half-way to the corner (relative), the response curve's
    effective exponent (absolute), the defocus disk radius (relative) and the motion blur's
    per-view path length (relative) and direction (degrees modulo 180).

    Parameters come from the first refit that switched the effect on (fitted with the scene on
    the training views, compared with the truth of those views) and otherwise from the probe
    (fitted on the held-out views with the scene frozen, compared with theirs): a held-out
    probe inherits whatever the fitted albedo absorbed from the training views. The response
    curve's exponent always comes from the ranking (the relight split's estimate)."""
    errors = {}
    found = {
        effect: (parameters, "train" if source == "refit" else "test")
        for effect, source, parameters in recovered_parameters(diagnosis, significant_only=False)
    }
    realised_by_split = {
        split: {item["name"]: item["parameters"] for item in items}
        for split, items in truth.get("realised", {}).items()
    }

    def pair(name: str) -> tuple[dict, dict]:
        parameters, split = found.get(name, ({}, "test"))
        return parameters, realised_by_split.get(split, {}).get(name, {})

    model_exposure, true_exposure = pair("exposure")
    true_ratios = true_exposure.get("ratios")
    model_ratios = model_exposure.get("ratios")
    if true_ratios and model_ratios and len(true_ratios) == len(model_ratios):
        true_log = torch.tensor(true_ratios, dtype=torch.float64).log()
        model_log = torch.tensor(model_ratios, dtype=torch.float64).log()
        relative = (model_log - model_log.mean() - (true_log - true_log.mean())).exp() - 1
        errors["exposure_ratio_median"] = float(relative.abs().median())
        errors["exposure_ratio_max"] = float(relative.abs().max())
    model_vignetting, true_vignetting = pair("vignetting")
    true_falloff = _mean(true_vignetting.get("corner_falloff"))
    model_falloff = model_vignetting.get("corner_falloff")
    if true_falloff and model_falloff:
        errors["vignetting_corner_falloff"] = abs(model_falloff - true_falloff) / true_falloff
    # The corners lie outside the object's pixels (an extrapolation of the fitted polynomial);
    # half-way out is inside them in every view.
    true_half = _mean(true_vignetting.get("half_radius_falloff"))
    model_half = model_vignetting.get("half_radius_falloff")
    if true_half and model_half:
        errors["vignetting_half_radius_falloff"] = abs(model_half - true_half) / true_half
    # Not the refit's exponent: under the training views' one light the albedo absorbs a curve,
    # so the refit cannot pin it. The ranking's estimate comes from the relight split, the one
    # place a curve shows (recon.diagnose.relight_probe).
    model_response = next(
        (
            item["parameters"]
            for item in diagnosis["candidates"]
            if item["name"] == "response_curve"
        ),
        {},
    )
    true_response = realised_by_split.get("test", {}).get("response_curve", {})
    true_gamma = true_response.get("effective_exponent")
    model_gamma = model_response.get("effective_gamma")
    if true_gamma and model_gamma:
        errors["response_gamma_absolute"] = abs(model_gamma - true_gamma)
    errors.update(_white_balance_errors(*pair("white_balance")))
    model_defocus, true_defocus = pair("defocus_blur")
    true_radius = true_defocus.get("radius_px")
    model_radius = model_defocus.get("equivalent_disk_radius_px")
    if true_radius and model_radius is not None:
        errors["defocus_radius_relative"] = abs(model_radius - true_radius) / true_radius
    errors.update(_motion_errors(*pair("motion_blur")))
    return errors


def _white_balance_errors(model: dict, true: dict) -> dict:
    """Per-view red and blue gains [V, 3] (green 1) against the truth's, each channel normalised
    by its geometric mean over the views (a colour cast common to every view is the albedo's to
    the fit): the median and largest relative error over views and the two channels."""
    model_gains, true_gains = model.get("gains"), true.get("gains")
    if not model_gains or not true_gains or len(model_gains) != len(true_gains):
        return {}
    model_log = torch.tensor(model_gains, dtype=torch.float64)[:, [0, 2]].log()
    true_log = torch.tensor(true_gains, dtype=torch.float64)[:, [0, 2]].log()
    relative = (model_log - model_log.mean(0) - (true_log - true_log.mean(0))).exp() - 1
    return {
        "white_balance_gain_median": float(relative.abs().median()),
        "white_balance_gain_max": float(relative.abs().max()),
    }


def _motion_errors(model: dict, true: dict) -> dict:
    """Per-view blur path lengths (relative) and directions (degrees, modulo 180: a blur has no
    sense of travel) against the truth's, medians over the views. The truth's paths may curve;
    the probe fits a straight line, so the length is compared with the path's."""
    model_lengths, true_lengths = model.get("lengths_px"), true.get("lengths_px")
    model_angles, true_angles = model.get("angles_deg"), true.get("angles_deg")
    if not model_lengths or not true_lengths or len(model_lengths) != len(true_lengths):
        return {}
    lengths = [
        abs(found - length) / length
        for found, length in zip(model_lengths, true_lengths, strict=True)
        if length > 0
    ]
    errors = {"motion_length_relative_median": statistics.median(lengths)} if lengths else {}
    if model_angles and true_angles and len(model_angles) == len(true_angles):
        turns = [
            abs((found - angle + 90.0) % 180.0 - 90.0)
            for found, angle in zip(model_angles, true_angles, strict=True)
        ]
        errors["motion_angle_deg_median"] = statistics.median(turns)
    return errors


def _mean(value):
    if isinstance(value, list):
        flat = [v for v in value if isinstance(v, (int, float))]
        return statistics.fmean(flat) if flat else None
    return value
