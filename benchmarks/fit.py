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


TITLE = "Reconstruction"
# How the scenes are named in the summary table.
SCENE_LABELS = {"default": "default (torus, genus 1)", "bob": "bob (genus 1, hole kept)"}
RECIPE = (
    "256², 48 training views, 8 held-out views, captures from data_synth without effects, "
    "whole pipeline per scene (synth, fit, evaluate, report), geometry metrics exact "
    "(point-to-surface) at 100k samples, in units of the reference diagonal:"
)


def _exponent(value: float) -> str:
    """3.9e-4 rather than 3.9e-04."""
    mantissa, exponent = f"{value:.1e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def markdown(result: dict) -> str:
    """The summary table of a result (docs/benchmarks.md and the README): one row per scene and
    the targets."""
    columns = [
        ("time", "seconds", lambda v: f"{v:.0f} s"),
        ("PSNR (sRGB)", "psnr", lambda v: f"{v:.2f} dB"),
        ("SSIM", "ssim", lambda v: f"{v:.3f}"),
        ("Chamfer-L1", "chamfer_l1", _exponent),
        ("F1@1%", "f1@1%", lambda v: f"{v:.3f}"),
        ("normal consistency", "normal_consistency", lambda v: f"{v:.3f}"),
        ("faces", "faces", lambda v: f"{v:,}"),
    ]
    lines = [RECIPE, "", "| scene | " + " | ".join(name for name, _, _ in columns) + " |"]
    lines.append("|---" * (len(columns) + 1) + "|")
    for scene in result["scenes"]:
        label = SCENE_LABELS.get(scene["scene"], scene["scene"])
        if "skipped" in scene or "failed" in scene:
            reason = scene.get("skipped") or f"failed (exit {scene['failed']})"
            lines.append(f"| {label} | {reason} |" + " |" * (len(columns) - 1))
            continue
        cells = ["" if scene.get(key) is None else form(scene[key]) for _, key, form in columns]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    targets = result.get("targets", {})
    units = {"seconds": " s", "psnr": " dB"}
    cells = []
    for _, key, _ in columns:
        if key not in targets:
            cells.append("")
            continue
        comparison, bound = targets[key]
        if key == "faces":
            text = f"{bound / 1000:g}k"
        elif 0 < abs(bound) < 0.01:
            mantissa, exponent = f"{bound:e}".split("e")
            text = f"{float(mantissa):g}e{int(exponent)}"
        else:
            text = f"{bound:g}{units.get(key, '')}"
        cells.append(f"{comparison} {text}")
    lines.append("| target | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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
