"""Add flat-field frames to synthetic run folders made before the config asked for them.

    python scripts/add_flat_field.py RUN [RUN ...] [--views 2] [--truth-dir DIR] [--force]

This is data_synth's (the world's) side, not the diagnosis': for each RUN it reads
RUN/config.resolved.yaml, sets capture.flat_field.views, and renders the frames through the
run's effects (the config's, plus the withheld ones from the truth file TRUTH_DIR/RUN_NAME.json,
by default RUN/../truth as recon-bench diagnose-blind lays it out) with data_synth.flat_field, the
function the synth stage calls: the frames draw from their own seeded streams, so they are the
frames a fresh synth with the new config writes (tests/data_synth/test_flat_field.py checks
this). It then writes RUN/dataset/flat_field, adds the realised parameters to the truth file
(withheld effects) or ground_truth/effects.json (the others), rewrites config.resolved.yaml,
and updates a blind benchmark case's bench_fit.json to the new config's hash: the fit never reads
the flat-field split, so the stored fit is the one the new config makes.

How the README's benchmark figures with flat fields were made (fits from before the frames):

    python scripts/add_flat_field.py runs/bench_diagnose/*/*_seed*
    recon-bench diagnose --reuse-fits --clean 6
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path


def add_flat_field(run: Path, views: int, truth_dir: Path | None, force: bool) -> dict:
    from data_synth.flat_field import write_flat_field
    from recon.config import config_hash, dump_resolved, load_config
    from recon.config.run_config import EffectConfig, RunConfig
    from recon.errors import ReconError
    from recon.io.atomic import atomic_write_json
    from recon.io.datasets import FLAT_FIELD_SPLIT
    from recon.io.run_folder import RunPaths

    paths = RunPaths(run)
    config_path = paths.resolved_config
    dataset = paths.dataset
    if not config_path.exists() or not dataset.is_dir():
        raise ReconError(f"{run}: not a synthetic run folder (no config.resolved.yaml or dataset/)")
    if paths.dataset_layout.has_flat_field and not force:
        raise ReconError(f"{dataset}: already has a {FLAT_FIELD_SPLIT} split (pass --force)")
    config = load_config(config_path, RunConfig)
    capture = replace(config.capture, flat_field=replace(config.capture.flat_field, views=views))
    config = replace(config, capture=capture)
    truth_path = (truth_dir or run.parent / "truth") / f"{run.name}.json"
    effects_path = paths.truth_effects
    recorded = json.loads(effects_path.read_text())
    truth = json.loads(truth_path.read_text()) if recorded.get("withheld") else None
    if recorded.get("withheld") and truth is None:
        raise ReconError(f"{run}: its effects were withheld and {truth_path} is missing")
    withheld = [
        EffectConfig(item["name"], dict(item["parameters"]))
        for item in (truth or {}).get("withheld", [])
    ]
    effects = list(capture.effects) + withheld
    realised = write_flat_field(dataset, capture, effects, config.seed, force=force)
    withheld_names = {effect.name for effect in withheld}
    recorded.setdefault("realised", {})[FLAT_FIELD_SPLIT] = [
        item for item in realised if item["name"] not in withheld_names
    ]
    atomic_write_json(effects_path, recorded)
    if truth is not None:
        truth.setdefault("realised", {})[FLAT_FIELD_SPLIT] = [
            item for item in realised if item["name"] in withheld_names
        ]
        atomic_write_json(truth_path, truth)
    dump_resolved(config, config_path)
    fit_record_path = run / "bench_fit.json"
    if fit_record_path.exists():
        fit_record = json.loads(fit_record_path.read_text())
        fit_record["config_hash"] = config_hash(config)
        atomic_write_json(fit_record_path, fit_record)
    return {"run": str(run), "views": views, "effects": [item["name"] for item in realised]}


def main(argv: list[str] | None = None) -> int:
    from recon.errors import ReconError

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--truth-dir", type=Path, default=None)
    parser.add_argument("--force", action="store_true", help="replace an existing flat field")
    arguments = parser.parse_args(argv)
    if arguments.views < 1:
        parser.error(f"--views: expected >= 1, got {arguments.views}")
    try:
        for run in arguments.runs:
            print(
                json.dumps(
                    add_flat_field(run, arguments.views, arguments.truth_dir, arguments.force)
                )
            )
    except ReconError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
