"""Real-capture benchmark: ../shared/captures/ethiopian_head (66 photos, 384², masks, LLFF
poses, off-centre, a turntable) fitted from its raw layout with configs/real_capture.yaml.

Runs, each in a fresh process, `recon fit configs/real_capture.yaml --data DATA --out RUN`
(stages fit, evaluate, report), then prints one JSON object: held-out masked PSNR (object pixels
only) and whole-image PSNR, the fit's and the whole run's seconds, the peak resident memory of
the run (env.json, resource.getrusage), the fitted mesh's faces and genus, the normalisation
found, and the issue's targets side by side. Run from the repository root:

    recon-bench real-capture [--data FOLDER] [--out runs/bench_real_capture]
        [--threads 2] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from benchmarks.record import commit as record_commit
from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO_ROOT.parent / "shared" / "captures" / "ethiopian_head"
TARGETS = {
    "psnr_masked": (">=", 23.0),
    "seconds": ("<=", 600.0),
    "peak_memory_mb": ("<=", 8192.0),
}


def _meets(value: float | None, rule: tuple[str, float]) -> bool | None:
    if value is None:
        return None
    comparison, bound = rule
    return value <= bound if comparison == "<=" else value >= bound


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument("--out", default="runs/bench_real_capture")
    parser.add_argument("--threads", type=int, default=2, help="torch/BLAS threads")
    parser.add_argument("--set", action="append", default=[], help="config override key=value")
    arguments = parser.parse_args(argv)
    data = Path(arguments.data)
    if not (data / "poses_bounds.npy").exists():
        print(json.dumps({"error": f"{data}: no poses_bounds.npy (is ../shared present?)"}))
        return 2
    environment = dict(os.environ)
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        environment[key] = str(arguments.threads)
    command = [
        sys.executable,
        "-m",
        "recon.cli",
        "fit",
        str(REPO_ROOT / "configs" / "real_capture.yaml"),
        "--data",
        str(data),
        "--out",
        arguments.out,
        "--force",
        "--device",
        "cpu",
    ]
    for override in arguments.set:
        command += ["--set", override]
    # The commit the run starts from (HEAD may move while it runs).
    commit = record_commit()
    started_at = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    started = time.perf_counter()
    completed = subprocess.run(command, env=environment, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        print(json.dumps({"error": completed.stderr[-2000:], "returncode": completed.returncode}))
        return 1
    run = RunPaths(Path(arguments.out))
    metrics = json.loads(run.metrics.read_text())
    env = json.loads(run.environment.read_text())
    normalization = json.loads(run.normalization.read_text())
    notes = [line for line in completed.stderr.splitlines() if line.startswith("recon: ")]
    result = {
        "date": started_at,
        "commit": commit,
        "data": str(data),
        "command": " ".join(command[2:]),
        "threads": arguments.threads,
        "views": {"test": metrics["views"]},
        "psnr_masked": metrics["image"].get("psnr_masked"),
        "psnr": metrics["image"]["psnr"],
        "ssim_masked": metrics["image"].get("ssim_masked"),
        "seconds": round(seconds, 1),
        "stage_seconds": env.get("stage_seconds", {}),
        "peak_memory_mb": max(env.get("peak_memory_mb", {"none": None}).values()),
        "faces": metrics["mesh"]["faces"],
        "genus": metrics["mesh"]["genus"],
        "watertight": metrics["mesh"]["watertight"],
        "components": metrics["mesh"]["components"],
        "normalization": {key: normalization[key] for key in ("scale", "centre", "up")},
        "messages": notes,
    }
    result["targets"] = {
        key: {"rule": f"{rule[0]} {rule[1]}", "met": _meets(result[key], rule)}
        for key, rule in TARGETS.items()
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
