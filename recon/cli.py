"""Command line: parse, resolve the config and device, call the pipeline. Nothing else.

Heavy modules (torch, recon.pipeline) are imported inside the commands that need them, so
``recon --help`` and the read-only views of recon/cli_info.py start fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from recon import __version__, cli_info
from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.errors import ReconError, describe_os_error
from recon.sweep.command import add_sweep_parser, run_sweep_command

DESCRIPTION = """\
Inverse-rendering reconstruction with its own differentiable rasterizer: synthesise captures
of a scene, fit mesh, texture and light to them, evaluate, report, and diagnose the gap
between the fitted model and the captures.

quickstart:
  recon run configs/quickstart.yaml --out runs/quickstart
  recon config keys              every config key with type, default and description
  recon COMMAND --help           the options of one command
"""


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set capture.train_views=8 (repeatable)",
    )
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="overrides 'device'")


def _add_new_run(parser: argparse.ArgumentParser, withhold: bool) -> None:
    parser.add_argument("config", nargs="?", help="YAML run config (see configs/)")
    parser.add_argument("--out", help="run folder (default: runs/<name>/<UTC stamp>)")
    parser.add_argument("--force", action="store_true", help="replace an existing run folder")
    parser.add_argument("--data", help="fit this dataset folder instead of synthesising one")
    _add_common(parser)
    if withhold:
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
            help="with --withhold: where the withheld effects go (never in the run folder)",
        )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="recon", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"recon {__version__}")
    parser.add_argument(
        "--debug", action="store_true", help="show the Python traceback of an error"
    )
    commands = parser.add_subparsers(dest="command", required=True)
    run_parser = commands.add_parser("run", help="run every stage the config lists")
    _add_new_run(run_parser, withhold=True)
    run_parser.add_argument("--resume", metavar="RUN", help="continue RUN from its checkpoints")
    synth_parser = commands.add_parser("synth", help="synthesise captures only (data_synth)")
    _add_new_run(synth_parser, withhold=True)
    synth_parser.add_argument("--resume", metavar="RUN", help="continue RUN's synthesis")
    fit_parser = commands.add_parser(
        "fit", help="fit a dataset: CONFIG (new run) or an existing RUN folder"
    )
    _add_new_run(fit_parser, withhold=False)
    fit_parser.add_argument("--resume", metavar="RUN", help="continue RUN's fit")
    for name, text in (("evaluate", "metrics of a fitted run"), ("report", "figures + report")):
        stage_parser = commands.add_parser(name, help=text)
        stage_parser.add_argument("run", help="run folder")
        _add_common(stage_parser)
    diagnose_parser = commands.add_parser(
        "diagnose",
        help="where the sim-to-real gap lies, which effect causes it, how far it shrinks",
    )
    diagnose_parser.add_argument("run", help="a fitted run folder")
    diagnose_parser.add_argument("--data", help="diagnose against this dataset instead")
    diagnose_parser.add_argument(
        "--refit",
        choices=["none", "top", "greedy"],
        default=None,
        help="how far: overrides the config's diagnose.refit (default top)",
    )
    diagnose_parser.add_argument(
        "--effects", default="all", help="candidates: 'all' or a comma-separated list"
    )
    diagnose_parser.add_argument("--device", choices=["auto", "cpu", "cuda"])
    diagnose_parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="diagnose.KEY=VALUE",
        help="override a diagnose setting of the run's config, e.g. --set "
        "diagnose.decision.minimum_share=0.03 (repeatable; recorded in diagnosis.json)",
    )
    compare_parser = commands.add_parser(
        "compare", help="compare a run's metrics with a baseline; exit 1 on a regression"
    )
    compare_parser.add_argument("run", help="run folder (or a metrics.json)")
    compare_parser.add_argument("--baseline", required=True, help="YAML/JSON bounds per metric")
    compare_parser.add_argument(
        "--write", action="store_true", help="write the baseline from this run instead"
    )
    compare_parser.add_argument(
        "--force", action="store_true", help="with --write: replace an existing baseline file"
    )
    cli_info.add_commands(commands)
    add_sweep_parser(commands)
    return parser


def _new_run(arguments, stages: list[str] | None):
    from recon import pipeline

    if not arguments.config:
        raise ReconError(f"recon {arguments.command}: give a CONFIG (or --resume RUN)")
    overrides = list(arguments.overrides)
    if getattr(arguments, "data", None):
        overrides.append(f"data={arguments.data}")
    config = load_config(arguments.config, RunConfig, overrides=overrides)
    withhold = getattr(arguments, "withhold", 0)
    truth_out = getattr(arguments, "truth_out", None)
    synth_options = {"withhold": withhold, "truth_out": truth_out} if withhold or truth_out else {}
    return pipeline.run(
        config,
        out=arguments.out,
        force=arguments.force,
        device=arguments.device,
        stages=stages,
        stage_options={"synth": synth_options},
        config_file=arguments.config,
    )


def _check_resume_alone(arguments) -> None:
    """--resume continues a run with its own recorded config: flags that would change what the
    run does cannot apply, so they are refused rather than silently ignored."""
    given = []
    if arguments.config:
        given.append(f"CONFIG {arguments.config}")
    for flag, value in (
        ("--set", arguments.overrides),
        ("--out", arguments.out),
        ("--force", arguments.force),
        ("--data", getattr(arguments, "data", None)),
        ("--withhold", getattr(arguments, "withhold", 0)),
        ("--truth-out", getattr(arguments, "truth_out", None)),
    ):
        if value:
            given.append(flag)
    if given:
        raise ReconError(
            f"--resume {arguments.resume}: continues the run with its recorded "
            f"config.resolved.yaml; {', '.join(given)} cannot apply (start a new run instead)"
        )


def _compare(arguments) -> int:
    from recon.io.run_folder import RunPaths
    from recon.report.compare import compare, format_table, load_baseline, write_baseline

    source = Path(arguments.run)
    metrics_path = RunPaths(source).metrics if source.is_dir() else source
    if not metrics_path.exists():
        raise ReconError(f"compare: {metrics_path} not found (run 'recon evaluate' first)")
    try:
        metrics = json.loads(metrics_path.read_text())
    except json.JSONDecodeError as error:
        raise ReconError(f"compare: {metrics_path}: not valid JSON ({error})") from error
    if arguments.write:
        write_baseline(metrics, arguments.baseline, force=arguments.force)
        print(f"baseline written: {arguments.baseline}")
        return 0
    results = compare(metrics, load_baseline(arguments.baseline), source=metrics_path)
    print(format_table(results))
    return 0 if all(item.passed for item in results) else 1


def _diagnose(arguments) -> int:
    from recon import pipeline
    from recon.io.run_folder import open_run_folder
    from recon.preflight import check_writable
    from recon.report.diagnosis_text import diagnosis_lines
    from recon.stages.diagnose import run_diagnosis

    paths = open_run_folder(arguments.run)
    outside = [item for item in arguments.overrides if not item.startswith("diagnose.")]
    if outside:
        raise ReconError(
            f"--set {outside[0]}: only diagnose.* settings can change after the fit (the fit "
            "was made with the others)"
        )
    config = load_config(paths.resolved_config, RunConfig, overrides=arguments.overrides)
    paths = open_run_folder(arguments.run, arguments.data or config.data)
    # Checked before the diagnosis runs, not when its result cannot be written.
    check_writable(paths.root, "run folder")
    candidates = None if arguments.effects == "all" else arguments.effects.split(",")
    device = pipeline.resolve_device(arguments.device or config.device)
    diagnosis = run_diagnosis(paths, config, device, arguments.refit, candidates)
    for line in diagnosis_lines(diagnosis):
        print(line)
    print(f"diagnosis: {paths.diagnosis}")
    # The report shows the diagnosis: bring it up to date with the new diagnosis.json.
    pipeline.run_stages(config, paths, device, ["report"], None)
    print(f"report: {paths.report_html} (with the diagnosis section)")
    return 0


def _run_command(arguments) -> int:
    command = arguments.command
    if command in cli_info.COMMANDS:
        return cli_info.run(arguments)
    from recon import pipeline  # torch: after parsing, so --help and the views stay fast

    if command == "compare":
        return _compare(arguments)
    if command == "diagnose":
        return _diagnose(arguments)
    if command == "sweep":
        return run_sweep_command(arguments)
    if command in ("evaluate", "report"):
        paths = pipeline.run_stage_on(arguments.run, command, arguments.device, arguments.overrides)
    elif getattr(arguments, "resume", None):
        _check_resume_alone(arguments)
        stages = {"fit": ["fit", "evaluate", "report"], "synth": ["synth"]}.get(command)
        paths = pipeline.resume(arguments.resume, arguments.device, stages=stages)
    elif command == "synth":
        paths = _new_run(arguments, ["synth"])
    elif command == "fit":
        paths = _new_run(arguments, ["fit", "evaluate", "report"])
    else:
        paths = _new_run(arguments, None)
    print(pipeline.describe(paths))
    return 0


def _interrupted_message(arguments, interrupt: KeyboardInterrupt) -> str:
    """Where to continue: the run folder the pipeline attached to the interrupt, if any."""
    run = getattr(interrupt, "run_folder", None) or getattr(arguments, "resume", None)
    if arguments.command not in ("run", "synth", "fit") or run is None:
        return "recon: interrupted"
    return (
        "recon: interrupted; what was written is kept: continue with "
        f"'recon {arguments.command} --resume {run}'"
    )


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and run it. Every failure is one line, `recon: error: ...`, and
    exit code 2 (1 is kept for `recon compare` finding a regression); --debug shows the
    traceback."""
    arguments = build_parser().parse_args(argv)
    try:
        return _run_command(arguments)
    except KeyboardInterrupt as interrupt:
        print(_interrupted_message(arguments, interrupt), file=sys.stderr)
        return 130
    except Exception as error:  # the one place that turns every failure into exit 2
        if arguments.debug:
            import traceback

            traceback.print_exc()
        if isinstance(error, ReconError):
            message = str(error)
            run = getattr(error, "run_folder", None)
            if run is not None and arguments.command in ("run", "synth", "fit"):
                message += f"; what was written is kept: 'recon {arguments.command} --resume {run}'"
        elif isinstance(error, OSError):
            message = describe_os_error(error)
        else:
            message = (
                f"internal error {type(error).__name__}: {error} (please report it; rerun "
                "with --debug for the traceback)"
            )
        print(f"recon: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
