"""Appearance-model benchmark: `pbr` against `lambert` on the same glossy path-traced captures.

For the config (default configs/bench/glossy_torus_studio.yaml: Mitsuba's principled BSDF,
roughness 0.25, a studio environment) it runs `recon run` twice in fresh processes with the
same seed (so the same captures), once per fit.material, and prints one JSON object: held-out
PSNR (all pixels and masked), Chamfer-L1, the fitted roughness against the true one (pbr), and
wall time, beside the issue's targets. --size/--views/--steps shrink the run for a small
machine. Run from the repository root:

    recon-bench material [--size 64] [--views 16] [--test-views 4]
        [--geometry-steps 150] [--texture-steps 100] [--spp 32] [--out runs/bench_material]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks import common
from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]

TARGETS = {"psnr": (">=", 32.0), "roughness_error": ("<=", 0.05), "seconds": ("<=", 600.0)}


def _true_roughness(config: dict) -> float | None:
    for effect in config.get("capture", {}).get("effects", []):
        if effect.get("name") == "specular":
            return float(effect.get("parameters", {}).get("roughness", 0.25))
    return None


def run_material(material: str, config: Path, out: Path, overrides: list[str]) -> dict:
    run_folder = out / material
    command = [sys.executable, "-m", "recon.cli", "run", str(config), "--out", str(run_folder)]
    command += ["--force", "--set", f"fit.material={material}"]
    for override in overrides:
        command += ["--set", override]
    print(f"[bench_material] {' '.join(command)}", file=sys.stderr, flush=True)
    started = time.perf_counter()
    completed = subprocess.run(command, cwd=REPO_ROOT, stdout=sys.stderr, stderr=sys.stderr)
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        return {"material": material, "failed": completed.returncode, "seconds": seconds}
    paths = RunPaths(run_folder)
    metrics = json.loads(paths.metrics.read_text())
    figures = {
        "material": material,
        "run_folder": str(run_folder),
        "seconds": round(seconds, 1),
        "stage_seconds": metrics.get("stage_seconds", {}),
        "psnr": metrics["image"]["psnr"],
        "psnr_masked": metrics["image"].get("psnr_masked"),
        "ssim": metrics["image"].get("ssim"),
        "chamfer_l1": metrics.get("geometry", {}).get("chamfer_l1"),
    }
    if material == "pbr":
        import yaml

        from recon.io.meshes import load_material_maps

        resolved = yaml.safe_load(paths.resolved_config.read_text())
        maps = load_material_maps(paths.fitted_mesh)
        truth = _true_roughness(resolved)
        roughness = float(maps[..., 0].median())
        figures.update(
            {
                "roughness_median": roughness,
                "roughness_true": truth,
                "roughness_error": None if truth is None else abs(roughness - truth),
                "metalness_median": float(maps[..., 1].median()),
            }
        )
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--config", default="configs/bench/glossy_torus_studio.yaml")
    parser.add_argument("--out", default="runs/bench_material")
    parser.add_argument("--size", type=int, default=None, help="image side (config's if unset)")
    parser.add_argument("--views", type=int, default=None, help="training views")
    parser.add_argument("--test-views", type=int, default=None)
    parser.add_argument("--geometry-steps", type=int, default=None)
    parser.add_argument("--texture-steps", type=int, default=None)
    parser.add_argument("--spp", type=int, default=None, help="Mitsuba samples per pixel")
    parser.add_argument("--materials", nargs="+", default=["lambert", "pbr"])
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    arguments = parser.parse_args(argv)
    overrides = []
    if arguments.size is not None:
        size = arguments.size
        overrides += [
            f"capture.cameras.resolution=[{size},{size}]",
            f"fit.geometry.resolutions=[{max(16, size // 2)},{size}]",
            f"fit.texture.texture_size={max(64, 4 * size)}",
        ]
    for value, key in (
        (arguments.views, "capture.train_views"),
        (arguments.test_views, "capture.test_views"),
        (arguments.geometry_steps, "fit.geometry.steps"),
        (arguments.texture_steps, "fit.texture.steps"),
        (arguments.spp, "capture.mitsuba_spp"),
    ):
        if value is not None:
            overrides.append(f"{key}={value}")
    overrides += arguments.overrides
    config = (REPO_ROOT / arguments.config).resolve()
    results = [
        run_material(material, config, Path(arguments.out).resolve(), overrides)
        for material in arguments.materials
    ]
    print(
        json.dumps(
            {
                "config": arguments.config,
                "overrides": overrides,
                "targets": {key: list(rule) for key, rule in TARGETS.items()},
                "environment": common.environment("cpu"),
                "results": results,
            },
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
