"""recon-bench diagnose-blind: the blind check of the gap diagnosis.

For every case (one effect, two effects, or none) a dataset is synthesised with the effects
withheld (random plausible strengths; the truth goes to a file outside the run folder), the
scene is fitted without effects, diagnosed without reading the truth, and only then scored:
top-1 accuracy (single effects), both-found rate (pairs), false-positive rate (clean), gap
closed by the refit, and parameter recovery for exposure, vignetting and the response curve.
Writes bench.json, confusion.png and bench.md.

    recon-bench diagnose-blind CONFIG --out DIR [--effects all] [--seeds 0,1,2] [--clean 3]

Broadened (issue 20): several worlds and scenes, scored leave-one-scene-out
(the benchmarks.blind package):

    recon-bench diagnose-blind configs/bench/diagnose_blind_48.yaml --out DIR \
        --worlds own,mitsuba,real --scenes spot,bob,bunny,teapot,torus,spot_glossy,torus_glossy \
        --seeds 0 [--doc docs/diagnosis/blind.md]

collects every case's evidence once (synth or derived photos, fit, diagnose with --refit none by
default), then calibrates the thresholds per held-out scene group on the other groups' clean
cases and scores by re-deciding the stored evidence; writes blind.json, blind.md,
blind_confusion.png and calibration.json.

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
from recon.sweep.scoring import NONE, PARAMETER_OWNER, BenchCase, score_case

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
    collected: dict[str, list[float]] = {}
    for record in records:
        for key, value in record["parameter_error"].items():
            if PARAMETER_OWNER.get(key) in record["truth"]:
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


def stored_cases(cases: list, out: Path) -> tuple[list[dict], list[dict]]:
    """The stored records of cases (benchmarks.blind.cases.BlindCase) under out, and a note for
    each case without one. Stored evidence is all a score needs: the scenes' inputs (../shared)
    may be absent where the cases were collected elsewhere."""
    from benchmarks.blind.cases import missing_inputs
    from benchmarks.blind.collect import finished_case

    collected, skipped = [], []
    for case in cases:
        stored = finished_case(case, out)
        if stored is None:
            reason = missing_inputs(case.scene) or "not collected (--score-only)"
            skipped.append({"case": case.to_json(), "reason": reason})
        else:
            collected.append(stored)
    return collected, skipped


def diagnose_blind_worlds(
    config_path: str | Path,
    out: str | Path,
    device: torch.device,
    worlds: list[str],
    scenes: list[str],
    effects: list[str] | None,
    seeds: list[int],
    pairs: list[tuple[str, str]],
    refit: str = "none",
    real_options=None,
    doc: str | Path | None = None,
    command: str = "",
    collect_only: bool = False,
    score_only: bool = False,
    shard: tuple[int, int] = (0, 1),
    candidates: list[str] | None = None,
    rediagnose: bool = False,
) -> dict:
    """The broadened blind check: collect every case's evidence (skipping finished ones), then
    score leave-one-scene-out per world. Cases whose inputs are absent (../shared) are skipped
    with a note; a case that fails is recorded and skipped, never scored. score_only: score the
    cases collected so far (an interrupted run), collecting nothing. shard (i, n): collect only
    every n-th case from the i-th (several processes on one folder), then stop; score the whole
    with a later score_only call. candidates: the effects each diagnosis considers (None: all;
    the suite's tiny benchmark narrows it). rediagnose: diagnose every stored fit again (the
    diagnosis code changed; fits whose config is unchanged are kept)."""
    import platform
    import shutil
    import traceback

    import yaml

    from benchmarks.blind.cases import WORLDS, build_cases, interleaved, missing_inputs
    from benchmarks.blind.collect import (
        RealOptions,
        collect_real,
        collect_synthetic,
    )
    from benchmarks.blind.score import score_and_write
    from benchmarks.calibrate import calibration_record
    from recon.errors import ReconError

    unknown = sorted(set(worlds) - set(WORLDS))
    if unknown:
        raise ReconError(f"--worlds: unknown {unknown}; known: {', '.join(WORLDS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = yaml.safe_load(Path(config_path).read_text())
    real_options = real_options or RealOptions()
    cases = interleaved(build_cases(worlds, scenes, effects, seeds, pairs))
    index, count = shard
    if count > 1:
        cases, collect_only = cases[index::count], True
    collected, skipped = [], []
    if score_only:
        collected, skipped = stored_cases(cases, out)
        cases = []
    for case in tqdm(cases, desc="diagnose-blind", unit="case"):
        reason = missing_inputs(case.scene)
        if reason:
            skipped.append({"case": case.to_json(), "reason": reason})
            continue
        try:
            if case.world == "real":
                record = collect_real(
                    case, real_options, out, device, refit, candidates, rediagnose
                )
            else:
                record = collect_synthetic(case, base, out, device, refit, candidates, rediagnose)
        except Exception as error:  # noqa: BLE001 - one failed case must not end the run
            skipped.append({"case": case.to_json(), "reason": f"{type(error).__name__}: {error}"})
            print(traceback.format_exc(), file=sys.stderr)
            continue
        collected.append(record)
        if count == 1:
            # Kept as it goes: an interrupted run can be scored (--score-only) or continued.
            atomic_write_json(out / "collected.json", {"cases": collected, "skipped": skipped})
    if count == 1:
        atomic_write_json(out / "collected.json", {"cases": collected, "skipped": skipped})
    if collect_only:
        return {"collected": len(collected), "skipped": skipped}
    provenance = calibration_record({}, [], base)["provenance"]
    provenance = {
        "commit": provenance["commit"],
        "base_config_sha256": provenance["base_config_sha256"],
        "command": command,
        "finished": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {__import__('os').cpu_count()} CPUs, torch "
        f"{torch.__version__}, device {device}",
        "skipped": skipped,
    }
    result = score_and_write(collected, base, out, provenance)
    if doc is not None:
        doc = Path(doc)
        atomic_write_text(doc, (out / "blind.md").read_text())
        shutil.copyfile(out / "blind_confusion.png", doc.parent / "blind_confusion.png")
        if (out / "calibration.json").exists():
            # The thresholds from every synthetic scene with their provenance: the form a
            # `diagnose:` config section takes.
            shutil.copyfile(out / "calibration.json", doc.parent / "blind_calibration.json")
    return {key: result[key]["summary"] for key in ("loso", "code")}


TITLE = "Blind diagnosis check"


def markdown(result: dict) -> str:
    """The record's summary (recon-bench diagnose-blind --record): with --worlds, the
    leave-one-scene-out metrics per world beside the code's thresholds; else the generic table."""
    if "loso" not in result:
        from benchmarks.record import generic_markdown

        return generic_markdown(result)
    from benchmarks.blind.score import SUMMARY_ROWS

    worlds = list(result["loso"])
    lines = [
        "| measure | " + " | ".join(f"{w} (held out) | {w} (code)" for w in worlds) + " |",
        "|---" * (2 * len(worlds) + 1) + "|",
    ]
    for title, field in SUMMARY_ROWS:
        cells = []
        for world in worlds:
            for key in ("loso", "code"):
                value = result[key].get(world, {}).get(field)
                cells.append("" if value is None else f"{value:g}")
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Cases, confusion matrices and thresholds: [diagnosis/blind.md](diagnosis/blind.md).",
    ]
    return "\n".join(lines)


