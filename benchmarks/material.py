"""Appearance-model benchmark: `pbr` against `lambert` on the same glossy path-traced captures.

For each config (default: configs/bench/glossy_torus_studio.yaml, a procedural torus with
Mitsuba's principled BSDF at roughness 0.25 in a studio, and configs/bench/glossy_spot_sky.yaml,
spot at roughness 0.35 under a sky with a sun) it runs `recon run` once per fit.material in
fresh processes with the same seed (so the same captures), and prints one JSON object: held-out
PSNR (all pixels and masked), Chamfer-L1 (in reference diagonals), the fitted roughness against
the true one (pbr: its median against a uniform truth, and, where the world's reference carries
its true maps, the surface comparison of metrics.json's material section as surface_*) and
wall time, beside the issue's targets. An optional spatially varying case: --configs
configs/bench/glossy_torus_checker_roughness.yaml. --size/--views/--steps shrink the run for
a small machine; `--record` writes docs/bench/material.json (benchmarks.record, whose
summary is markdown() here). Run from the repository root:

    recon-bench material [--record] [--configs A.yaml B.yaml] [--size 64] [--views 16]
        [--test-views 4] [--geometry-steps 150] [--texture-steps 100] [--spp 32]
        [--out runs/bench_material]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from benchmarks import common
from benchmarks.record import commit as record_commit
from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]

TARGETS = {
    "psnr": (">=", 32.0),
    "chamfer_l1": ("<=", 1e-3),
    "roughness_error": ("<=", 0.05),
    "seconds": ("<=", 600.0),
}
DEFAULT_CONFIGS = ["configs/bench/glossy_torus_studio.yaml", "configs/bench/glossy_spot_sky.yaml"]


def _true_roughness(config: dict) -> float | None:
    """The world's uniform roughness: the specular effect's, else the scene material's (0.3 by
    default); None without a specular effect or where the roughness varies over the surface
    (scene.material.roughness_texture: the evaluate stage's material section scores it)."""
    material = config.get("scene", {}).get("material", {})
    if material.get("roughness_texture", "none") != "none":
        return None
    for effect in config.get("capture", {}).get("effects", []):
        if effect.get("name") == "specular":
            return float(
                effect.get("parameters", {}).get("roughness", material.get("roughness", 0.3))
            )
    return None


# metrics.json's material section (the fitted maps against the true ones over the surface,
# recon/metrics/material.py) as the benchmark reports it: key here <- key there.
SURFACE_KEYS = {
    "surface_roughness_mae": "roughness_mae",
    "surface_roughness_median_error": "roughness_median_error",
    "surface_roughness_within_tolerance": "roughness_within_tolerance",
    "surface_roughness_uniform_mae": "roughness_uniform_mae",
    "surface_metalness_mae": "metalness_mae",
    "surface_metalness_within_tolerance": "metalness_within_tolerance",
    "surface_compared_fraction": "compared_fraction",
}


def _meets(value: float | None, rule: tuple[str, float]) -> bool | None:
    if value is None:
        return None
    comparison, bound = rule
    return value <= bound if comparison == "<=" else value >= bound


def run_material(material: str, config: Path, out: Path, overrides: list[str]) -> dict:
    run_folder = out / config.stem / material
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
    # recon's Chamfer-L1 is in units of the reference's bounding-box diagonal already.
    figures["chamfer_l1_floor"] = metrics.get("geometry", {}).get("sampling_floor")
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
        surface = metrics.get("material")
        if surface is not None:
            figures.update({key: surface.get(source) for key, source in SURFACE_KEYS.items()})
    figures["targets"] = {
        key: _meets(figures.get(key), rule) for key, rule in TARGETS.items() if key in figures
    }
    return figures


def markdown(result: dict) -> str:
    """The result as a Markdown table: the summary of docs/bench/material.json (--record)."""
    environment = result["environment"]
    lines = [
        f"Commit {result['commit']}, {result['date']}; {environment['cpu_count']} CPUs "
        f"({environment['cpu_model']}), load average at start {environment['load_average_at_start']}"
        f", torch {environment['torch']}, mitsuba {environment['mitsuba']}.  ",
        f"Overrides: `{' '.join(result['overrides']) or 'none'}`.  ",
        "Targets: " + ", ".join(f"{key} {rule[0]} {rule[1]}" for key, rule in TARGETS.items()),
        "",
        "| scene | material | PSNR | masked PSNR | Chamfer-L1 / diagonal | roughness (true) "
        "| surface roughness MAE (share within tolerance) | metalness | seconds |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def number(value, digits=2, scientific=False):
        if value is None:
            return "-"
        return f"{value:.{digits}e}" if scientific else f"{value:.{digits}f}"

    for scene in result["scenes"]:
        for row in scene["results"]:
            if "failed" in row:
                lines.append(
                    f"| {Path(scene['config']).stem} | {row['material']} | failed ({row['failed']}) "
                    "| | | | | | |"
                )
                continue
            roughness = "-"
            if row.get("roughness_median") is not None:
                roughness = f"{row['roughness_median']:.3f} ({row['roughness_true']})"
            surface = "-"
            if row.get("surface_roughness_mae") is not None:
                surface = (
                    f"{row['surface_roughness_mae']:.3f} "
                    f"({100 * row['surface_roughness_within_tolerance']:.0f} %)"
                )
            lines.append(
                f"| {Path(scene['config']).stem} | {row['material']} | {number(row['psnr'])} "
                f"| {number(row['psnr_masked'])} "
                f"| {number(row.get('chamfer_l1'), 2, True)} | {roughness} | {surface} "
                f"| {number(row.get('metalness_median'), 3)} | {row['seconds']:.0f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS)
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
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    commit = record_commit()  # HEAD may move while the runs go on
    environment = common.environment("cpu")
    scenes = []
    for name in arguments.configs:
        config = (REPO_ROOT / name).resolve()
        results = [
            run_material(material, config, Path(arguments.out).resolve(), overrides)
            for material in arguments.materials
        ]
        scenes.append({"config": name, "results": results})
    result = {
        "date": started,
        "commit": commit,
        "command": "recon-bench material " + " ".join(argv if argv is not None else sys.argv[1:]),
        "overrides": overrides,
        "targets": {key: list(rule) for key, rule in TARGETS.items()},
        "environment": environment,
        "load_average_at_end": common.load_average(),
        "scenes": scenes,
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
