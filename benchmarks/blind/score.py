"""Scoring of the broadened blind check: leave-one-scene-out calibration, metrics per world,
confusion matrices, and the Markdown/JSON/figure outputs.

Every collected case (benchmarks.blind.collect) holds its diagnosis' evidence. For each held-out
scene group the thresholds are calibrated (benchmarks.calibrate.calibrate_thresholds) on the
clean cases of the *other* groups of the synthetic worlds, and the held-out group's cases are
scored by re-deciding their stored evidence with those thresholds; the real-photo world is
scored with thresholds calibrated on every synthetic scene (it is never calibrated on). The same
cases are also scored with the thresholds in the code today, as the baseline.
"""

from __future__ import annotations

import json
import math
import statistics
from collections import Counter
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import torch

from benchmarks.blind.cases import REAL_SCENE, BlindCase, scene_group
from benchmarks.blind.decide import code_thresholds, redecide_with, significant_effects
from benchmarks.calibrate import calibrate_thresholds, calibration_record
from recon.effects.registry import MODEL_EFFECTS
from recon.errors import ReconError
from recon.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from recon.io.run_folder import RunPaths
from recon.report.report import recovered_parameters
from recon.sweep.scoring import NONE, parameter_errors
from recon.sweep.scoring import PARAMETER_OWNER as SCORED_PARAMETERS

matplotlib.use("Agg")

PARAMETER_OWNER = {
    **SCORED_PARAMETERS,
    "exposure_ratio_median_vs_untouched": "exposure",
    "exposure_ratio_max_vs_untouched": "exposure",
}


def load_collected(record: dict) -> dict:
    """A collected case with its diagnosis and truth read back (the truth only for scoring)."""
    paths = RunPaths(Path(record["run_folder"]))
    return {
        **record,
        "diagnosis": json.loads(paths.diagnosis.read_text()),
        "truth_record": json.loads(Path(record["truth_file"]).read_text()),
    }


# A case's injected effect must add at least this share to the held-out error of the clean fit
# of its world, scene and seed before its refit is scored for the gap it closes: two fits of
# the same data differ by about as much (b48v12: the Mitsuba spot's clean fit and its
# interreflection fit, 8.1e-3 and 8.3e-3), and an effect the fit absorbed whole (vignetting,
# white balance under one light) leaves no held-out gap of its own to close.
SMALLEST_EFFECT_SHARE = 0.1


def with_clean_references(records: list[dict]) -> list[dict]:
    """records (load_collected's) with 'clean_heldout_mse': the held-out MSE its refits are
    measured on (gap.heldout_mse) of the clean case of the same world, scene and seed, where
    that case was diagnosed with a refit mode (else None); and 'clean_exposure': the per-view
    exposure ratios the clean case's diagnosis read on the same views ({"source", "ratios"},
    or None). The clean case is the one with nothing withheld (a glossy scene's keeps its
    specular)."""
    clean, exposure = {}, {}
    for record in records:
        case = case_of(record)
        if not case.withheld:  # the untouched case (a glossy scene's keeps its specular)
            key = (case.world, case.scene, case.seed)
            clean[key] = record["diagnosis"]["gap"].get("heldout_mse")
            exposure[key] = exposure_reading(record["diagnosis"])
    return [
        {
            **record,
            "clean_heldout_mse": clean.get(
                (record["case"]["world"], record["case"]["scene"], record["case"]["seed"])
            ),
            "clean_exposure": exposure.get(
                (record["case"]["world"], record["case"]["scene"], record["case"]["seed"])
            ),
        }
        for record in records
    ]


def exposure_reading(diagnosis: dict) -> dict | None:
    """The per-view exposure ratios a diagnosis recovered, significant or not, with where they
    come from ("refit": training views; otherwise held-out views); None without them."""
    if "candidates" not in diagnosis:  # a stored diagnosis of the legacy layout
        return None
    for effect, source, parameters in recovered_parameters(diagnosis, significant_only=False):
        if effect == "exposure" and parameters.get("ratios"):
            return {
                "source": "refit" if source == "refit" else "heldout",
                "ratios": parameters["ratios"],
                "estimator": parameters.get("estimator", ""),
                "backdrop": backdrop_ratios(diagnosis),
            }
    return None


