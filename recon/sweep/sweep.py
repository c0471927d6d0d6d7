"""Run a sweep: expand the sweep file into trials, skip finished ones (--resume), run the rest
on a backend, and keep the tables and the summary up to date.

Sweep folder (the sweep file's 'out'):
    sweep.json        the sweep file as read and its trials (ids, overrides, parameters)
    trials/<id>/      one folder per trial (see recon.sweep.trial)
    results.jsonl/.csv/.md, summary.html
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.sweep.backends import run_local, run_ray
from recon.sweep.results import write_results
from recon.sweep.spec import SweepSpec, load_sweep
from recon.sweep.summary import write_summary
from recon.sweep.trial import RESULT_NAME
from recon.sweep.trials import expand

BACKENDS = ("local", "ray")
MANIFEST = "sweep.json"


def settings_of(spec: SweepSpec) -> dict:
    """What every trial needs besides itself (plain values: sent to Ray workers)."""
    return {
        "metrics": list(spec.metrics),
        "kind": spec.kind,
        "device": spec.device,
        "cpus_per_trial": spec.cpus_per_trial,
        "gpus_per_trial": spec.gpus_per_trial,
        "diagnose": asdict(spec.diagnose),
        # Workers (Ray's start elsewhere) open relative paths in configs from here.
        "cwd": os.getcwd(),
    }


def prepare_out(out: Path, resume: bool, sweep_path: str) -> None:
    """Refuse to write into an existing folder unless resuming a sweep that lives there."""
    if out.exists() and not out.is_dir():
        raise ReconError(f"sweep out {out}: exists and is not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    if not (out / MANIFEST).exists():
        raise ReconError(
            f"sweep out {out}: exists, is not empty and holds no sweep; choose another 'out'"
        )
    if not resume:
        raise ReconError(
            f"sweep out {out}: already holds a sweep; pass --resume to continue it "
            f"(recon sweep {sweep_path} --resume) or choose another 'out'"
        )


def finished_record(folder: Path) -> dict | None:
    """The trial's record if it finished successfully (failed trials run again on resume)."""
    path = folder / RESULT_NAME
    if not path.exists():
        return None
    record = json.loads(path.read_text())
    return record if record.get("status") == "ok" else None


def run_sweep(
    sweep_path: str | Path,
    backend: str = "local",
    address: str | None = None,
    max_concurrent: int | None = None,
    resume: bool = False,
    num_cpus: int | None = None,
    progress=print,
) -> dict:
    """Run the sweep file's trials; returns {'out', 'trials', 'skipped', 'failed', ...}.

    An interrupt (KeyboardInterrupt) leaves the finished trials' records and the unfinished
    trials' checkpoints; run again with resume=True to continue.
    """
    if backend not in BACKENDS:
        raise ReconError(f"--backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if address and backend != "ray":
        raise ReconError("--address: only with --backend ray")
    if num_cpus is not None and (backend != "ray" or address):
        raise ReconError("--num-cpus: only for a local Ray (--backend ray without --address)")
    if max_concurrent is not None and max_concurrent < 1:
        raise ReconError(f"--max-concurrent: expected N >= 1, got {max_concurrent}")
    spec = load_sweep(sweep_path)
    trials = expand(spec)
    out = Path(spec.out).absolute()
    prepare_out(out, resume, str(sweep_path))
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(
        out / MANIFEST,
        {
            "sweep_file": str(sweep_path),
            "spec": asdict(spec),
            "trials": [t.to_dict() for t in trials],
        },
    )
    records: dict[str, dict] = {}
    jobs = []
    for trial in trials:
        folder = out / "trials" / trial.trial_id
        record = finished_record(folder) if resume else None
        if record is not None:
            records[trial.trial_id] = record
            continue
        job = trial.to_dict()
        job["base"] = str(Path(trial.base).absolute())
        jobs.append((job, str(folder)))
    skipped = len(records)
    progress(
        f"sweep: {len(trials)} trials, {skipped} finished before, {len(jobs)} to run ({backend})"
    )

    def ordered() -> list[dict]:
        return [records[trial.trial_id] for trial in trials if trial.trial_id in records]

    def on_record(record: dict) -> None:
        records[record["trial_id"]] = record
        write_results(out, ordered(), spec.metrics)
        note = record["error"] if record["status"] != "ok" else record["metrics"]
        progress(f"  {record['trial_id']} {record['status']}: {note}")

    settings = settings_of(spec)
    concurrent = max_concurrent or spec.max_concurrent
    try:
        if backend == "local":
            run_local(jobs, settings, on_record)
        else:
            run_ray(jobs, settings, on_record, address, concurrent, num_cpus)
    finally:
        write_results(out, ordered(), spec.metrics)
    summary = write_summary(out, f"recon sweep {Path(sweep_path).name}", ordered(), spec.metrics)
    failed = [record["trial_id"] for record in ordered() if record["status"] != "ok"]
    return {
        "out": str(out),
        "trials": len(trials),
        "skipped": skipped,
        "ran": len(jobs),
        "failed": failed,
        "summary": str(summary),
    }
