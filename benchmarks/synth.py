#!/usr/bin/env python
"""Benchmark the synth stage (data_synth): how long a capture dataset takes to make.

Prints one JSON document on stdout (progress goes to stderr) and writes it to --out atomically.

Sections (--sections, default both):
  own      configs/bench/synth_own.yaml: spot (../shared/meshes; the procedural 'blob' with a
           note when absent), 100 views (80 train / 10 val / 10 test) at 256x256 through the
           camera chain (exposure, white_balance, vignetting, lens_distortion, defocus_blur,
           noise), recon's own rasterizer, written to a temporary run folder. --runs runs
           (default 3): median wall time (target < 30 s) and the time split render / effects /
           writing / other (mesh loading, ground truth, contact sheet).
  mitsuba  configs/bench/synth_mitsuba.yaml: the same scene and chain with Mitsuba light
           transport (specular + shadows) at 64 spp. 16 views are timed; the per-view time is
           extrapolated to 100 views, and a real 100-view run follows when the extrapolation is
           under --mitsuba-full-budget seconds (default 300; --mitsuba-full never|always).
           Skipped when mitsuba is not installed.

Every run goes through recon.pipeline.run (what `recon synth` calls) into a fresh temporary
folder that is deleted afterwards. The time split comes from wrapping the stage's own functions
(data_synth.stage.render_split, data_synth.effects.registry.apply_effects, the dataset writers
and data_synth.mitsuba_backend.render_mitsuba) with timers for the duration of a run; nothing else
changes. Relative paths in the bench configs resolve against the repository root.

torch uses every CPU (torch.set_num_threads(os.cpu_count())); Mitsuba's LLVM backend uses its
own pool. `cores_used` (CPU seconds / wall seconds) and the load average show whether other
processes competed for the cores: when they did, the times are inflated.

Examples:
  recon-bench synth                       # both sections, 3 runs of the own one
  recon-bench synth --sections own --runs 5 --out synth.json
  recon-bench synth --quick               # smoke test: tiny images, a few views
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import tempfile
import time
from pathlib import Path

from benchmarks import common
from recon.io.run_folder import RunPaths

REPO_ROOT = common.REPO_ROOT
OWN_CONFIG = REPO_ROOT / "configs" / "bench" / "synth_own.yaml"
MITSUBA_CONFIG = REPO_ROOT / "configs" / "bench" / "synth_mitsuba.yaml"
SECTIONS = ("own", "mitsuba")

OWN_TARGET_S = 30.0
FULL_VIEWS = 100
FULL_SPLITS = (80, 10, 10)  # train / val / test of a 100-view dataset
MITSUBA_SAMPLE_VIEWS = 16
MITSUBA_FULL_BUDGET_S = 300.0
RESOLUTION = 256

QUICK = {
    "resolution": 32,
    "own_splits": (1, 1, 1),
    "runs": 1,
    "mitsuba_sample_views": 1,
    "mitsuba_full_splits": (1, 1, 0),
    "mitsuba_spp": 4,
}
FALLBACK_OVERRIDES = [
    "scene.shape.mesh_path=null",
    "scene.shape.texture_path=null",
    "scene.shape.procedural=blob",
    "scene.material.albedo=checker",
]
# Phases timed by wrapping the stage's functions; 'other' is the rest of the wall time.
PHASES = ("render", "effects", "writing")


# ----------------------------------------------------------------------------------------------
# Instrumentation


class PhaseTimer:
    """Seconds spent inside the wrapped functions, per phase (nested calls count once)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._active: set[str] = set()

    def wrap(self, phase: str, function):
        def timed(*args, **kwargs):
            if phase in self._active:
                return function(*args, **kwargs)
            self._active.add(phase)
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self._active.discard(phase)
                self.seconds[phase] = self.seconds.get(phase, 0.0) + time.perf_counter() - started

        return timed