def backdrop_ratios(diagnosis: dict) -> list[float] | None:
    """The per-view brightness gains the static backdrop showed for the exposure candidate
    (recon.diagnose.backdrop: exp of each held-out view's log gain), whether or not it
    confirmed the exposure; None where the frames had no backdrop reading."""
    for candidate in diagnosis["candidates"]:
        if candidate["name"] != "exposure":
            continue
        for evidence in candidate.get("evidence", []):
            components = evidence.get("details", {}).get("backdrop_components")
            if evidence["kind"] == "backdrop" and components:
                return [math.exp(view[0]) for view in components]
    return None


def exposure_errors_vs_untouched(
    diagnosis: dict, truth_record: dict, clean: dict | None
) -> dict[str, float]:
    """The injected exposure's recovery measured against the untouched photos' own reading.

    A per-view gain read off a fit is the injected exposure times whatever per-view gain the
    untouched data already shows against the fitted model (the real capture's, with a fixed
    exposure, reads up to 14 % per view: a glossy object's highlights under a diffuse fit).
    Dividing the case's recovered ratios by the clean case's (same views, same estimator: where
    the case's gains were read off the static backdrop, the untouched photos' backdrop reading)
    leaves the injected part: injection-recovery. Both normalised by their geometric mean, as
    the absolute measure is (recon.sweep.scoring.parameter_errors). Empty where either reading
    or the truth is missing, or the readings come from different views."""
    reading = exposure_reading(diagnosis)
    if reading is None or clean is None or reading["source"] != clean["source"]:
        return {}
    untouched = clean["ratios"]
    if reading.get("estimator") == "backdrop":
        # The case's gains were read off the backdrop: so must the untouched photos' be.
        untouched = clean.get("backdrop")
        if not untouched:
            return {}
    split = "train" if reading["source"] == "refit" else "test"
    realised = {
        item["name"]: item["parameters"] for item in truth_record.get("realised", {}).get(split, [])
    }
    true_ratios = realised.get("exposure", {}).get("ratios")
    model = reading["ratios"]
    if not true_ratios or not (len(true_ratios) == len(model) == len(untouched)):
        return {}
    model_log = torch.tensor(model, dtype=torch.float64).log()
    model_log = model_log - torch.tensor(untouched, dtype=torch.float64).log()
    true_log = torch.tensor(true_ratios, dtype=torch.float64).log()
    relative = (model_log - model_log.mean() - (true_log - true_log.mean())).exp() - 1
    return {
        "exposure_ratio_median_vs_untouched": float(relative.abs().median()),
        "exposure_ratio_max_vs_untouched": float(relative.abs().max()),
    }


def gap_closed_of_effect(refit: dict | None, clean: float | None) -> float | None:
    """The share of the held-out error the injected effect added that the refit with the named
    effect removes: (before - after) / (before - clean), before and after the refit's held-out
    MSE (recon.diagnose.how_far: per-view effect parameters fitted on the first half of each
    view's pixel blocks, the error on the second half) and clean the clean fit's on the same
    views and measure. None without a refit, without a clean reference, or where the effect
    added less than SMALLEST_EFFECT_SHARE of the clean error (no gap of its own to close).
    Above 1 where the refit's extra steps also improve what the clean fit left."""
    if refit is None or clean is None:
        return None
    added = refit["before"] - clean
    if added < SMALLEST_EFFECT_SHARE * clean:
        return None
    return (refit["before"] - refit["after"]) / added


def case_of(record: dict) -> BlindCase:
    case = record["case"]
    return BlindCase(
        case["world"],
        case["scene"],
        tuple(case["withheld"]),
        case["seed"],
        tuple(case.get("intrinsic", ())),
    )


