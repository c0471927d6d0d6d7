"""Reconstruction benchmark: spot, bob (../shared/meshes) and the default scene at 256², 48
training views, 8 held-out views, captures from data_synth without effects.

Runs `recon run configs/bench/fit_<scene>.yaml` for each scene in a fresh process (so each
scene's time is the whole pipeline's) and prints one JSON object with the metrics and the
issue's targets side by side. Run from the repository root:

    recon-bench fit [--scenes spot bob default] [--out runs/bench_fit] [--set k=v ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"
TARGETS = {
    "seconds": ("<=", 600.0),
    "psnr": (">=", 32.0),
    "chamfer_l1": ("<=", 2e-3),
    "f1@1%": (">=", 0.98),
    "normal_consistency": (">=", 0.97),
    "faces": ("<=", 20000),
}


def _meets(value: float | None, rule: tuple[str, float]) -> bool | None:
    if value is None:
        return None
    comparison, bound = rule
    return value <= bound if comparison == "<=" else value >= bound


def run_scene(scene: str, out: Path, overrides: list[str]) -> dict:
    config = REPO_ROOT / "configs" / "bench" / f"fit_{scene}.yaml"
    if scene in ("spot", "bob") and not SHARED_MESHES.is_dir():
        return {"scene": scene, "skipped": f"{SHARED_MESHES} is absent"}
    run_folder = out / scene
    command = [
        sys.executable,
        "-m",
        "recon.cli",
        "run",
        str(config),
        "--out",
        str(run_folder),
        "--force",
    ]
    for override in overrides:
        command += ["--set", override]
    print(f"[bench_fit] {scene}: {' '.join(command)}", file=sys.stderr, flush=True)
    started = time.perf_counter()
    completed = subprocess.run(command, cwd=REPO_ROOT, stdout=sys.stderr, stderr=sys.stderr)
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        return {"scene": scene, "failed": completed.returncode, "seconds": seconds}
    metrics = json.loads(RunPaths(run_folder).metrics.read_text())
    figures = {
        "seconds": round(seconds, 1),
        "psnr": metrics["image"]["psnr"],
        "ssim": metrics["image"]["ssim"],
        "psnr_linear": metrics["image"]["psnr_linear"],
        "chamfer_l1": metrics.get("geometry", {}).get("chamfer_l1"),
        "f1@1%": metrics.get("geometry", {}).get("f1@1%"),
        "normal_consistency": metrics.get("geometry", {}).get("normal_consistency"),
        "hausdorff_p95": metrics.get("geometry", {}).get("hausdorff_p95"),
        "faces": metrics["mesh"]["faces"],
        "watertight": metrics["mesh"].get("watertight"),
        "genus": metrics["mesh"].get("genus"),
        "stage_seconds": metrics.get("stage_seconds", {}),
    }
    figures["meets_targets"] = {
        key: _meets(figures.get(key), rule) for key, rule in TARGETS.items()
    }
    return {"scene": scene, "run_folder": str(run_folder), **figures}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["default", "spot", "bob"])
    parser.add_argument("--out", default="runs/bench_fit")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    arguments = parser.parse_args(argv)
    results = [
        run_scene(scene, Path(arguments.out), arguments.overrides) for scene in arguments.scenes
    ]
    print(
        json.dumps(
            {"targets": {k: list(v) for k, v in TARGETS.items()}, "scenes": results}, indent=2
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
