"""Shared helpers of the benchmarks (timing, environment, workers, output).

Benchmarks print their JSON result to stdout and progress to stderr. Each measured configuration
runs in a fresh worker subprocess (the same module, `python -m MODULE --worker`), so that its
peak RSS (ru_maxrss) belongs to that configuration alone and a configuration that runs out of
time or memory can be killed and recorded as skipped without taking the whole run down.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
# A worker prints its result on one stdout line that starts with this marker.
RESULT_MARKER = "@@BENCH_RESULT@@ "


def log(message: str) -> None:
    """Progress line on stderr (stdout is reserved for the JSON result)."""
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def configure_threads(threads: int | None = None) -> int:
    """Set torch's intra-op pool explicitly: every CPU (os.cpu_count()) unless threads is given;
    returns the thread count."""
    import torch

    threads = threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    return threads


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when available, else 'cpu'; 'cuda' without a GPU raises SystemExit."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch.cuda.is_available() is False")
    return name


def synchronize(device: str) -> None:
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def median(values: list[float]) -> float | None:
    return round(float(statistics.median(values)), 3) if values else None


def cpu_seconds() -> float:
    """User + system CPU time of this process (all its threads) so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class CpuMeter:
    """Cores this process kept busy between start() and cores_used(): CPU seconds / wall seconds.

    Close to the thread count when the benchmark had the machine to itself; well below it when
    other processes competed for the cores (timings are then inflated)."""

    def start(self) -> None:
        self.wall, self.cpu = time.perf_counter(), cpu_seconds()

    def cores_used(self) -> float:
        wall = time.perf_counter() - self.wall
        return round((cpu_seconds() - self.cpu) / wall, 2) if wall > 0 else 0.0


def load_average() -> list[float] | None:
    return [round(value, 2) for value in os.getloadavg()] if hasattr(os, "getloadavg") else None


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MiB (ru_maxrss: KiB on Linux)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    divisor = 1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0
    return peak / divisor


def current_rss_mb() -> float | None:
    """Current resident set size in MiB (Linux /proc only; None elsewhere)."""
    try:
        with open("/proc/self/statm") as statm:
            resident_pages = int(statm.read().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return resident_pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def available_memory_mb() -> float | None:
    """MemAvailable from /proc/meminfo in MiB, or None."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        return None
    return None


def limit_address_space(limit_mb: float | None) -> None:
    """Cap this process's virtual memory so an oversized configuration fails with an allocation
    error (recorded as skipped) instead of waking the system OOM killer. CPU workers only: the
    CUDA driver maps far more address space than it uses."""
    if not limit_mb:
        return
    limit = int(limit_mb * 2**20)
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))


def is_out_of_memory(error: BaseException) -> bool:
    text = str(error).lower()
    return isinstance(error, MemoryError) or any(
        marker in text
        for marker in (
            "out of memory",
            "can't allocate memory",
            "cannot allocate memory",
            "bad_alloc",
        )
    )


def environment(device: str) -> dict:
    """Versions and machine facts that a reader needs to interpret the timings."""
    import torch

    info = {
        "device": device,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "cpu_model": _cpu_model(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_at_start": load_average(),
        "memory_available_mb_at_start": available_memory_mb(),
    }
    if device.startswith("cuda"):
        info["cuda_device"] = torch.cuda.get_device_name()
        info["cuda_version"] = torch.version.cuda
    info["mitsuba"] = mitsuba_version()
    return info


def mitsuba_version() -> str:
    """Installed mitsuba version, or 'not installed' (without importing it)."""
    from importlib import metadata

    try:
        return metadata.version("mitsuba")
    except metadata.PackageNotFoundError:
        return "not installed"


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def run_worker(module: str, job: dict, timeout_s: float) -> dict:
    """Run `python -m module --worker JSON` in a fresh process and return its result dict.

    Returns {"skipped": reason} when the worker exceeds timeout_s, is killed (typically by the
    OOM killer) or exits without a result; the worker's stderr passes through as progress.
    """
    command = [sys.executable, "-m", module, "--worker", json.dumps(job)]
    environment_variables = dict(os.environ)
    python_path = environment_variables.get("PYTHONPATH", "")
    environment_variables["PYTHONPATH"] = os.pathsep.join(
        part for part in (str(REPO_ROOT), python_path) if part
    )
    started = time.perf_counter()
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=None, text=True, env=environment_variables
    )
    try:
        stdout, _ = process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        return {"skipped": f"exceeded --timeout-per-config {timeout_s:g} s (killed)"}
    elapsed = time.perf_counter() - started
    for line in reversed(stdout.splitlines()):
        # Libraries may leave a partial line on stdout (Mitsuba's warnings do): find the marker.
        position = line.find(RESULT_MARKER)
        if position >= 0:
            result = json.loads(line[position + len(RESULT_MARKER) :])
            result.setdefault("worker_wall_s", round(elapsed, 3))
            return result
    code = process.returncode
    if code < 0:
        name = signal.Signals(-code).name
        reason = f"worker killed by {name}"
        if -code == signal.SIGKILL:
            reason += " (likely out of memory)"
        return {"skipped": reason}
    return {"skipped": f"worker exited with code {code} without a result"}


def emit_worker_result(result: dict) -> None:
    """Print a worker's result on stdout for run_worker to pick up."""
    print("\n" + RESULT_MARKER + json.dumps(result), flush=True)


def write_json_atomic(path: str | os.PathLike, payload: dict) -> None:
    """Write JSON to path through a temporary file in the same folder and os.replace."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(descriptor, "w") as handle:
            json.dump(payload, handle, indent=2)
            handle.write("\n")
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
