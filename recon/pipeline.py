"""The stage sequence of a run: resolve the config, prepare the run folder, run the stages.

Stages are looked up by name in the ``recon.stages`` entry-point group (pyproject.toml). recon's
own stages live in recon; the synth stage belongs to data_synth (the "world"), which recon must
not import, so every stage is found the same way, by name.
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
from recon.config import config_hash, dump_resolved, load_config
from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.run_folder import RunPaths, open_run_folder, prepare_run_folder

Stage = Callable[..., dict]
# Stages that can pick up from their checkpoints when a run is resumed.
RESUMABLE = {"fit"}


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


def peak_memory_mb() -> float:
    """The process's peak resident set size in MiB (resource.getrusage's ru_maxrss: KiB on
    Linux, bytes on macOS)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (1024 * 1024 if sys.platform == "darwin" else 1024), 1)


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


def _stages_to_run(config: RunConfig, stages: list[str] | None) -> list[str]:
    chosen = list(stages or config.stages)
    if config.data is not None and "synth" in chosen:
        # A given dataset replaces the synthetic captures.
        chosen.remove("synth")
    return chosen


def run(
    config: RunConfig,
    out: str | Path | None = None,
    force: bool = False,
    device: str | None = None,
    stages: list[str] | None = None,
    stage_options: dict[str, dict] | None = None,
) -> RunPaths:
    """Run the config's stages into a new run folder; returns its paths.

    stage_options: keyword arguments per stage name (e.g. {"synth": {"withhold": 2,
    "truth_out": path}}).
    """
    resolved_device = resolve_device(device or config.device)
    paths = prepare_run_folder(out or default_run_folder(config), force=force)
    if config.data is not None:
        paths = RunPaths(paths.root, Path(config.data))
    dump_resolved(config, paths.resolved_config)
    return run_stages(config, paths, resolved_device, _stages_to_run(config, stages), stage_options)


def resume(
    run_folder: str | Path,
    device: str | None = None,
    stages: list[str] | None = None,
    stage_options: dict[str, dict] | None = None,
) -> RunPaths:
    """Continue a run from its checkpoints: finished stages whose outputs exist are skipped
    (synth), the fit resumes from its last checkpoint, evaluate and report run again."""
    config = load_config(Path(run_folder) / "config.resolved.yaml", RunConfig)
    paths = open_run_folder(run_folder, config.data)
    resolved_device = resolve_device(device or config.device)
    chosen = _stages_to_run(config, stages)
    if "synth" in chosen and (paths.dataset / "transforms_train.json").exists():
        chosen.remove("synth")
    return run_stages(config, paths, resolved_device, chosen, stage_options, resume=True)


def run_stage_on(
    run_folder: str | Path, stage: str, device: str | None = None, overrides: list[str] = ()
) -> RunPaths:
    """One stage on an existing run folder (recon fit/evaluate/report RUN)."""
    config = load_config(Path(run_folder) / "config.resolved.yaml", RunConfig, overrides=overrides)
    paths = open_run_folder(run_folder, config.data)
    if overrides:
        dump_resolved(config, paths.resolved_config)
    return run_stages(config, paths, resolve_device(device or config.device), [stage], None)


def run_stages(
    config: RunConfig,
    paths: RunPaths,
    device: torch.device,
    stages: list[str],
    stage_options: dict[str, dict] | None,
    resume: bool = False,
) -> RunPaths:
    stage_options = stage_options or {}
    environment = json.loads(paths.environment.read_text()) if paths.environment.exists() else {}
    environment.update(environment_record(device))
    environment["config_hash"] = config_hash(config)
    environment.setdefault("stage_seconds", {})
    atomic_write_json(paths.environment, environment)
    seed_everything(config.seed)
    for name in stages:
        started = time.perf_counter()
        options = dict(stage_options.get(name, {}))
        if resume and name in RESUMABLE:
            options["resume"] = True
        find_stage(name)(config, paths, device, **options)
        environment["stage_seconds"][name] = round(time.perf_counter() - started, 3)
        # The process's peak resident memory so far (Linux: ru_maxrss in KiB).
        environment.setdefault("peak_memory_mb", {})[name] = peak_memory_mb()
        atomic_write_json(paths.environment, environment)
    return paths


def describe(paths: RunPaths) -> str:
    environment = json.loads(paths.environment.read_text())
    seconds = ", ".join(f"{k} {v:.1f} s" for k, v in environment.get("stage_seconds", {}).items())
    return f"run folder: {paths.root} ({seconds})"
