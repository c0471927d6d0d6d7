"""Checks that run before a new run folder is created or any expensive stage starts.

Everything that can be known from the config, the command line and file headers is checked here,
so a mistyped path or an impossible combination fails in a second with `recon: error: ...`, not
after a fit, and leaves no run folder behind.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.dataset_check import DatasetSummary, check_dataset


@dataclass
class Preflight:
    """What the checks found: the files a run reads (never inside a folder --force replaces),
    the dataset's summary when one is given, and warnings to print."""

    inputs: list[Path] = field(default_factory=list)
    dataset: DatasetSummary | None = None
    warnings: list[str] = field(default_factory=list)


def _first_existing_ancestor(path: Path) -> Path:
    current = path.absolute()
    while not current.exists() and current != current.parent:
        current = current.parent
    return current


def check_writable(folder: Path, what: str) -> None:
    """Raise ReconError unless `folder` (or the folder it would be created in) is writable."""
    existing = _first_existing_ancestor(folder)
    if not existing.is_dir():
        raise ReconError(f"{what} {folder}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ReconError(f"{what} {folder}: {existing} is not writable (permission denied)")


def _is_recon_truth(path: Path) -> bool:
    """Whether path is a withheld-truth file recon wrote (JSON with a 'withheld' list)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and isinstance(data.get("withheld"), list)


def check_withhold(
    config: RunConfig,
    stages: list[str],
    out: Path,
    withhold: int,
    truth_out: str | None,
    force: bool,
) -> None:
    """--withhold / --truth-out: they apply only to synthesised captures, and never overwrite a
    file recon did not write."""
    if withhold < 0:
        raise ReconError(f"--withhold: expected N >= 0, got {withhold}")
    if not withhold:
        if truth_out:
            raise ReconError(f"--truth-out {truth_out}: applies only with --withhold N (N > 0)")
        return
    if "synth" not in stages:
        reason = (
            f"the run fits the given dataset {config.data}"
            if config.data is not None
            else "the synth stage is not run"
        )
        raise ReconError(
            f"--withhold {withhold}: withholds effects from synthesised captures, but {reason}"
        )
    if not truth_out:
        raise ReconError("--withhold needs --truth-out PATH, outside the run folder")
    truth = Path(truth_out)
    if truth.absolute().is_relative_to(out.absolute()):
        raise ReconError(
            f"--truth-out {truth}: must lie outside the run folder {out}, or the diagnosis "
            "could read it"
        )
    if truth.is_dir():
        raise ReconError(f"--truth-out {truth}: is a folder; expected a file path (JSON)")
    if truth.exists():
        if not force:
            raise ReconError(f"--truth-out {truth}: already exists; pass --force to replace it")
        if not _is_recon_truth(truth):
            raise ReconError(
                f"--truth-out {truth}: already exists and is not a truth file recon wrote (a "
                "JSON with a 'withheld' list); --force never replaces other files"
            )
    check_writable(truth.parent, "--truth-out")


def check_scene_files(config: RunConfig) -> list[Path]:
    """The synth stage's input files exist; returns them."""
    shape = config.scene.shape
    files = []
    for key, value in (
        ("scene.shape.mesh_path", shape.mesh_path),
        ("scene.shape.texture_path", shape.texture_path),
    ):
        if value is None:
            continue
        path = Path(value)
        if not path.is_file():
            raise ReconError(f"{key}: {path}: file not found")
        files.append(path)
    environment = config.scene.lighting.environment
    if environment.kind == "exr" and environment.path:
        path = Path(environment.path)
        if not path.is_file():
            raise ReconError(f"scene.lighting.environment.path: {path}: file not found")
        files.append(path)
    return files


def check_new_run(
    config: RunConfig,
    stages: list[str],
    out: Path,
    config_file: str | Path | None = None,
    withhold: int = 0,
    truth_out: str | None = None,
    force: bool = False,
) -> Preflight:
    """Every check a new run can pass before its folder exists (see the module docstring)."""
    found = Preflight()
    if config_file is not None:
        found.inputs.append(Path(config_file))
    check_withhold(config, stages, out, withhold, truth_out, force)
    if "synth" in stages:
        found.inputs += check_scene_files(config)
    if config.data is not None:
        found.dataset = check_dataset(config.data, heldout_needed="evaluate" in stages)
        found.inputs.append(Path(config.data))
        found.warnings += found.dataset.warnings
    elif "synth" not in stages and stages:
        raise ReconError(
            f"stages {stages}: without the synth stage the run needs a dataset (config key "
            "'data' or --data FOLDER)"
        )
    check_writable(out, "run folder")
    return found