@contextlib.contextmanager
def instrumented(timer: PhaseTimer):
    """Wrap the synth stage's render, effect and writer functions with timer for the duration.

    render_split and the writers are looked up as data_synth.stage globals at call time, and
    apply_effects / render_mitsuba are imported from their modules inside the stage at call time,
    so replacing the module attributes reaches them.
    """
    import data_synth.effects.registry as registry
    import data_synth.stage as stage

    targets = [
        (stage, "render_split", "render"),
        (registry, "apply_effects", "effects"),
        (stage, "write_nerf_synthetic", "writing"),
        (stage, "write_exr", "writing"),
    ]
    try:
        import data_synth.mitsuba_backend as mitsuba_backend

        targets.append((mitsuba_backend, "render_mitsuba", "render_mitsuba"))
    except ImportError:  # pragma: no cover - the backend module imports mitsuba lazily
        pass
    originals = [(module, name, getattr(module, name)) for module, name, _ in targets]
    try:
        for (module, name, phase), (_, _, original) in zip(targets, originals, strict=True):
            setattr(module, name, timer.wrap(phase, original))
        yield timer
    finally:
        for module, name, original in originals:
            setattr(module, name, original)


# ----------------------------------------------------------------------------------------------
# Configs


def shared_mesh_available(config_path: Path) -> bool:
    """True when the bench config's mesh file (resolved against the repo root) exists."""
    from recon.config import load_config
    from recon.config.run_config import RunConfig

    shape = load_config(config_path, RunConfig).scene.shape
    return shape.mesh_path is None or _from_repo_root(shape.mesh_path).is_file()


def _from_repo_root(path: str) -> Path:
    candidate = Path(path)
    return candidate if candidate.is_absolute() else (REPO_ROOT / candidate).resolve()


def load_bench_config(
    config_path: Path,
    splits: tuple[int, int, int],
    resolution: int,
    fallback: bool,
    spp: int | None = None,
):
    """The bench config with the views, resolution (and spp) set; mesh paths made absolute
    (relative to the repository root), or the procedural blob when fallback."""
    from recon.config import load_config
    from recon.config.run_config import RunConfig

    train, val, test = splits
    overrides = [
        f"capture.train_views={train}",
        f"capture.val_views={val}",
        f"capture.test_views={test}",
        f"capture.cameras.resolution=[{resolution}, {resolution}]",
    ]
    if spp is not None:
        overrides.append(f"capture.mitsuba_spp={spp}")
    if fallback:
        overrides += FALLBACK_OVERRIDES
    config = load_config(config_path, RunConfig, overrides=overrides)
    shape = config.scene.shape
    if shape.mesh_path is not None:
        shape.mesh_path = str(_from_repo_root(shape.mesh_path))
    if shape.texture_path is not None:
        shape.texture_path = str(_from_repo_root(shape.texture_path))
    return config


def scene_record(config, fallback: bool) -> dict:
    shape = config.scene.shape
    record = {
        "shape": Path(shape.mesh_path).name if shape.mesh_path else shape.procedural,
        "effects": [effect.name for effect in config.capture.effects],
        "backend": config.capture.backend,
    }
    if fallback:
        record["note"] = (
            "../shared/meshes/spot_triangulated.obj is absent: the procedural 'blob' "
            "(checker albedo) stands in for spot"
        )
    return record


# ----------------------------------------------------------------------------------------------
# One run


def _folder_size_mb(folder: Path) -> float:
    return round(
        sum(path.stat().st_size for path in folder.rglob("*") if path.is_file()) / 2**20, 2
    )


