"""The stage sequence of a run: resolve the config, prepare the run folder, run the stages.

Stages are looked up by name (recon.stages.find_stage): recon's own in recon/stages/, the synth
stage, which belongs to data_synth (the "world") that recon must not import, in the
``recon.stages`` entry-point group (pyproject.toml).
"""

from __future__ import annotations

import json
import os
import platform
import random
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from recon import __version__
from recon.config import config_hash, dump_resolved, load_config
from recon.config.run_config import RunConfig
from recon.errors import ReconError, WriteError, warn_user
from recon.io.atomic import append_json_line, atomic_write_json, remove_stale_temporaries
from recon.io.run_folder import NewRunFolder, RunPaths, open_run_folder, start_run_folder
from recon.preflight import check_new_run, check_writable

Stage = Callable[..., dict]
# Stages that can pick up from their checkpoints when a run is resumed.
RESUMABLE = {"synth", "fit"}


def resolve_device(requested: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cuda' without a GPU is an error."""
    if requested == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if requested == "cuda" and not torch.cuda.is_available():
        raise ReconError("device: 'cuda' was requested but torch sees no CUDA device")
    if requested not in ("cpu", "cuda"):
        raise ReconError(f"device: expected one of auto, cpu, cuda, got {requested!r}")
    return torch.device(requested)


def seed_everything(seed: int, deterministic: bool = True) -> None:
    """One seed for every random source, so the same config gives the same result on CPU.

    deterministic: torch's deterministic kernels. Without them, accumulating index_put (the
    backward of advanced indexing) sums in a thread-dependent order on CPU, so two runs with
    two threads differed in the last bits and, through the fit, in every metric. warn_only keeps
    CUDA ops that have no deterministic kernel usable (they warn once).
    """
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
    if deterministic:
        # cuBLAS is deterministic only with a fixed workspace; read when CUDA starts.
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(deterministic, warn_only=True)


def find_stage(name: str) -> Stage:
    """The stage function of that name (recon.stages.find_stage)."""
    from recon.stages import find_stage as find

    return find(name)


def peak_memory_mb() -> float:
    """The process's peak resident set size in MiB (resource.getrusage's ru_maxrss: KiB on
    Linux, bytes on macOS)."""
    import resource

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
    config_file: str | Path | None = None,
) -> RunPaths:
    """Run the config's stages into a new run folder; returns its paths.

    Every input is checked (recon.preflight) before the folder is created. With force, an old
    run folder in the way is moved aside and deleted only once the first stage has finished; if
    a check inside that stage fails (ReconError), the new folder is removed and the old run put
    back, so a failed start never costs the previous run.

    stage_options: keyword arguments per stage name (e.g. {"synth": {"withhold": 2,
    "truth_out": path}}). config_file: the YAML the config came from (never replaced by --force).
    """
    resolved_device = resolve_device(device or config.device)
    chosen = _stages_to_run(config, stages)
    for name in chosen:
        find_stage(name)
    out = Path(out or default_run_folder(config))
    synth_options = (stage_options or {}).get("synth", {})
    found = check_new_run(
        config,
        chosen,
        out,
        config_file=config_file,
        # withhold_effects: the blind benchmark and sweeps name the withheld effects.
        withhold=int(synth_options.get("withhold", 0) or 0)
        or len(synth_options.get("withhold_effects") or ()),
        truth_out=synth_options.get("truth_out"),
        force=force,
    )
    for message in found.warnings:
        warn_user(message)
    started = start_run_folder(out, force=force, inputs=found.inputs)
    paths = started.paths
    if config.data is not None:
        paths = RunPaths(paths.root, Path(config.data))
    try:
        dump_resolved(config, paths.resolved_config)
        return run_stages(
            config,
            paths,
            resolved_device,
            chosen,
            stage_options,
            on_first_stage_done=started.commit,
        )
    except (WriteError, OSError, KeyboardInterrupt) as error:
        # Listed before ReconError, of which WriteError is one: a failed write is no failed check.
        _keep_after_failure(started, error)
        raise
    except ReconError:
        # A check that fails inside the first stage leaves nothing behind: the old run, if
        # --force moved one aside, is put back.
        if not _completed_stages(paths):
            started.abandon()
        raise


