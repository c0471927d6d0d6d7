"""recon sweep: 8 tiny fits one after another (local backend) vs as Ray tasks (JSON on stdout).

Figures (each the median over --repeats):
  local_seconds          the local backend's wall time for the 8 trials (1 torch thread each)
  local_2threads_seconds the same with 2 torch threads per trial (the sequential alternative
                         that also uses both cores)
  ray_seconds            the Ray backend on an already started local Ray (num_cpus = --cpus,
                         1 CPU per trial): the sweep's own cost
  ray_warm_workers_seconds  the same sweep again on that Ray (workers have imported recon)
  ray_cold_seconds       the same including starting and stopping the local Ray
  ray_start_seconds      ray.init alone; ray_first_task_seconds a first trivial task after it
                         (a worker process is spawned)
  speedup                local_seconds / ray_seconds (and vs local_2threads_seconds)
  overhead_per_trial     Ray's slot time not spent inside a trial: (ray_seconds x cpus -
                         sum of the trials' own seconds) / trials

Usage: recon-bench sweep [--trials 8] [--repeats 3] [--cpus 2] [--steps 12]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import yaml

from benchmarks.record import commit

REPO_ROOT = Path(__file__).resolve().parents[1]


def tiny_sweep(folder: Path, out: Path, trials: int, steps: int, threads: int) -> Path:
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit"]
    config["device"] = "cpu"
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 8, "val_views": 0, "test_views": 2})
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 32
    config["fit"] = {
        "hull_resolution": 16,
        "geometry": {"steps": steps, "resolutions": [32], "remesh_every": 0, "views_per_step": 4},
        "texture": {"steps": steps // 2, "texture_size": 64, "views_per_step": 4},
    }
    (folder / "tiny.yaml").write_text(yaml.safe_dump(config))
    sweep = {
        "base": str(folder / "tiny.yaml"),
        "seeds": list(range(trials)),
        "metrics": ["fit.loss"],
        "out": str(out),
        "cpus_per_trial": threads,
    }
    path = folder / f"{out.name}.yaml"
    path.write_text(yaml.safe_dump(sweep))
    return path


def timed_sweep(path: Path, backend: str, **options) -> tuple[float, list[float]]:
    from recon.sweep.results import read_records
    from recon.sweep.sweep import run_sweep

    started = time.perf_counter()
    result = run_sweep(path, backend=backend, progress=lambda text: None, **options)
    seconds = time.perf_counter() - started
    if result["failed"]:
        raise SystemExit(f"bench_sweep: trials failed: {result['failed']}")
    records = read_records(Path(result["out"]) / "results.jsonl")
    return seconds, [record["seconds"] for record in records]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray")
    parser.add_argument("--steps", type=int, default=12, help="geometry steps per fit")
    arguments = parser.parse_args(argv)

    import ray
    import torch

    figures: dict[str, list[float]] = {}

    def add(name: str, value: float) -> None:
        figures.setdefault(name, []).append(value)

    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for repeat in range(arguments.repeats):

            def sweep(name: str, threads: int = 1, repeat: int = repeat) -> Path:
                out = folder / f"{name}_{repeat}"
                return tiny_sweep(folder, out, arguments.trials, arguments.steps, threads)

            seconds, trial_seconds = timed_sweep(sweep("local"), "local")
            add("local_seconds", seconds)
            add("local_trial_seconds", statistics.median(trial_seconds))
            seconds, _ = timed_sweep(sweep("local2", threads=2), "local")
            add("local_2threads_seconds", seconds)
            started = time.perf_counter()
            ray.init(
                num_cpus=arguments.cpus,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
            add("ray_start_seconds", time.perf_counter() - started)
            started = time.perf_counter()
            ray.get(ray.remote(lambda: os.getpid()).remote())
            add("ray_first_task_seconds", time.perf_counter() - started)
            seconds, trial_seconds = timed_sweep(sweep("ray"), "ray")
            add("ray_seconds", seconds)
            add("ray_trial_seconds", statistics.median(trial_seconds))
            add(
                "overhead_per_trial",
                (seconds * arguments.cpus - sum(trial_seconds)) / arguments.trials,
            )
            # The same sweep again on the same Ray: its workers have imported recon and torch.
            seconds, trial_seconds = timed_sweep(sweep("ray_again"), "ray")
            add("ray_warm_workers_seconds", seconds)
            add(
                "overhead_per_trial_warm_workers",
                (seconds * arguments.cpus - sum(trial_seconds)) / arguments.trials,
            )
            ray.shutdown()
            seconds, _ = timed_sweep(sweep("ray_cold"), "ray", num_cpus=arguments.cpus)
            add("ray_cold_seconds", seconds)
    medians = {name: round(statistics.median(values), 3) for name, values in figures.items()}
    medians["speedup"] = round(medians["local_seconds"] / medians["ray_seconds"], 3)
    medians["speedup_warm_workers"] = round(
        medians["local_seconds"] / medians["ray_warm_workers_seconds"], 3
    )
    medians["speedup_vs_local_2threads"] = round(
        medians["local_2threads_seconds"] / medians["ray_seconds"], 3
    )
    report = {
        "what": f"{arguments.trials} tiny fits (32 px, {arguments.steps} geometry steps), "
        f"local vs Ray with {arguments.cpus} CPUs, 1 CPU per trial",
        "medians": medians,
        "all": {name: [round(value, 3) for value in values] for name, values in figures.items()},
        "repeats": arguments.repeats,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        # The machine is shared: the load says how much of it the benchmark had.
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "ray": ray.__version__,
        "commit": commit(),
        "command": " ".join(["recon-bench sweep", *(sys.argv[1:] if argv is None else argv)]),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