def synth_once(config, device: str, label: str) -> dict:
    """One timed `recon synth` of config into a temporary folder (deleted afterwards)."""
    from recon import pipeline

    timer = PhaseTimer()
    meter = common.CpuMeter()
    views = config.capture.train_views + config.capture.val_views + config.capture.test_views
    common.log(f"{label}: {views} views at {config.capture.cameras.resolution} ...")
    with tempfile.TemporaryDirectory(prefix="bench_synth_") as folder:
        out = Path(folder) / "run"
        meter.start()
        started = time.perf_counter()
        with instrumented(timer):
            pipeline.run(config, out=out, device=device, stages=["synth"])
        wall = time.perf_counter() - started
        cores = meter.cores_used()
        written = sum(
            len(json.loads(path.read_text())["frames"])
            for path in RunPaths(out).dataset_layout.split_files()
        )
        size_mb = _folder_size_mb(out)
    if written != views:
        raise RuntimeError(f"{label}: expected {views} frames written, found {written}")
    split = {phase: round(timer.seconds.get(phase, 0.0), 3) for phase in PHASES}
    split["other"] = round(max(wall - sum(split.values()), 0.0), 3)
    result = {
        "wall_s": round(wall, 3),
        "split_s": split,
        "views": views,
        "run_folder_mb": size_mb,
        "cores_used": cores,
        "load_average": common.load_average(),
    }
    if "render_mitsuba" in timer.seconds:
        result["mitsuba_render_s"] = round(timer.seconds["render_mitsuba"], 3)
    common.log(f"{label}: {wall:.2f} s ({split}, {cores} cores busy)")
    return result


# ----------------------------------------------------------------------------------------------
# Sections


