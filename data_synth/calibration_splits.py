"""Completing a synthetic run folder with calibration frames its config did not ask for.

Flat-field and line-target frames (data_synth.flat_field, data_synth.line_target) are captures
the fit never reads: a run made before the config asked for them can take them afterwards, and
its fit stays the fit the new config makes. The frames draw from their own seeded streams, so
they are the frames a fresh synth with the new config writes (tests/data_synth/ check this).
Used by scripts/add_flat_field.py and by the blind benchmark's stored cases.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from data_synth.effects.base import Capture
from recon.config import config_hash, dump_resolved, load_config
from recon.config.run_config import EffectConfig, RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.datasets import write_nerf_synthetic
from recon.io.run_folder import RunPaths

CALIBRATION_SPLITS = ("flat_field", "line_target")


def write_frames(
    dataset: Path, split: str, capture: Capture, write_exr: bool, force: bool = False
) -> None:
    """A calibration capture's frames as the dataset's split (NeRF-synthetic layout, linear EXR
    beside the 8-bit PNG with write_exr; an existing split only with force)."""
    write_nerf_synthetic(
        dataset,
        split,
        capture.cameras,
        capture.images,
        capture.alpha,
        write_exr=write_exr,
        force=force,
    )


def _writer(split: str):
    from data_synth.flat_field import write_flat_field
    from data_synth.line_target import write_line_target

    return {"flat_field": write_flat_field, "line_target": write_line_target}[split]


def add_calibration_split(
    run: Path, split: str, views: int, truth_file: Path | None, force: bool = False
) -> dict:
    """Write split (one of CALIBRATION_SPLITS) with views frames into run's dataset through the
    run's effects: the config's, plus the withheld ones from truth_file (required when the run
    withheld effects). Adds the realised parameters to truth_file (withheld effects) or
    ground_truth/effects.json (the others), rewrites config.resolved.yaml with the split's
    views, and updates a bench_fit.json's config hash. An existing split only with force."""
    if split not in CALIBRATION_SPLITS:
        raise ReconError(f"split: expected one of {CALIBRATION_SPLITS}, got {split!r}")
    paths = RunPaths(run)
    config_path = paths.resolved_config
    dataset = paths.dataset
    if not config_path.exists() or not dataset.is_dir():
        raise ReconError(f"{run}: not a synthetic run folder (no config.resolved.yaml or dataset/)")
    if paths.dataset_layout.split_file(split).is_file() and not force:
        raise ReconError(f"{dataset}: already has a {split} split (pass --force)")
    config = load_config(config_path, RunConfig)
    frames = replace(getattr(config.capture, split), views=views)
    capture = replace(config.capture, **{split: frames})
    config = replace(config, capture=capture)
    effects_path = paths.truth_effects
    recorded = json.loads(effects_path.read_text())
    truth = None
    if recorded.get("withheld"):
        if truth_file is None or not truth_file.exists():
            raise ReconError(f"{run}: its effects were withheld and {truth_file} is missing")
        truth = json.loads(truth_file.read_text())
    withheld = [
        EffectConfig(item["name"], dict(item["parameters"]))
        for item in (truth or {}).get("withheld", [])
    ]
    effects = list(capture.effects) + withheld
    realised = _writer(split)(dataset, capture, effects, config.seed, force=force)
    withheld_names = {effect.name for effect in withheld}
    recorded.setdefault("realised", {})[split] = [
        item for item in realised if item["name"] not in withheld_names
    ]
    atomic_write_json(effects_path, recorded)
    if truth is not None and truth_file is not None:
        truth.setdefault("realised", {})[split] = [
            item for item in realised if item["name"] in withheld_names
        ]
        atomic_write_json(truth_file, truth)
    dump_resolved(config, config_path)
    fit_record_path = run / "bench_fit.json"
    if fit_record_path.exists():
        fit_record = json.loads(fit_record_path.read_text())
        fit_record["config_hash"] = config_hash(config)
        atomic_write_json(fit_record_path, fit_record)
    return {
        "run": str(run),
        "split": split,
        "views": views,
        "effects": [item["name"] for item in realised],
    }
