"""Tiny sweeps for the sweep tests: the quickstart scene at 32 px, fitted in a few steps."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]


def tiny_config(folder: Path) -> Path:
    """A run config that synthesises and fits in well under a second per trial."""
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit"]
    config["device"] = "cpu"
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 4, "val_views": 0, "test_views": 2})
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 32
    config["fit"] = {
        "hull_resolution": 16,
        "checkpoint_every": 1,
        "geometry": {"steps": 3, "resolutions": [32], "remesh_every": 0, "views_per_step": 2},
        "texture": {"steps": 2, "texture_size": 64, "views_per_step": 2},
    }
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def write_sweep(folder: Path, out: Path, **changes) -> Path:
    """A sweep file of 3 tiny trials (geometry steps 1 and 3 at seed 0, steps 3 at seed 1 via a
    case) collecting the fit's final loss and PSNR; changes replace or add keys."""
    sweep = {
        "base": str(tiny_config(folder)),
        "grid": {"fit.geometry.steps": [1, 3]},
        "seeds": [0, 1],
        "metrics": ["fit.loss", "fit.psnr_linear"],
        "out": str(out),
        "cpus_per_trial": 1,
    }
    sweep.update(changes)
    path = folder / f"sweep_{out.name}.yaml"
    path.write_text(yaml.safe_dump(sweep))
    return path


def three_trials(folder: Path, out: Path, **changes) -> Path:
    """Exactly three trials: two grid points at seed 0 plus one at seed 1 (as cases)."""
    changes.setdefault("grid", None)
    changes.setdefault(
        "cases",
        [["fit.geometry.steps=1"], ["fit.geometry.steps=3"], ["fit.texture.steps=1"]],
    )
    changes.setdefault("seeds", [0])
    sweep = write_sweep(folder, out, **changes)
    data = yaml.safe_load(sweep.read_text())
    data = {key: value for key, value in data.items() if value is not None}
    sweep.write_text(yaml.safe_dump(data))
    return sweep


def records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]


def metrics_by_trial(out: Path) -> dict[str, dict]:
    return {record["trial_id"]: record["metrics"] for record in records(out)}