def bench_own(args, fallback: bool) -> dict:
    splits = QUICK["own_splits"] if args.quick else FULL_SPLITS
    resolution = QUICK["resolution"] if args.quick else RESOLUTION
    runs = QUICK["runs"] if args.quick else args.runs
    config = load_bench_config(OWN_CONFIG, splits, resolution, fallback)
    warmup = None
    if not args.quick:
        # One tiny untimed run first: first-call costs (lazy imports, allocator, kernels) would
        # otherwise land in run 1 only.
        tiny = load_bench_config(OWN_CONFIG, QUICK["own_splits"], QUICK["resolution"], fallback)
        warmup = synth_once(tiny, args.device, "own warm-up")["wall_s"]
    measured = [synth_once(config, args.device, f"own run {k + 1}/{runs}") for k in range(runs)]
    walls = [run["wall_s"] for run in measured]
    median_wall = common.median(walls)
    # The split of the run whose wall time is the median (lower median for an even count).
    middle = sorted(range(runs), key=lambda k: walls[k])[(runs - 1) // 2]
    return {
        "config": str(OWN_CONFIG.relative_to(REPO_ROOT)),
        "scene": scene_record(config, fallback),
        "views": sum(splits),
        "splits": dict(zip(("train", "val", "test"), splits, strict=True)),
        "resolution": [resolution, resolution],
        "runs": runs,
        "warmup_s": warmup,
        "wall_s": median_wall,
        "wall_s_all": walls,
        "split_s_of_median_run": measured[middle]["split_s"],
        "per_view_ms": round(1000 * median_wall / sum(splits), 1),
        "target_s": OWN_TARGET_S,
        "meets_target": bool(median_wall < OWN_TARGET_S),
        "cores_used_all": [run["cores_used"] for run in measured],
        "load_average_all": [run["load_average"] for run in measured],
        "run_folder_mb": measured[middle]["run_folder_mb"],
    }


def _extrapolate(run: dict, views: int) -> float:
    """Wall time for views views: the per-view phases scale, the rest (mesh, scene, ground
    truth, contact sheet of at most 16 views) stays."""
    per_view = sum(run["split_s"][phase] for phase in PHASES) / run["views"]
    fixed = run["wall_s"] - per_view * run["views"]
    return round(fixed + per_view * views, 1)


def bench_mitsuba(args, fallback: bool) -> dict:
    from data_synth.mitsuba_backend import pick_variant

    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return {"skipped": "mitsuba is not installed (pip install -e '.[mitsuba]')"}
    resolution = QUICK["resolution"] if args.quick else RESOLUTION
    spp = QUICK["mitsuba_spp"] if args.quick else args.spp
    sample_views = QUICK["mitsuba_sample_views"] if args.quick else args.mitsuba_views
    full_splits = QUICK["mitsuba_full_splits"] if args.quick else FULL_SPLITS
    full_views = sum(full_splits)
    config = load_bench_config(MITSUBA_CONFIG, (sample_views, 0, 0), resolution, fallback, spp)
    sample = synth_once(config, args.device, f"mitsuba {sample_views} views")
    per_view = sample["split_s"]["render"] / sample_views
    extrapolated = _extrapolate(sample, full_views)
    report = {
        "config": str(MITSUBA_CONFIG.relative_to(REPO_ROOT)),
        "scene": scene_record(config, fallback),
        "variant": pick_variant(),
        "spp": spp,
        "resolution": [resolution, resolution],
        "sample": sample,
        "render_s_per_view": round(per_view, 3),
        "mitsuba_s_per_view": round(sample.get("mitsuba_render_s", 0.0) / sample_views, 3),
        "wall_s_per_view": round(sample["wall_s"] / sample_views, 3),
        f"extrapolated_{full_views}_views_s": extrapolated,
    }
    run_full = args.mitsuba_full == "always" or (
        args.mitsuba_full == "auto" and extrapolated <= args.mitsuba_full_budget
    )
    if not run_full:
        reason = (
            "--mitsuba-full never"
            if args.mitsuba_full == "never"
            else f"extrapolated {extrapolated} s > --mitsuba-full-budget "
            f"{args.mitsuba_full_budget:g} s"
        )
        report["full_run"] = {"skipped": reason}
        return report
    full_config = load_bench_config(MITSUBA_CONFIG, full_splits, resolution, fallback, spp)
    full = synth_once(full_config, args.device, f"mitsuba {full_views} views")
    full["extrapolation_error"] = round(extrapolated / full["wall_s"] - 1.0, 3)
    report["full_run"] = full
    return report


# ----------------------------------------------------------------------------------------------
# Entry point


def parse_arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sections", default=",".join(SECTIONS), help="own,mitsuba")
    parser.add_argument("--runs", type=int, default=3, help="timed runs of the own section")
    parser.add_argument(
        "--mitsuba-views", type=int, default=MITSUBA_SAMPLE_VIEWS, help="views timed with Mitsuba"
    )
    parser.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel")
    parser.add_argument(
        "--mitsuba-full",
        choices=["auto", "always", "never"],
        default="auto",
        help="the real 100-view Mitsuba run: auto = when extrapolated under the budget",
    )
    parser.add_argument(
        "--mitsuba-full-budget",
        type=float,
        default=MITSUBA_FULL_BUDGET_S,
        help="seconds the extrapolated 100-view Mitsuba run may take (auto mode)",
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto (recon's renderer)")
    parser.add_argument("--threads", type=int, help="torch threads (default: os.cpu_count())")
    parser.add_argument("--quick", action="store_true", help="smoke test: tiny and fast")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    sections = [name.strip() for name in args.sections.split(",") if name.strip()]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        parser.error(f"--sections: unknown {unknown} (known: {', '.join(SECTIONS)})")
    if args.runs < 1 or args.mitsuba_views < 1 or args.spp < 1:
        parser.error("--runs, --mitsuba-views and --spp must be at least 1")
    args.sections = sections
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse_arguments(argv)
    threads = common.configure_threads(args.threads)
    args.device = common.resolve_device(args.device)
    fallback = not shared_mesh_available(OWN_CONFIG)
    if fallback:
        common.log("../shared/meshes is absent: benchmarking the procedural blob instead of spot")
    report: dict = {
        "benchmark": "synth",
        "environment": common.environment(args.device),
        "settings": {
            "sections": args.sections,
            "quick": args.quick,
            "runs": QUICK["runs"] if args.quick else args.runs,
            "threads": threads,
            "device": args.device,
        },
    }
    started = time.perf_counter()
    if "own" in args.sections:
        report["own"] = bench_own(args, fallback)
    if "mitsuba" in args.sections:
        report["mitsuba"] = bench_mitsuba(args, fallback)
    report["total_s"] = round(time.perf_counter() - started, 1)
    text = json.dumps(report, indent=2, default=_json_default)
    print(text)
    if args.out:
        common.write_json_atomic(args.out, json.loads(text))
    return json.loads(text)


def _json_default(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)


if __name__ == "__main__":
    main()