def inert_effects(truth_record: dict) -> list[str]:
    """The withheld effects whose realisation changed no pixel: a defocus disk inside the centre
    pixel (its antialiased pillbox is the identity kernel; cases stored before the sampler's
    1 px floor hold 0.47 px at 48 px). The data then holds no such effect: the case is scored
    against what was realised, and the withheld name is kept as 'inert'."""
    from data_synth.effects.optics import disk_kernel

    inert = []
    for entry in truth_record.get("withheld", []):
        if entry["name"] == "defocus_blur":
            kernel = disk_kernel(float(entry["parameters"]["radius_px"]))
            if float(kernel.max()) >= 1.0 - 1e-9:
                inert.append(entry["name"])
    return inert


def declared_unidentifiable(diagnosis: dict) -> list[str]:
    """The candidates a (re-decided) diagnosis reports as not identifiable from its data."""
    return [
        item["name"] for item in diagnosis["candidates"] if item.get("status") == "not_identifiable"
    ]


def score_one(record: dict, thresholds: dict[str, float], calibrated_on: list[str]) -> dict:
    """One case scored against its truth after re-deciding its evidence with thresholds.

    Besides the strict measures: 'answered' counts a truth effect the diagnosis reports as
    not identifiable from this data (with why and what capture would settle it) as answered,
    not as a silent miss; it is never counted as found."""
    case = case_of(record)
    diagnosis = redecide_with(record["diagnosis"], thresholds)
    named = significant_effects(diagnosis)
    present = set(case.present)
    # Effects the world holds without injecting them are set aside (reported as present_named).
    significant = [name for name in named if name not in present]
    top = significant[0] if significant else NONE
    inert = inert_effects(record["truth_record"])
    truth = [name for name in case.truth if name not in inert]
    kind = {0: "clean", 1: "single"}.get(len(truth), "pair")
    unidentifiable = declared_unidentifiable(diagnosis)
    # Answered: every truth effect is named or declared not identifiable, nothing else named.
    answered = set(truth) - set(significant) <= set(unidentifiable) and set(significant) <= set(
        truth
    )
    refits = diagnosis.get("refits") or []
    fit_seconds = max(float(record["fit_seconds"]), 1e-9)
    return {
        "world": case.world,
        "scene": case.scene,
        "case": case.label,
        "kind": kind,
        "seed": case.seed,
        "truth": truth,
        "inert": inert,
        "predicted_top": top,
        "significant": significant,
        "not_identifiable": unidentifiable,
        "top1_correct": (top in truth) if truth else top == NONE,
        "top1_answered": (top in truth or (top == NONE and truth[0] in unidentifiable))
        if truth
        else top == NONE,
        "exact_set": set(significant) == set(truth),
        "exact_set_answered": answered,
        "both_found": set(truth) <= set(significant) if kind == "pair" else None,
        "false_positive": bool(significant) if kind == "clean" else None,
        "exact_set_strict": set(named) == set(truth),
        "spurious": sorted(set(significant) - set(truth)),
        "present_named": sorted(set(named) & present),
        "closed_fraction": refits[0].get("closed_fraction") if refits else None,
        "refitted": refits[0]["effects"] if refits else [],
        "closed_of_effect": gap_closed_of_effect(
            refits[0] if refits and truth else None, record.get("clean_heldout_mse")
        ),
        # A refit whose effect adds too little to the clean fit's error to be scored.
        "no_gap_to_close": bool(refits and truth and record.get("clean_heldout_mse"))
        and gap_closed_of_effect(refits[0], record["clean_heldout_mse"]) is None,
        "fit_seconds": record["fit_seconds"],
        "diagnose_seconds": record["diagnose_seconds"],
        "diagnosis_share_of_fit": record["diagnose_seconds"] / fit_seconds,
        "parameter_error": {
            **parameter_errors(diagnosis, record["truth_record"]),
            **exposure_errors_vs_untouched(
                diagnosis, record["truth_record"], record.get("clean_exposure")
            ),
        },
        "calibrated_on": calibrated_on,
        "run_folder": record["run_folder"],
    }


