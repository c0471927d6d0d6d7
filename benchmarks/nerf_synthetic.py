"""NeRF-synthetic style scenes from the Mitsuba world, fitted and scored like NeRF-synthetic.

For each scene (configs/bench/nerf_synthetic_SCENE.yaml: a textured object on white, cameras on
the upper hemisphere, glossy material and shadows path traced by Mitsuba, 200 px, 48 training
and 8 test views) it runs `recon run CONFIG` in a fresh process (synth, fit, evaluate, report)
and prints one JSON object: held-out PSNR over the whole image (what NeRF-synthetic papers
report, on the white background) and over the object, SSIM, the seconds and the load average,
beside nvdiffrec's published figure and the differences in setting. Run from the repository
root (needs ../shared/meshes and mitsuba):

    recon-bench nerf-synthetic [--scenes spot,bob] [--out runs/bench_nerf_synthetic]
        [--set key=value ...] [--json FILE]
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

from benchmarks import common
from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = {
    "method": "nvdiffrec (Munkberg et al., CVPR 2022)",
    "psnr": 29.0,
    "setting": (
        "NeRF-synthetic's 8 Blender scenes (Cycles renders), 800 x 800 px, 100 training and "
        "200 test views, fitted on a GPU for about an hour per scene (5000 + 5000 iterations)"
    ),
}
OURS = (
    "Mitsuba-rendered scenes of the project's meshes (not the Blender scenes), 200 x 200 px, "
    "48 training and 8 test views, fitted on 2 shared CPU cores (300 + 200 steps), "
    "Lambertian material under an SH light + sun against a glossy (GGX) truth with shadows"
)


def run_scene(scene: str, out: Path, overrides: list[str], threads: int) -> dict:
    config = REPO_ROOT / "configs" / "bench" / f"nerf_synthetic_{scene}.yaml"
    if not config.is_file():
        return {"error": f"{config}: no such config"}
    environment = dict(os.environ)
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        environment[key] = str(threads)
    run = out / scene
    command = [sys.executable, "-m", "recon.cli", "run", str(config), "--out", str(run)]
    command += ["--force", "--device", "cpu"]
    for override in overrides:
        command += ["--set", override]
    load_before = common.load_average()
    started = time.perf_counter()
    completed = subprocess.run(
        command, cwd=REPO_ROOT, env=environment, capture_output=True, text=True
    )
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        return {"error": completed.stderr[-1500:], "returncode": completed.returncode}
    metrics = json.loads(RunPaths(run).metrics.read_text())
    image = metrics["image"]
    return {
        "psnr": round(image["psnr"], 3),
        "psnr_masked": round(image["psnr_masked"], 3) if "psnr_masked" in image else None,
        "ssim": round(image["ssim"], 4) if "ssim" in image else None,
        "test_views": metrics["views"],
        "chamfer": metrics.get("geometry", {}).get("chamfer_l1"),
        "seconds": round(seconds, 1),
        "stage_seconds": metrics.get("stage_seconds", {}),
        "load_average_before": load_before,
        "load_average_after": common.load_average(),
        "difference_to_published_db": round(image["psnr"] - PUBLISHED["psnr"], 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="spot,bob")
    parser.add_argument("--out", default="runs/bench_nerf_synthetic")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], help="config override key=value")
    parser.add_argument("--json", help="also write the result here")
    arguments = parser.parse_args(argv)
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        print(json.dumps({"skipped": "mitsuba is not installed (pip install -e '.[mitsuba]')"}))
        return 0
    result: dict = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "published": PUBLISHED,
        "this_setting": OURS,
        "overrides": arguments.set,
        "scenes": {},
    }
    for scene in arguments.scenes.split(","):
        result["scenes"][scene] = run_scene(
            scene, Path(arguments.out), arguments.set, arguments.threads
        )
    scored = [value["psnr"] for value in result["scenes"].values() if "psnr" in value]
    if scored:
        result["mean_psnr"] = round(sum(scored) / len(scored), 3)
    print(json.dumps(result, indent=2))
    if arguments.json:
        common.write_json_atomic(arguments.json, result)
    return 0 if scored else 1


if __name__ == "__main__":
    sys.exit(main())
