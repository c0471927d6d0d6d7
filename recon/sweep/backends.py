"""Where trials run: 'local' (one after another in this process, no extra dependency) or 'ray'
(Ray core tasks on a local Ray started on demand, or on a cluster at --address).

Both call recon.sweep.trial.run_trial with the same arguments and hand each record to
on_record as soon as it is finished. Scheduling, retries and placement are Ray's: the Ray
backend only keeps at most max_concurrent tasks submitted (Ray's 'limit pending tasks' pattern).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from recon.errors import ReconError
from recon.sweep.trial import run_trial

Job = tuple[dict, str]  # (Trial.to_dict(), trial folder)
OnRecord = Callable[[dict], None]


def run_local(jobs: list[Job], settings: dict, on_record: OnRecord) -> None:
    for trial, folder in jobs:
        on_record(run_trial(trial, folder, settings))


def import_ray():
    try:
        import ray
    except ImportError:
        raise ReconError(
            "--backend ray: Ray is not installed; install the extra with "
            "pip install -e '.[ray]' (or use --backend local)"
        ) from None
    return ray


def start_ray(address: str | None, num_cpus: int | None) -> bool:
    """Connect to Ray: an already initialised one as is, the cluster at address, or a new
    local instance with num_cpus CPUs. Returns True when this call started it."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    options = {"log_to_driver": False, "configure_logging": False}
    if address:
        try:
            ray.init(address=address, **options)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise ReconError(f"--address {address}: cannot connect to Ray ({error})") from None
        return True
    ray.init(num_cpus=num_cpus, include_dashboard=False, **options)
    return True


def crashed_record(trial: dict, folder: str, error: BaseException) -> dict:
    """The record of a trial whose worker died (the trial could not record anything itself)."""
    return {
        "trial_id": trial["trial_id"],
        "parameters": trial["parameters"],
        "run_folder": str(Path(folder) / "run"),
        "status": "failed",
        "error": f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}",
        "metrics": {},
        "resumed": False,
    }


def run_ray(
    jobs: list[Job],
    settings: dict,
    on_record: OnRecord,
    address: str | None = None,
    max_concurrent: int | None = None,
    num_cpus: int | None = None,
) -> None:
    ray = import_ray()
    started_here = start_ray(address, num_cpus)
    # A worker that dies mid-trial (killed, out of memory) is retried by Ray; the retry finds
    # the trial's run folder and resumes it from its checkpoints.
    task = ray.remote(run_trial).options(
        num_cpus=settings["cpus_per_trial"],
        num_gpus=settings["gpus_per_trial"],
        max_retries=2,
    )
    queue = list(jobs)
    limit = max_concurrent or len(queue) or 1
    in_flight: dict = {}
    try:
        while queue or in_flight:
            while queue and len(in_flight) < limit:
                trial, folder = queue.pop(0)
                in_flight[task.remote(trial, folder, settings)] = (trial, folder)
            done, _ = ray.wait(list(in_flight), num_returns=1)
            for reference in done:
                trial, folder = in_flight.pop(reference)
                try:
                    record = ray.get(reference)
                except ray.exceptions.RayError as error:
                    record = crashed_record(trial, folder, error)
                on_record(record)
    except BaseException:
        for reference in in_flight:
            ray.cancel(reference, force=True)
        raise
    finally:
        if started_here:
            ray.shutdown()