def _keep_after_failure(started: NewRunFolder, error: BaseException) -> None:
    """An interrupt or a failed write (full disk, read-only folder) keeps what the new run wrote
    so it can be resumed, and the run --force replaced stays aside: nothing is deleted."""
    error.run_folder = started.paths.root  # the CLI says where to --resume
    if started.replaced is not None:
        warn_user(
            f"the run folder replaced by --force is kept at {started.replaced} until you delete it"
        )


def _completed_stages(paths: RunPaths) -> list[str]:
    """Stages that finished in this run folder (env.json's stage_seconds, written after each)."""
    if not paths.environment.exists():
        return []
    return list(json.loads(paths.environment.read_text()).get("stage_seconds", {}))


def resume(
    run_folder: str | Path,
    device: str | None = None,
    stages: list[str] | None = None,
    stage_options: dict[str, dict] | None = None,
) -> RunPaths:
    """Continue a run from its checkpoints: stages that finished are skipped when their outputs
    exist (synth), the synth and fit stages continue from what they wrote, evaluate and report
    run again."""
    config = load_config(open_run_folder(run_folder).resolved_config, RunConfig)
    paths = open_run_folder(run_folder, config.data)
    resolved_device = resolve_device(device or config.device)
    # A process killed mid-write leaves atomic_path's temporary file behind: it was never a
    # result, so it goes before the stages continue.
    remove_stale_temporaries(paths.root)
    chosen = _stages_to_run(config, stages)
    if "synth" in chosen and "synth" in _completed_stages(paths):
        chosen.remove("synth")
    return run_stages(config, paths, resolved_device, chosen, stage_options, resume=True)


def run_stage_on(
    run_folder: str | Path, stage: str, device: str | None = None, overrides: list[str] = ()
) -> RunPaths:
    """One stage on an existing run folder (recon evaluate/report RUN).

    The run's config.resolved.yaml and its hash stay the record of the fit: overrides given to a
    later stage are recorded beside them (RunPaths.stage_overrides), never written into them.
    """
    paths = open_run_folder(run_folder)
    config = load_config(paths.resolved_config, RunConfig, overrides=overrides)
    paths = open_run_folder(run_folder, config.data)
    check_writable(paths.root, "run folder")
    if overrides:
        record = {
            "stage": stage,
            "overrides": list(overrides),
            "config_hash": config_hash(config),
            "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        append_json_line(paths.stage_overrides, record)
    return run_stages(config, paths, resolve_device(device or config.device), [stage], None)


def run_stages(
    config: RunConfig,
    paths: RunPaths,
    device: torch.device,
    stages: list[str],
    stage_options: dict[str, dict] | None,
    resume: bool = False,
    on_first_stage_done: Callable[[], None] | None = None,
) -> RunPaths:
    """Run stages in order, recording each one's time in env.json once it has finished.

    env.json's config_hash is the hash of the config the run was created with; a later stage
    run with overrides keeps it (its own hash goes to stage_overrides.jsonl).
    """
    stage_options = stage_options or {}
    environment = json.loads(paths.environment.read_text()) if paths.environment.exists() else {}
    environment.update(environment_record(device))
    environment.setdefault("config_hash", config_hash(config))
    environment.setdefault("stage_seconds", {})
    atomic_write_json(paths.environment, environment)
    seed_everything(config.seed, config.deterministic)
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
        if on_first_stage_done is not None:
            on_first_stage_done()
            on_first_stage_done = None
    return paths


def describe(paths: RunPaths) -> str:
    environment = json.loads(paths.environment.read_text())
    seconds = ", ".join(f"{k} {v:.1f} s" for k, v in environment.get("stage_seconds", {}).items())
    return f"run folder: {paths.root} ({seconds})"