def _reproducing_command(argv: list[str]) -> str:
    """The command that collects and scores what this call scores: --score-only and --shard
    only split the same work (any split gives the same cases); --rediagnose only redoes it."""
    kept, skip = [], False
    for argument in argv:
        if skip:
            skip = False
            continue
        if argument == "--shard":
            skip = True
            continue
        if argument in ("--score-only", "--rediagnose") or argument.startswith("--shard="):
            continue
        kept.append(argument)
    return "recon-bench diagnose-blind " + " ".join(kept)


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
    parser.add_argument(
        "--refit",
        choices=["none", "top", "greedy"],
        help="refit after the diagnosis (default: top; none with --worlds)",
    )
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
    broad = parser.add_argument_group("broadened check (issue 20)")
    broad.add_argument(
        "--worlds",
        help="comma-separated worlds (own, mitsuba, real): run the broadened check, "
        "scored leave-one-scene-out (refit defaults to none)",
    )
    broad.add_argument(
        "--scenes",
        default="spot,bob,bunny,teapot,torus,spot_glossy,torus_glossy",
        help="comma-separated scenes of the synthetic worlds (benchmarks/blind/cases.py)",
    )
    broad.add_argument(
        "--pairs",
        default="exposure+vignetting,response_curve+lens_distortion",
        help="comma-separated pairs A+B per scene ('' for none)",
    )
    broad.add_argument("--real-resolution", type=int, default=96, help="photos' longer side")
    broad.add_argument("--real-view-every", type=int, default=2, help="keep every N-th photo")
    broad.add_argument(
        "--real-config",
        type=Path,
        help="the real world's fit config (default configs/bench/blind_real.yaml)",
    )
    broad.add_argument(
        "--doc",
        help="also write the Markdown page here (its figure and calibration.json beside it)",
    )
    broad.add_argument("--collect-only", action="store_true", help="collect evidence, do not score")
    broad.add_argument(
        "--rediagnose",
        action="store_true",
        help="diagnose stored fits again (the diagnosis changed); fits are kept",
    )
    broad.add_argument(
        "--score-only",
        action="store_true",
        help="score the cases collected so far (an interrupted run); collect nothing",
    )
    broad.add_argument(
        "--shard",
        default="0/1",
        help="I/N: collect every N-th case from the I-th (parallel collectors), no scoring",
    )
    return parser


