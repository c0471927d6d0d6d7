"""Command line: parse, resolve the config and device, call the pipeline. Nothing else."""

from __future__ import annotations

import argparse
import sys

from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.errors import ReconError


def _add_run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="YAML run config (see configs/)")
    parser.add_argument("--out", help="run folder (default: runs/<name>/<UTC stamp>)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set capture.train_views=8 (repeatable)",
    )
    parser.add_argument("--force", action="store_true", help="replace an existing run folder")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="overrides 'device'")
    parser.add_argument(
        "--withhold",
        type=int,
        default=0,
        metavar="N",
        help="inject N random effects with random plausible strengths (blind check)",
    )
    parser.add_argument(
        "--truth-out",
        metavar="PATH",
        help="with --withhold: where the withheld effects are written (never in the run folder)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="recon", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    run_parser = commands.add_parser("run", help="run every stage the config lists")
    _add_run_arguments(run_parser)
    synth_parser = commands.add_parser(
        "synth", help="synthesise captures of the config's reference scene (data_synth)"
    )
    _add_run_arguments(synth_parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    from recon import pipeline

    arguments = build_parser().parse_args(argv)
    try:
        config = load_config(arguments.config, RunConfig, overrides=arguments.overrides)
        stages = ["synth"] if arguments.command == "synth" else None
        if arguments.withhold < 0:
            raise ReconError(f"--withhold: expected N >= 0, got {arguments.withhold}")
        if arguments.withhold and not arguments.truth_out:
            raise ReconError("--withhold needs --truth-out PATH, outside the run folder")
        synth_options = {}
        if arguments.withhold:
            synth_options = {"withhold": arguments.withhold, "truth_out": arguments.truth_out}
        paths = pipeline.run(
            config,
            out=arguments.out,
            force=arguments.force,
            device=arguments.device,
            stages=stages,
            stage_options={"synth": synth_options},
        )
    except ReconError as error:
        print(f"recon: error: {error}", file=sys.stderr)
        return 2
    print(pipeline.describe(paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
