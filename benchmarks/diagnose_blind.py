"""recon-bench diagnose-blind: the blind check of the gap diagnosis.

For every case (one effect, two effects, or none) a dataset is synthesised with the effects
withheld (random plausible strengths; the truth goes to a file outside the run folder), the
scene is fitted without effects, diagnosed without reading the truth, and only then scored:
top-1 accuracy (single effects), both-found rate (pairs), false-positive rate (clean), gap
closed by the refit, and parameter recovery for exposure, vignetting and the response curve.
Writes bench.json, confusion.png and bench.md.

    recon-bench diagnose-blind CONFIG --out DIR [--effects all] [--seeds 0,1,2] [--clean 3]

The scoring itself (BenchCase, score_case) is recon.sweep.scoring, shared with recon's
diagnosis sweeps.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import torch
from tqdm import tqdm

from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.diagnose.decision import redecide
from recon.effects.registry import MODEL_EFFECTS
from recon.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from recon.io.run_folder import open_run_folder, prepare_run_folder
from recon.stages.diagnose import run_diagnosis
from recon.sweep.scoring import NONE, BenchCase, score_case

matplotlib.use("Agg")

# Two-effect cases: one camera-photometric + one optical, one optical + one tone, one per-view
# colour + one light-transport, one geometric + one geometric (each pair from a different
# family, so a pair is not two readings of one signal).
DEFAULT_PAIRS = [
    ("exposure", "vignetting"),
    ("defocus_blur", "response_curve"),
    ("white_balance", "specular"),
    ("pose_error", "lens_distortion"),
]


def default_cases(
    effects: list[str], seeds: list[int], pairs: list[tuple[str, str]], clean: int
) -> list[BenchCase]:
    cases = [BenchCase((name,), seed) for name in effects for seed in seeds]
    cases += [BenchCase(pair, seeds[index % len(seeds)]) for index, pair in enumerate(pairs)]
    cases += [BenchCase((), 100 + index) for index in range(clean)]
    return cases


def run_case(
    case: BenchCase,
    config: RunConfig,
    out: Path,
    device: torch.device,
    refit: str,
    reuse_fits: bool = False,
    fits_only: bool = False,
    rescore: bool = False,
) -> dict | None:
    """Synth (withheld) -> fit -> diagnose (blind) -> score against the truth.

    reuse_fits: keep a case folder whose fit finished under the same config (its bench_fit.json
    records the config hash and the fit's time), so the diagnosis can be rerun on the same data.
    fits_only: stop after the fit (returns None); a later run with reuse_fits diagnoses.
    rescore: reuse the fit and the stored diagnosis.json too, re-deciding its significance with
    the current thresholds (its refit stays the one it ran).
    """
    from dataclasses import replace

    from recon.config import config_hash, dump_resolved
    from recon.pipeline import run_stages

    case_config = replace(config, seed=case.seed, stages=["synth", "fit"])
    folder = out / f"{case.label}_seed{case.seed}"
    truth_path = out / "truth" / f"{case.label}_seed{case.seed}.json"
    fit_record_path = folder / "bench_fit.json"
    # The fit does not depend on the diagnose section: re-deciding with other settings reuses it.
    digest = config_hash(case_config, exclude=("diagnose",))
    fit_record = json.loads(fit_record_path.read_text()) if fit_record_path.exists() else {}
    if reuse_fits and fit_record.get("config_hash") == digest:
        paths = open_run_folder(folder)
        fit_seconds = float(fit_record["fit_seconds"])
    else:
        paths = prepare_run_folder(folder, force=True)
        dump_resolved(case_config, paths.resolved_config)
        started = time.perf_counter()
        synth_options = (
            {"withhold_effects": list(case.effects), "truth_out": truth_path}
            if case.effects
            else {}
        )
        run_stages(case_config, paths, device, ["synth", "fit"], {"synth": synth_options})
        fit_seconds = time.perf_counter() - started
        atomic_write_json(fit_record_path, {"config_hash": digest, "fit_seconds": fit_seconds})
    if fits_only:
        return None
    stored = paths.diagnosis
    if rescore and reuse_fits and stored.exists():
        diagnosis = redecide(json.loads(stored.read_text()), case_config.diagnose).to_json()
        diagnose_seconds = diagnosis["timings"]["diagnose_seconds"] + diagnosis["timings"].get(
            "refit_seconds", 0.0
        )
    else:
        started = time.perf_counter()
        diagnosis = run_diagnosis(paths, case_config, device, refit=refit).to_json()
        diagnose_seconds = time.perf_counter() - started
    # Only now is the truth read: the diagnosis above never saw it.
    truth = json.loads(truth_path.read_text()) if case.effects else {"withheld": []}
    return score_case(case, diagnosis, truth, fit_seconds, diagnose_seconds, paths.root)


def _fraction_text(value: float | None) -> str:
    return "" if value is None else f"{value:.2f}"


def summarise(records: list[dict]) -> dict:
    singles = [r for r in records if r["kind"] == "single"]
    pairs = [r for r in records if r["kind"] == "pair"]
    clean = [r for r in records if r["kind"] == "clean"]
    closed = [r["closed_fraction"] for r in records if r["closed_fraction"] is not None]
    relight_closed = [
        r["relight_closed_fraction"]
        for r in records
        if r.get("relight_closed_fraction") is not None
    ]

    def share(values):
        return sum(values) / len(values) if values else None

    return {
        "top1_accuracy": share([r["top1_correct"] for r in singles]),
        "both_found_rate": share([r["both_found"] for r in pairs]),
        "false_positive_rate": share([r["false_positive"] for r in clean]),
        "median_closed_fraction": statistics.median(closed) if closed else None,
        # The same refits measured on the relight split (where the dataset has one): effects
        # baked into the albedo under the training light show there, not in held-out views.
        "median_relight_closed_fraction": statistics.median(relight_closed)
        if relight_closed
        else None,
        "cases": {"single": len(singles), "pair": len(pairs), "clean": len(clean)},
        "median_fit_seconds": statistics.median([r["fit_seconds"] for r in records]),
        "median_diagnose_seconds": statistics.median([r["diagnose_seconds"] for r in records]),
        "median_diagnosis_share_of_fit": statistics.median(
            [r["diagnosis_share_of_fit"] for r in records]
        ),
        "median_refit_share_of_fit": statistics.median([r["refit_share_of_fit"] for r in records]),
        "parameter_error_median": {
            key: statistics.median(values) for key, values in _parameter_errors(singles).items()
        },
    }


def _parameter_errors(records: list[dict]) -> dict[str, list[float]]:
    """Each parameter error over the cases where the withheld effect is that parameter's."""
    owner = {
        "exposure_ratio_median": "exposure",
        "exposure_ratio_max": "exposure",
        "vignetting_corner_falloff": "vignetting",
        "vignetting_half_radius_falloff": "vignetting",
        "response_gamma_absolute": "response_curve",
    }
    collected: dict[str, list[float]] = {}
    for record in records:
        for key, value in record["parameter_error"].items():
            if owner.get(key) in record["truth"]:
                collected.setdefault(key, []).append(value)
    return collected


def confusion_matrix(records: list[dict]) -> tuple[list[str], list[list[int]]]:
    labels = sorted(MODEL_EFFECTS) + [NONE]
    index = {label: position for position, label in enumerate(labels)}
    matrix = [[0] * len(labels) for _ in labels]
    for record in records:
        if record["kind"] == "pair":
            continue
        truth = record["truth"][0] if record["truth"] else NONE
        matrix[index[truth]][index.get(record["predicted_top"], index[NONE])] += 1
    return labels, matrix


def write_outputs(records: list[dict], out: Path) -> dict:
    summary = summarise(records)
    labels, matrix = confusion_matrix(records)
    atomic_write_json(
        out / "bench.json",
        {"summary": summary, "confusion": {"labels": labels, "matrix": matrix}, "cases": records},
    )
    figure, axis = plt.subplots(figsize=(7, 6))
    axis.imshow(matrix, cmap="Blues")
    axis.set_xticks(range(len(labels)), labels, rotation=60, ha="right")
    axis.set_yticks(range(len(labels)), labels)
    axis.set_xlabel("diagnosed (top significant)")
    axis.set_ylabel("withheld")
    for row, values in enumerate(matrix):
        for column, value in enumerate(values):
            if value:
                axis.text(column, row, str(value), ha="center", va="center")
    with atomic_path(out / "confusion.png") as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)
    lines = ["# Blind diagnosis benchmark", "", "| measure | value |", "|---|---|"]
    lines += [f"| {key} | {value} |" for key, value in summary.items()]
    lines += [
        "",
        "| case | seed | predicted | significant | closed | closed (relight) |",
        "|---|---|---|---|---|---|",
    ]
    for record in records:
        closed, relight = record["closed_fraction"], record.get("relight_closed_fraction")
        lines.append(
            f"| {record['case']} | {record['seed']} | {record['predicted_top']} | "
            f"{', '.join(record['significant'])} | {_fraction_text(closed)} | "
            f"{_fraction_text(relight)} |"
        )
    lines += ["", "![confusion matrix](confusion.png)"]
    atomic_write_text(out / "bench.md", "\n".join(lines) + "\n")
    return summary