def _scored_held_out(
    scored_cases: list[dict], calibration_cases: list[dict], base_config: dict
) -> tuple[list[dict], dict]:
    """scored_cases scored with thresholds calibrated on calibration_cases (their clean
    diagnoses, present effects left out); returns (scores, calibration record)."""
    calibrated_scenes = sorted({record["case"]["scene"] for record in calibration_cases})
    thresholds = calibrate_thresholds(
        [record["diagnosis"] for record in calibration_cases],
        [case_of(record).present for record in calibration_cases],
    )
    calibration = calibration_record(
        thresholds,
        [
            {key: record["case"][key] for key in ("world", "scene", "seed")}
            for record in calibration_cases
        ],
        base_config,
    )
    return [
        score_one(record, thresholds, calibrated_scenes) for record in scored_cases
    ], calibration


def leave_one_scene_out(records: list[dict], base_config: dict) -> tuple[list[dict], dict]:
    """Scores of every case, each with thresholds calibrated only on other scene groups'
    clean synthetic cases; returns (scored cases, calibration record per held-out group)."""
    synthetic = [record for record in records if record["case"]["world"] != "real"]
    clean = [record for record in synthetic if case_of(record).kind == "clean"]
    groups = sorted({scene_group(record["case"]["scene"]) for record in records})
    scored: list[dict] = []
    calibrations: dict[str, dict] = {}
    for group in groups:
        calibration_cases = [
            record for record in clean if scene_group(record["case"]["scene"]) != group
        ]
        scored_cases = [
            record for record in records if scene_group(record["case"]["scene"]) == group
        ]
        if not calibration_cases:
            raise ReconError(
                f"leave-one-scene-out: no clean synthetic case outside scene group {group!r} "
                "to calibrate on (add scenes or clean cases)"
            )
        if group in {scene_group(record["case"]["scene"]) for record in calibration_cases}:
            raise ReconError(f"leave-one-scene-out: scene group {group!r} calibrated on itself")
        held, calibrations[group] = _scored_held_out(scored_cases, calibration_cases, base_config)
        scored += held
    return scored, calibrations


def world_order(world: str) -> int:
    """Where a world's column goes in the page: the own world, the path tracer, the photos."""
    order = ("own", "mitsuba", "real")
    return order.index(world) if world in order else len(order)


def leave_one_world_and_scene_out(
    records: list[dict], base_config: dict
) -> tuple[list[dict], dict]:
    """Scores of every case with thresholds calibrated only on clean synthetic cases of other
    scene groups *and* other worlds (a synthetic world is never calibrated on itself; the real
    photos, which calibrate nothing, as leave_one_scene_out). Returns (scored cases,
    calibration record per "world/group"); a world and group with nothing to calibrate on
    (one synthetic world only) is left out of the scores."""
    synthetic = [record for record in records if record["case"]["world"] != "real"]
    clean = [record for record in synthetic if case_of(record).kind == "clean"]
    keys = sorted(
        {(record["case"]["world"], scene_group(record["case"]["scene"])) for record in records}
    )
    scored: list[dict] = []
    calibrations: dict[str, dict] = {}
    for world, group in keys:
        calibration_cases = [
            record
            for record in clean
            if scene_group(record["case"]["scene"]) != group and record["case"]["world"] != world
        ]
        if not calibration_cases:
            continue
        scored_cases = [
            record
            for record in records
            if record["case"]["world"] == world and scene_group(record["case"]["scene"]) == group
        ]
        held, calibrations[f"{world}/{group}"] = _scored_held_out(
            scored_cases, calibration_cases, base_config
        )
        scored += held
    return scored, calibrations


def with_code_thresholds(records: list[dict]) -> list[dict]:
    """Every case scored with the thresholds in the code today (the shipped calibration)."""
    thresholds = code_thresholds()
    return [
        score_one(record, thresholds, ["code (diagnose.decision defaults)"]) for record in records
    ]


def _share(values: list) -> float | None:
    values = [value for value in values if value is not None]
    return round(sum(values) / len(values), 3) if values else None


