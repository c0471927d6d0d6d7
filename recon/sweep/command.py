"""`recon sweep SWEEP.yaml`: the command's arguments and body (recon.cli registers them)."""

from __future__ import annotations

import argparse
import sys


def add_sweep_parser(commands) -> argparse.ArgumentParser:
    """Add the 'sweep' sub-command to the CLI's sub-parsers."""
    parser = commands.add_parser(
        "sweep", help="many runs (configs, scenes, seeds, withheld effects) from a sweep file"
    )
    parser.add_argument("sweep", help="sweep file (YAML; see docs/sweep.md)")
    parser.add_argument("--backend", choices=["local", "ray"], default="local")
    parser.add_argument(
        "--address", help="with --backend ray: an existing Ray cluster (HEAD:6379 or 'auto')"
    )
    parser.add_argument(
        "--max-concurrent", type=int, metavar="N", help="at most N trials at once (Ray)"
    )
    parser.add_argument(
        "--num-cpus",
        type=int,
        metavar="N",
        help="with --backend ray and no --address: CPUs of the local Ray (default: all)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the sweep in its folder: finished trials are kept, the rest resume",
    )
    return parser


def run_sweep_command(arguments) -> int:
    """0 when every trial finished, 1 when some failed (recorded), 130 when interrupted.
    A ReconError (bad sweep file, folder in the way) propagates to the CLI (exit 2)."""
    from recon.sweep.sweep import run_sweep

    try:
        result = run_sweep(
            arguments.sweep,
            backend=arguments.backend,
            address=arguments.address,
            max_concurrent=arguments.max_concurrent,
            resume=arguments.resume,
            num_cpus=arguments.num_cpus,
        )
    except KeyboardInterrupt:
        print(
            "recon: sweep interrupted; finished trials are kept: continue with "
            f"'recon sweep {arguments.sweep} --resume'",
            file=sys.stderr,
        )
        return 130
    print(
        f"sweep folder: {result['out']} ({result['ran']} run, {result['skipped']} kept, "
        f"{len(result['failed'])} failed); summary: {result['summary']}"
    )
    return 1 if result["failed"] else 0
