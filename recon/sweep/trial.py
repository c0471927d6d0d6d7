"""Run one trial into its own folder: trials/<id>/run is an ordinary recon run folder.

run_trial is what both backends call (in this process, or in a Ray worker), so a trial computes
the same thing wherever it runs: the same config, seed, device and torch thread count.

Trial folder:
    run/          the run folder (recon.pipeline.run, or pipeline.resume when it exists)
    truth.json    withheld effects (only with 'withhold'; beside the run folder, never in it)
    running.json  host and process id of the trial's last (or current) attempt
    result.json   the trial's record; its presence marks the trial finished
    error.txt     the traceback of a failed trial
"""

from __future__ import annotations

import json
import os
import socket
import time
import traceback
from dataclasses import replace
from pathlib import Path

import torch

from recon import pipeline
from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json, atomic_write_text
from recon.io.run_folder import RunPaths

RESULT_NAME = "result.json"
RUNNING_NAME = "running.json"


def read_metric(name: str, run_folder: Path, score: dict | None) -> object:
    """The value of metric 'SOURCE.KEY.PATH' for the trial whose run folder is run_folder."""
    source, _, key = name.partition(".")
    if source == "metrics":
        path = RunPaths(run_folder).metrics
        if not path.exists():
            raise ReconError(
                f"metric {name!r}: {path} not found (add 'evaluate' to the base config's stages)"
            )
        data = json.loads(path.read_text())
    elif source == "fit":
        path = RunPaths(run_folder).history
        lines = path.read_text().splitlines() if path.exists() else []
        if not lines:
            raise ReconError(f"metric {name!r}: {path} has no fit record")
        data = json.loads(lines[-1])
    else:
        path = Path("score")
        data = score or {}
    value = data
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            known = ", ".join(sorted(value)) if isinstance(value, dict) else "none"
            raise ReconError(f"metric {name!r}: no key {part!r} in {path} (known: {known})")
        value = value[part]
    return value


def trial_config(trial: dict, kind: str) -> RunConfig:
    """The base config with the trial's overrides (diagnosis trials stop after the fit)."""
    config = load_config(trial["base"], RunConfig, overrides=trial["overrides"])
    if kind == "diagnosis":
        config = replace(config, stages=["synth", "fit"])
    return config


def run_trial(trial: dict, folder: str, settings: dict) -> dict:
    """Run (or resume) one trial; returns its record and writes it to folder/result.json.

    trial: Trial.to_dict(). settings: 'metrics', 'kind', 'device', 'cpus_per_trial',
    'diagnose' (refit, candidates). Errors of the trial are recorded, not raised; an interrupt
    (KeyboardInterrupt) is raised, leaving the run folder's checkpoints to resume from.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    run_folder = folder / "run"
    record = {
        "trial_id": trial["trial_id"],
        "parameters": trial["parameters"],
        "run_folder": str(run_folder),
        "status": "ok",
        "error": None,
        "metrics": {},
        "resumed": False,
    }
    started = time.perf_counter()
    # Which process runs the trial (on a cluster: which node), while it runs and after.
    where = {"host": socket.gethostname(), "pid": os.getpid()}
    record.update(where)
    atomic_write_json(folder / RUNNING_NAME, where)
    previous_threads = torch.get_num_threads()
    # Ray sets OMP_NUM_THREADS=1 in its workers; set the count explicitly in every backend so
    # the same trial does the same arithmetic (and gives the same numbers) everywhere.
    torch.set_num_threads(settings["cpus_per_trial"])
    previous_folder = os.getcwd()
    # A Ray worker starts in its own folder; configs' relative paths are from the sweep's.
    os.chdir(settings.get("cwd", previous_folder))
    try:
        score = _run(trial, folder, run_folder, settings, record)
        record["metrics"] = {
            name: read_metric(name, run_folder, score) for name in settings["metrics"]
        }
        if score is not None:
            record["diagnosis"] = {
                key: score[key] for key in ("truth", "predicted_top", "significant")
            }
    except Exception as error:  # noqa: BLE001 - a failed trial is recorded and the sweep goes on
        record["status"] = "failed"
        record["error"] = f"{type(error).__name__}: {error}"
        atomic_write_text(folder / "error.txt", traceback.format_exc())
    finally:
        torch.set_num_threads(previous_threads)
        os.chdir(previous_folder)
    record["seconds"] = round(time.perf_counter() - started, 3)
    atomic_write_json(folder / RESULT_NAME, record)
    return record


def _run(trial: dict, folder: Path, run_folder: Path, settings: dict, record: dict) -> dict | None:
    kind = settings["kind"]
    truth_path = folder / "truth.json"
    withhold = trial.get("withhold")
    synth_options = (
        {"withhold_effects": list(withhold), "truth_out": truth_path} if withhold else {}
    )
    if RunPaths(run_folder).resolved_config.exists():
        # An interrupted trial: finished stages are skipped, the fit resumes from its checkpoint.
        record["resumed"] = True
        paths = pipeline.resume(
            run_folder, device=settings["device"], stage_options={"synth": synth_options}
        )
    else:
        config = trial_config(trial, kind)
        paths = pipeline.run(
            config,
            out=run_folder,
            force=True,  # the trial's own folder, created by the sweep (never a user's)
            device=settings["device"],
            stage_options={"synth": synth_options},
        )
    if kind != "diagnosis":
        return None
    return _diagnose(trial, paths, truth_path, settings)


def _diagnose(trial: dict, paths, truth_path: Path, settings: dict) -> dict:
    """Diagnose the fitted trial blind, then (only then) read the truth and score it."""
    from recon.stages.diagnose import run_diagnosis
    from recon.sweep.scoring import BenchCase, score_case

    config = load_config(paths.resolved_config, RunConfig)
    device = pipeline.resolve_device(settings["device"])
    started = time.perf_counter()
    diagnosis = run_diagnosis(
        paths,
        config,
        device,
        refit=settings["diagnose"]["refit"],
        candidates=settings["diagnose"]["candidates"] or None,
    ).to_json()
    diagnose_seconds = time.perf_counter() - started
    withheld = tuple(trial.get("withhold") or ())
    truth = json.loads(truth_path.read_text()) if withheld else {"withheld": []}
    environment = json.loads(paths.environment.read_text())
    fit_seconds = sum(environment.get("stage_seconds", {}).values())
    return score_case(
        BenchCase(withheld, trial["seed"]),
        diagnosis,
        truth,
        fit_seconds,
        diagnose_seconds,
        paths.root,
    )