def _median(values: list) -> float | None:
    values = [value for value in values if value is not None]
    return round(statistics.median(values), 3) if values else None


def summarise_world(scored: list[dict]) -> dict:
    """The issue's metrics over one world's scored cases."""
    singles = [record for record in scored if record["kind"] == "single"]
    pairs = [record for record in scored if record["kind"] == "pair"]
    clean = [record for record in scored if record["kind"] == "clean"]
    errors: dict[str, list[float]] = {}
    for record in scored:
        for key, value in record["parameter_error"].items():
            if PARAMETER_OWNER.get(key) in record["truth"]:
                errors.setdefault(key, []).append(value)
    return {
        "cases": {"single": len(singles), "pair": len(pairs), "clean": len(clean)},
        "top1_accuracy": _share([record["top1_correct"] for record in singles]),
        "top1_answered": _share([record.get("top1_answered") for record in singles]),
        "exact_set_accuracy": _share([record["exact_set"] for record in scored]),
        "exact_set_answered": _share([record.get("exact_set_answered") for record in scored]),
        "inert": dict(Counter(name for record in scored for name in record.get("inert", []))),
        "exact_set_singles": _share([record["exact_set"] for record in singles]),
        "exact_set_strict": _share([record["exact_set_strict"] for record in scored]),
        "present_named": dict(
            Counter(name for record in scored for name in record["present_named"])
        ),
        "false_positive_rate": _share([record["false_positive"] for record in clean]),
        "both_found_rate": _share([record["both_found"] for record in pairs]),
        "median_closed_fraction": _median([record["closed_fraction"] for record in scored]),
        "median_closed_of_effect": _median([record.get("closed_of_effect") for record in scored]),
        "median_closed_of_effect_true": _median(
            [
                record.get("closed_of_effect")
                for record in scored
                if set(record.get("refitted", [])) <= set(record["truth"])
            ]
        ),
        "refits_scored": sum(record.get("closed_of_effect") is not None for record in scored),
        "refits_no_gap": sum(bool(record.get("no_gap_to_close")) for record in scored),
        "parameter_error_median": {key: _median(values) for key, values in errors.items()},
        # Which effects were named where they were not (across every case of the world).
        "spurious_effects": dict(Counter(name for record in scored for name in record["spurious"])),
        "median_fit_seconds": _median([record["fit_seconds"] for record in scored]),
        "median_diagnose_seconds": _median([record["diagnose_seconds"] for record in scored]),
        "median_diagnosis_share_of_fit": _median(
            [record["diagnosis_share_of_fit"] for record in scored]
        ),
    }


def confusion(scored: list[dict]) -> tuple[list[str], list[list[int]]]:
    """Rows: the true effect of single and clean cases; columns: the top significant effect."""
    labels = sorted(MODEL_EFFECTS) + [NONE]
    index = {label: position for position, label in enumerate(labels)}
    matrix = [[0] * len(labels) for _ in labels]
    for record in scored:
        if record["kind"] == "pair":
            continue
        truth = record["truth"][0] if record["truth"] else NONE
        matrix[index[truth]][index.get(record["predicted_top"], index[NONE])] += 1
    return labels, matrix


def by_world(scored: list[dict]) -> dict[str, list[dict]]:
    worlds: dict[str, list[dict]] = {}
    for record in scored:
        worlds.setdefault(record["world"], []).append(record)
    return worlds


def confusion_figure(scored: list[dict], path: Path) -> None:
    """One confusion matrix per world, side by side (PNG)."""
    worlds = by_world(scored)
    figure, axes = plt.subplots(1, len(worlds), figsize=(6 * len(worlds), 5.5), squeeze=False)
    for axis, (world, records) in zip(axes[0], worlds.items(), strict=True):
        labels, matrix = confusion(records)
        used = [
            position
            for position in range(len(labels))
            if any(matrix[position]) or any(row[position] for row in matrix)
        ]
        shown = [[matrix[row][column] for column in used] for row in used]
        names = [labels[position] for position in used]
        axis.imshow(shown, cmap="Blues")
        axis.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=7)
        axis.set_yticks(range(len(names)), names, fontsize=7)
        axis.set_title(f"{world}")
        axis.set_xlabel("diagnosed (top significant)")
        axis.set_ylabel("true")
        for row, values in enumerate(shown):
            for column, value in enumerate(values):
                if value:
                    axis.text(column, row, str(value), ha="center", va="center", fontsize=7)
    figure.tight_layout()
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=100, bbox_inches="tight", format="png")
    plt.close(figure)


