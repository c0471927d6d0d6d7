"""Cost of summing a fit's gradients across processes: all_reduce over gloo on localhost.

Spawns --processes processes (default 2) that join one torch.distributed group (gloo, TCP on
127.0.0.1) and time all_reduce(SUM) of float32 tensors the size of a fit's parameters: vertex
positions (V x 3), an RGBA texture (T x T x 4), and both flattened into one buffer (how a
data-parallel step would send them: one call per step). Prints JSON: the median seconds per
call over --repeats calls after --warmup calls, and the bandwidth (bytes / second).

Usage: recon-bench allreduce [--processes 2] [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import tempfile
import time
from datetime import datetime, timezone

import torch
import torch.distributed as distributed
import torch.multiprocessing as multiprocessing

SIZES = {
    "vertices 20k x 3": (20_000, 3),
    "vertices 100k x 3": (100_000, 3),
    "texture 512 x 512 x 3": (512, 512, 3),
    "texture 512 x 512 x 4": (512, 512, 4),
    "texture 1024 x 1024 x 4": (1024, 1024, 4),
    # One flattened buffer: 20k vertices + a 512² RGBA texture + a few light parameters.
    "fit step: 20k x 3 + 512 x 512 x 4 + 16": (20_000 * 3 + 512 * 512 * 4 + 16,),
}


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def worker(rank: int, world: int, port: int, warmup: int, repeats: int, result_path: str) -> None:
    # One thread per process: what each process of a data-parallel fit on a small machine has.
    torch.set_num_threads(1)
    distributed.init_process_group(
        "gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world
    )
    results = {}
    for name, shape in SIZES.items():
        tensor = torch.randn(shape)
        seconds = []
        for index in range(warmup + repeats):
            distributed.barrier()
            started = time.perf_counter()
            distributed.all_reduce(tensor)
            if index >= warmup:
                seconds.append(time.perf_counter() - started)
        median = statistics.median(seconds)
        size = tensor.numel() * tensor.element_size()
        results[name] = {
            "bytes": size,
            "median_seconds": round(median, 6),
            "min_seconds": round(min(seconds), 6),
            "megabytes_per_second": round(size / median / 1e6, 1),
        }
    if rank == 0:
        with open(result_path, "w") as handle:
            json.dump(results, handle)
    distributed.destroy_process_group()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=20)
    arguments = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        result_path = os.path.join(scratch, "allreduce.json")
        multiprocessing.spawn(
            worker,
            args=(
                arguments.processes,
                free_port(),
                arguments.warmup,
                arguments.repeats,
                result_path,
            ),
            nprocs=arguments.processes,
        )
        with open(result_path) as handle:
            results = json.load(handle)
    print(
        json.dumps(
            {
                "what": f"all_reduce(SUM) float32, gloo, {arguments.processes} processes on "
                "localhost, 1 torch thread each",
                "results": results,
                "repeats": arguments.repeats,
                "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                "machine": f"{platform.machine()}, {os.cpu_count()} cores",
                "load_average_1min_at_end": round(os.getloadavg()[0], 2),
                "torch": torch.__version__,
                "command": "recon-bench allreduce",
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