def diagnose_blind(
    config_path: str | Path,
    out: str | Path,
    device: torch.device,
    effects: list[str] | None = None,
    seeds: list[int] | None = None,
    pairs: list[tuple[str, str]] | None = None,
    clean: int = 3,
    refit: str = "top",
    overrides: list[str] = (),
    reuse_fits: bool = False,
    fits_only: bool = False,
    rescore: bool = False,
) -> dict:
    config = load_config(config_path, RunConfig, overrides=overrides)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cases = default_cases(
        effects or sorted(MODEL_EFFECTS),
        seeds or [0, 1, 2],
        pairs if pairs is not None else DEFAULT_PAIRS,
        clean,
    )
    records = []
    for case in tqdm(cases, desc="diagnose-blind", unit="case"):
        record = run_case(case, config, out, device, refit, reuse_fits, fits_only, rescore)
        if record is not None:
            records.append(record)
            write_outputs(records, out)  # keep partial results if interrupted
    return write_outputs(records, out) if records else {"fitted_cases": len(cases)}


def build_parser() -> argparse.ArgumentParser:
    """The options of `recon-bench diagnose-blind` (formerly `recon diagnose-bench`)."""
    parser = argparse.ArgumentParser(
        description="blind check: withheld effects -> fit -> diagnose -> score"
    )
    parser.add_argument("config", help="the scene/fit config of every case")
    parser.add_argument("--out", required=True, help="benchmark folder")
    parser.add_argument("--effects", default="all", help="'all' or a comma-separated list")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--clean", type=int, default=3, help="clean datasets")
    parser.add_argument("--no-pairs", action="store_true", help="skip two-effect cases")
    parser.add_argument("--refit", choices=["none", "top", "greedy"], default="top")
    parser.add_argument(
        "--reuse-fits",
        action="store_true",
        help="keep cases whose fit finished under the same config (rediagnose the same data)",
    )
    parser.add_argument(
        "--fits-only", action="store_true", help="synthesise and fit every case, then stop"
    )
    parser.add_argument(
        "--rescore",
        action="store_true",
        help="with --reuse-fits: re-decide stored diagnoses with the current thresholds",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set capture.train_views=8 (repeatable)",
    )
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="overrides 'device'")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its summary as JSON."""
    from recon import pipeline

    arguments = build_parser().parse_args(argv)
    summary = diagnose_blind(
        arguments.config,
        arguments.out,
        pipeline.resolve_device(arguments.device or "auto"),
        effects=None if arguments.effects == "all" else arguments.effects.split(","),
        seeds=[int(seed) for seed in arguments.seeds.split(",")],
        pairs=[] if arguments.no_pairs else None,
        clean=arguments.clean,
        refit=arguments.refit,
        overrides=arguments.overrides,
        reuse_fits=arguments.reuse_fits,
        fits_only=arguments.fits_only,
        rescore=arguments.rescore,
    )
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