def _matrix_markdown(scored: list[dict]) -> list[str]:
    labels, matrix = confusion(scored)
    used = [
        position
        for position in range(len(labels))
        if any(matrix[position]) or any(row[position] for row in matrix)
    ]
    lines = ["| true \\ diagnosed | " + " | ".join(labels[c] for c in used) + " |"]
    lines.append("|---" * (len(used) + 1) + "|")
    for row in used:
        cells = [str(matrix[row][column]) if matrix[row][column] else "" for column in used]
        lines.append(f"| {labels[row]} | " + " | ".join(cells) + " |")
    return lines


SUMMARY_ROWS = (
    ("top-1 (singles)", "top1_accuracy"),
    ("top-1 or declared not identifiable (singles)", "top1_answered"),
    ("exact set (all cases)", "exact_set_accuracy"),
    ("exact set, a truth declared not identifiable answers (all cases)", "exact_set_answered"),
    ("exact set (singles)", "exact_set_singles"),
    ("exact set, strict (present effects count as errors)", "exact_set_strict"),
    ("false positives (clean)", "false_positive_rate"),
    ("both found (pairs)", "both_found_rate"),
    ("gap closed above the noise floor (median, refit)", "median_closed_fraction"),
    ("gap closed of the effect's error (median, refit)", "median_closed_of_effect"),
    ("gap closed of the effect's error, a true effect refitted", "median_closed_of_effect_true"),
    ("refits scored for the gap closed", "refits_scored"),
    ("refits not scored: the effect adds < 10 % to the clean error", "refits_no_gap"),
    ("fit s (median)", "median_fit_seconds"),
    ("diagnosis s (median)", "median_diagnose_seconds"),
    ("diagnosis / fit (median)", "median_diagnosis_share_of_fit"),
)


def _cell(value) -> str:
    return "" if value is None else f"{value:g}"


def _counts(counts: dict[str, int]) -> str:
    ordered = sorted(counts.items(), key=lambda item: (-item[1], item[0]))
    return ", ".join(f"{name} {count}" for name, count in ordered) or "none"