def real_options(arguments: argparse.Namespace):
    """The real-photo world's RealOptions from the command line (--real-*)."""
    from benchmarks.blind.collect import RealOptions

    chosen = {"config": arguments.real_config} if arguments.real_config else {}
    return RealOptions(
        max_resolution=arguments.real_resolution, view_every=arguments.real_view_every, **chosen
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its summary as JSON."""
    from recon import pipeline

    arguments = build_parser().parse_args(argv)
    if arguments.worlds:
        pairs = [
            tuple(pair.split("+")) for pair in arguments.pairs.split(",") if pair and "+" in pair
        ]
        summary = diagnose_blind_worlds(
            arguments.config,
            arguments.out,
            pipeline.resolve_device(arguments.device or "auto"),
            worlds=arguments.worlds.split(","),
            scenes=arguments.scenes.split(","),
            effects=None if arguments.effects == "all" else arguments.effects.split(","),
            seeds=[int(seed) for seed in arguments.seeds.split(",")],
            pairs=pairs,
            refit=arguments.refit or "none",
            real_options=real_options(arguments),
            doc=arguments.doc,
            command=_reproducing_command(argv if argv is not None else sys.argv[1:]),
            collect_only=arguments.collect_only,
            score_only=arguments.score_only,
            shard=tuple(int(part) for part in arguments.shard.split("/")),
            rediagnose=arguments.rediagnose,
        )
        print(json.dumps(summary, indent=2))
        return 0
    summary = diagnose_blind(
        arguments.config,
        arguments.out,
        pipeline.resolve_device(arguments.device or "auto"),
        effects=None if arguments.effects == "all" else arguments.effects.split(","),
        seeds=[int(seed) for seed in arguments.seeds.split(",")],
        pairs=[] if arguments.no_pairs else None,
        clean=arguments.clean,
        refit=arguments.refit or "top",
        overrides=arguments.overrides,
        reuse_fits=arguments.reuse_fits,
        fits_only=arguments.fits_only,
        rescore=arguments.rescore,
    )
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
