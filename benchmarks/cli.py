"""recon-bench: run one benchmark by name.

    recon-bench                       list the benchmarks
    recon-bench NAME [ARGS ...]       run one; `recon-bench NAME --help` shows its options
    recon-bench NAME --record [ARGS]  run one and write docs/bench/NAME.json (with commit, date,
                                      machine, config hash), then regenerate docs/benchmarks.md
                                      and the README's benchmark summary (benchmarks.record)
    recon-bench docs                  regenerate those two pages from docs/bench/*.json

Each benchmark is a module of this package with ``main(argv) -> int | None``; adding one is one
line in BENCHMARKS. Modules are imported only when their benchmark runs, so the listing stays
fast and a benchmark's optional dependency (Ray, Mitsuba) is needed only by that benchmark.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import sys

from recon.errors import ReconError, describe_os_error

# name -> (module, one line on what it measures)
BENCHMARKS: dict[str, tuple[str, str]] = {
    "diagnose-blind": (
        "benchmarks.diagnose_blind",
        "blind check: withheld effects -> fit -> diagnose -> score (--worlds: across worlds and "
        "scenes, leave-one-scene-out)",
    ),
    "calibrate": ("benchmarks.calibrate", "null allowances of the diagnosis from clean fits"),
    "render": ("benchmarks.render", "renderer forward + backward timings, Mitsuba 3 peer"),
    "synth": ("benchmarks.synth", "data_synth's own and Mitsuba backends, time per view"),
    "fit": ("benchmarks.fit", "full runs on the bench scenes against the quality targets"),
    "diagnose": ("benchmarks.diagnose", "the blind benchmark at 128 px on default and spot"),
    "sweep": ("benchmarks.sweep", "recon sweep: local against Ray, overhead per trial"),
    "allreduce": ("benchmarks.allreduce", "gloo all_reduce bandwidth between local processes"),
    "diagnosis-costs": ("benchmarks.diagnosis_costs", "the diagnosis' pieces timed on a run"),
    "time-diagnosis": ("benchmarks.time_diagnosis", "diagnosis time against fit time"),
    "flat-field-accuracy": (
        "benchmarks.flat_field_accuracy",
        "flat-field falloff measurement against the world's",
    ),
    "vignetting-extrapolation": (
        "benchmarks.vignetting_extrapolation",
        "vignetting falloff extrapolated to the corners",
    ),
    "refit-settings": ("benchmarks.refit_settings", "refit learning rates of one effect"),
    "real-capture": (
        "benchmarks.real_capture",
        "the shared real capture fitted from its raw layout",
    ),
    "sfm-poses": (
        "benchmarks.sfm_poses",
        "plain-folder SfM poses against the real capture's published ones",
    ),
    "nerf-synthetic": (
        "benchmarks.nerf_synthetic",
        "NeRF-synthetic style Mitsuba scenes at 200 px beside nvdiffrec",
    ),
    "material": ("benchmarks.material", "pbr against lambert on a Mitsuba-rendered glossy scene"),
}

PROGRAM = "recon-bench"


def usage() -> str:
    """The listing printed by `recon-bench` and `recon-bench --help`."""
    width = max(len(name) for name in BENCHMARKS)
    lines = [f"usage: {PROGRAM} NAME [ARGS ...]  ({PROGRAM} NAME --help for its options)", ""]
    lines += [f"  {name:<{width}}  {summary}" for name, (_, summary) in BENCHMARKS.items()]
    lines += [
        "",
        f"  {PROGRAM} NAME --record ...  also write docs/bench/NAME.json and the pages from it",
        f"  {PROGRAM} docs               regenerate docs/benchmarks.md and the README summary",
    ]
    return "\n".join(lines)


class _Tee(io.TextIOBase):
    """Stdout that is also kept: a recorded benchmark's printed JSON becomes its record."""

    def __init__(self, stream) -> None:
        self.stream, self.kept = stream, io.StringIO()

    def write(self, text: str) -> int:
        self.kept.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()


def _record(name: str, module, argv: list[str], output: str, prov: dict) -> None:
    """Write docs/bench/NAME.json from the benchmark's printed JSON, then the pages."""
    from benchmarks import record

    result = record.parse_output(output)
    if result is None:
        raise ReconError(f"--record: {PROGRAM} {name} printed no JSON result to record")
    path = record.RECORDS / f"{name}.json"
    old = json.loads(path.read_text()) if path.exists() else None
    title = (old or {}).get("title") or getattr(module, "TITLE", name)
    command = " ".join([PROGRAM, name, *argv])
    summary = record.summary_markdown(module, result)
    record.write_record(record.make_record(name, title, command, prov, result, summary, old))
    record.regenerate()
    print(f"{PROGRAM}: recorded {path}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Dispatch to one benchmark's main. Exit codes: the benchmark's own (0 when it returns
    no code); 2 for an unknown name or a ReconError/OSError, printed as one line."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name == "docs":
        from benchmarks import record

        record.regenerate()
        return 0
    recording = "--record" in rest
    rest = [item for item in rest if item != "--record"]
    if name not in BENCHMARKS:
        print(f"{PROGRAM}: error: unknown benchmark {name!r}\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(BENCHMARKS[name][0])
    # argparse names the program after argv[0]: show `recon-bench NAME` in usage and errors.
    program = sys.argv[0]
    sys.argv[0] = f"{PROGRAM} {name}"
    try:
        if recording:
            from benchmarks import record

            prov = record.provenance(name, rest)
            tee = _Tee(sys.stdout)
            with contextlib.redirect_stdout(tee):
                code = module.main(rest)
            if code in (None, 0):
                _record(name, module, rest, tee.kept.getvalue(), prov)
        else:
            code = module.main(rest)
    except ReconError as error:
        print(f"{PROGRAM}: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"{PROGRAM}: error: {describe_os_error(error)}", file=sys.stderr)
        return 2
    finally:
        sys.argv[0] = program
    return code if isinstance(code, int) else 0


if __name__ == "__main__":
    sys.exit(main())
