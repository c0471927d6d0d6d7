"""The stage sequence of a run: resolve the config, prepare the run folder, run the stages.

Stages are looked up by name. recon's own stages live in recon; the synth stage belongs to
data_synth (the "world"), which recon must not import, so it is found through the
``recon.stages`` entry-point group that data_synth's package metadata declares.
"""

from __future__ import annotations

import json
import platform
import random
import time
from collections.abc import Callable
from datetime import datetime, timezone
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import torch

from recon import __version__
from recon.config import config_hash, dump_resolved
from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.run_folder import RunPaths, prepare_run_folder

Stage = Callable[[RunConfig, RunPaths, torch.device], dict]


def resolve_device(requested: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cuda' without a GPU is an error."""
    if requested == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if requested == "cuda" and not torch.cuda.is_available():
        raise ReconError("device: 'cuda' was requested but torch sees no CUDA device")
    if requested not in ("cpu", "cuda"):
        raise ReconError(f"device: expected one of auto, cpu, cuda, got {requested!r}")
    return torch.device(requested)


def seed_everything(seed: int) -> None:
    """One seed for every random source, so the same config gives the same result on CPU."""
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def find_stage(name: str) -> Stage:
    """The stage function registered under name in the 'recon.stages' entry-point group."""
    found = {entry.name: entry for entry in entry_points(group="recon.stages")}
    if name not in found:
        raise ReconError(
            f"stage {name!r}: not installed (known: {', '.join(sorted(found)) or 'none'}); "
            "install the project with 'pip install -e .'"
        )
    return found[name].load()


def default_run_folder(config: RunConfig) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / config.name / stamp


def environment_record(device: torch.device) -> dict:
    record = {
        "recon": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "platform": platform.platform(),
        "device": str(device),
        "threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        record["gpu"] = torch.cuda.get_device_name(device)
    return record


def run(
    config: RunConfig,
    out: str | Path | None = None,
    force: bool = False,
    device: str | None = None,
    stages: list[str] | None = None,
    stage_options: dict[str, dict] | None = None,
) -> RunPaths:
    """Run the config's stages into a run folder; returns its paths.

    stage_options: keyword arguments per stage name (e.g. {"synth": {"withhold": 2,
    "truth_out": path}}).
    """
    stage_options = stage_options or {}
    resolved_device = resolve_device(device or config.device)
    paths = prepare_run_folder(out or default_run_folder(config), force=force)
    dump_resolved(config, paths.resolved_config)
    environment = environment_record(resolved_device)
    environment["config_hash"] = config_hash(config)
    atomic_write_json(paths.environment, environment)
    seed_everything(config.seed)
    timings = {}
    for name in stages or config.stages:
        started = time.perf_counter()
        find_stage(name)(config, paths, resolved_device, **stage_options.get(name, {}))
        timings[name] = round(time.perf_counter() - started, 3)
    environment["stage_seconds"] = timings
    atomic_write_json(paths.environment, environment)
    return paths


def describe(paths: RunPaths) -> str:
    environment = json.loads(paths.environment.read_text())
    seconds = ", ".join(f"{k} {v:.1f} s" for k, v in environment.get("stage_seconds", {}).items())
    return f"run folder: {paths.root} ({seconds})"