def markdown(result: dict, provenance: dict) -> str:
    """The generated Markdown page of one benchmark run."""
    lines = [
        "# Blind diagnosis check, broadened (generated)",
        "",
        "Generated by `recon-bench diagnose-blind --worlds ...` (benchmarks/diagnose_blind.py);",
        "do not edit by hand. Reproduce with:",
        "",
        f"    {provenance['command']}",
        "",
        f"Commit `{provenance['commit']}`, base config sha256 `{provenance['base_config_sha256']}`,"
        f" {provenance['finished']}, {provenance['machine']}.",
        "",
        "Scores are on scenes never used for calibration (leave-one-scene-out: the thresholds of",
        "each scene group are calibrated on the other groups' clean synthetic cases; the real",
        "photos on every synthetic scene): twice the largest clean statistic, a clean probe",
        "counting only where its run's own null would let it clear (benchmarks/calibrate.py).",
        "'Leave one world and scene out' calibrates each synthetic world's scene group on the",
        "other world's other scenes only (the real photos as above). The baseline rows use the",
        "thresholds in the code today (the diagnose.decision defaults, DecisionConfig, calibrated on",
        "the own world's torus and spot at 128 px).",
        "",
        "Effects a world holds without injecting them are set aside: the path tracer's renders",
        "carry the cast shadows of the scene's sun (`shadows`), real photos the object's light",
        "transport (`specular`, `shadows`, `interreflection`). Naming them is neither required",
        "nor counted as an error; the rows 'exact set, strict' and 'named, present' show them,",
        "and their evidence on clean cases is left out of calibration.",
        "",
        "An injected effect whose realisation changed no pixel is scored as not there (row",
        "'injected but inert'): a defocus pillbox inside the centre pixel is the identity kernel",
        "(the images equal the clean case's). The sampler draws at least 1 px (decision 0199);",
        "cases synthesised before it hold 0.47 px at 48 px and stay inert.",
        "The strict rows count a truth effect that the diagnosis reports as",
        "'not identifiable from this data' as missed; the 'declared not identifiable' rows count",
        "it as answered (never as found). See docs/decisions/0191-blind-misses.md.",
        "",
        "Gap closed (with a refit mode; the same refits in both tables, run on the code's",
        "decision): the diagnosis refits the scene with its top significant effect switched on",
        "(recon.diagnose.how_far) and measures the held-out MSE again (per-view effect",
        "parameters fitted on half of each view's pixel blocks, the error on the other half).",
        "'Above the noise floor' is the share of (before - floor) the refit removes, as",
        "diagnosis.json reports it; the base fit's own misfit counts in it. 'Of the effect's",
        "error' is (before - after) / (before - clean): the share of the held-out error above",
        "the clean fit's (the untouched case of the same world, scene and seed, same views and",
        "measure) that the refit removes. Cases whose effect adds less than 10 % to the clean",
        "error (absorbed by the fit: nothing of its own to close) are counted, not scored.",
        "Values above 1: the refit's extra steps also improve what the clean fit left.",
        "",
        "Parameter rows (recon.sweep.scoring.parameter_errors), each over the single cases of",
        "its effect, significant or not: per-view exposure and white-balance gains relative,",
        "normalised by their geometric mean over the views (a common scale or cast is the",
        "albedo's); the defocus disk radius relative; motion blur per-view path length relative",
        "and direction in degrees modulo 180 (medians over the views); vignetting falloffs",
        "relative; the response curve's exponent absolute. The exposure rows 'vs untouched'",
        "divide out what the untouched case of the same scene and seed reads on the same views",
        "with the same estimator (the object's gains, or the static backdrop's where the case's",
        "gains were read off it): the real photos' frames change by a few per cent on their own.",
        "",
        "The timing rows are this check's own: its fits are short (a third of the real",
        "capture config's steps, 40 + 30 steps at 48 px), so a diagnosis of fixed size costs a",
        "large share of them. The diagnosis's cost against a full fit is recorded by",
        "`recon-bench time-diagnosis` (docs/bench/time-diagnosis.json).",
        "",
    ]
    for label, key in (
        ("leave-one-scene-out", "loso"),
        ("leave one world and scene out", "lowo"),
        ("code thresholds", "code"),
    ):
        if key not in result:
            continue
        worlds = result[key]["summary"]
        names = list(worlds)
        lines += [f"## {label}", "", "| measure | " + " | ".join(names) + " |"]
        lines.append("|---" * (len(names) + 1) + "|")
        for title, field in SUMMARY_ROWS:
            cells = [_cell(worlds[w][field]) for w in names]
            lines.append(f"| {title} | " + " | ".join(cells) + " |")
        for kind in ("single", "pair", "clean"):
            cells = [str(worlds[w]["cases"][kind]) for w in names]
            lines.append(f"| cases: {kind} | " + " | ".join(cells) + " |")
        parameters = sorted({key for w in names for key in worlds[w]["parameter_error_median"]})
        for key in parameters:
            cells = [_cell(worlds[w]["parameter_error_median"].get(key)) for w in names]
            lines.append(f"| {key} (median error) | " + " | ".join(cells) + " |")
        spurious = [_counts(worlds[w]["spurious_effects"]) for w in names]
        lines.append("| spurious significant effects | " + " | ".join(spurious) + " |")
        present = [_counts(worlds[w]["present_named"]) for w in names]
        lines.append("| named, present in the world, not injected | " + " | ".join(present) + " |")
        inert = [_counts(worlds[w].get("inert", {})) for w in names]
        lines.append("| injected but inert (scored as not there) | " + " | ".join(inert) + " |")
        lines.append("")
    lines += ["## Confusion matrices (leave-one-scene-out; singles and clean)", ""]
    for world, records in by_world(result["loso"]["cases"]).items():
        lines += [f"### {world}", "", *_matrix_markdown(records), ""]
    lines += ["![confusion matrices](blind_confusion.png)", ""]
    lines += [
        "## Cases (leave-one-scene-out)",
        "",
        "| world | scene | case | truth | significant | not identifiable | exact | calibrated on |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for record in result["loso"]["cases"]:
        lines.append(
            f"| {record['world']} | {record['scene']} | {record['case']} | "
            f"{', '.join(record['truth']) or 'none'} | {', '.join(record['significant']) or 'none'}"
            f" | {', '.join(record.get('not_identifiable', []))}"
            f" | {'yes' if record['exact_set'] else 'no'} | {', '.join(record['calibrated_on'])} |"
        )
    lines += ["", "## Calibrated thresholds per held-out scene group", ""]
    calibrations = result["calibrations"]
    names = sorted({name for record in calibrations.values() for name in record["thresholds"]})
    code = code_thresholds()
    groups = list(calibrations)
    headers = ["for the real photos" if g == REAL_SCENE else f"without {g}" for g in groups]
    lines.append("| threshold | code | " + " | ".join(headers) + " |")
    lines.append("|---" * (len(groups) + 2) + "|")
    for name in names:
        values = [calibrations[g]["thresholds"].get(name) for g in groups]
        if all(value == code.get(name) for value in values):
            continue
        cells = ["" if value is None else f"{value:g}" for value in values]
        lines.append(f"| {name} | {code.get(name, ''):g} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Thresholds not listed equal the code's in every calibration.")
    return "\n".join(lines) + "\n"


def score_and_write(records: list[dict], base_config: dict, out: Path, provenance: dict) -> dict:
    """Score every collected case (leave-one-scene-out and with the code's thresholds), write
    OUT/blind.json, OUT/blind.md, OUT/blind_confusion.png and OUT/calibration.json (the
    thresholds calibrated on every synthetic scene, in the form a diagnose config takes)."""
    loaded = with_clean_references([load_collected(record) for record in records])
    loso, calibrations = leave_one_scene_out(loaded, base_config)
    lowo, _ = leave_one_world_and_scene_out(loaded, base_config)
    code = with_code_thresholds(loaded)
    result = {
        "provenance": provenance,
        "loso": {
            "summary": {w: summarise_world(r) for w, r in by_world(loso).items()},
            "confusion": {
                w: dict(zip(("labels", "matrix"), confusion(r), strict=True))
                for w, r in by_world(loso).items()
            },
            "cases": loso,
        },
        "lowo": {
            "summary": {
                w: summarise_world(r)
                for w, r in sorted(by_world(lowo).items(), key=lambda item: world_order(item[0]))
            },
            "cases": lowo,
        },
        "code": {
            "summary": {w: summarise_world(r) for w, r in by_world(code).items()},
            "cases": code,
        },
        "calibrations": calibrations,
    }
    synthetic_clean = [
        record
        for record in loaded
        if record["case"]["world"] != "real" and case_of(record).kind == "clean"
    ]
    if synthetic_clean:
        atomic_write_json(
            out / "calibration.json",
            calibration_record(
                calibrate_thresholds(
                    [record["diagnosis"] for record in synthetic_clean],
                    [case_of(record).present for record in synthetic_clean],
                ),
                [
                    {key: record["case"][key] for key in ("world", "scene", "seed")}
                    for record in synthetic_clean
                ],
                base_config,
            ),
        )
    atomic_write_json(out / "blind.json", result)
    confusion_figure(loso, out / "blind_confusion.png")
    atomic_write_text(out / "blind.md", markdown(result, provenance))
    return result
