"""Null allowances of the gap diagnosis from clean calibration fits.

Diagnoses run folders fitted on clean data (no effect injected) and prints, per candidate
effect, the largest held-out reduction its probe and its absorption refit reached, and the
allowance the config section diagnose.decision takes (twice that, floored at its
minimum_share), plus the
visibility fingerprint's largest share. The runs must not be cases the blind benchmark scores.

    recon-bench calibrate RUN [RUN ...]

For example the clean calibration seeds of the benchmark (fitted with
``recon-bench diagnose --fits-only --clean 6``; seeds 103-105 calibrate,
100-102 are scored):

    recon-bench calibrate runs/bench_diagnose/*/none_seed10[345]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml


def _largest(candidates, kind: str, into: dict) -> None:
    """The largest reduction of one evidence kind per candidate, accumulated into `into`."""
    for candidate in candidates:
        evidence = candidate.evidence_of(kind)
        if evidence is not None and evidence.details.get("reduction") is not None:
            into[candidate.name] = max(into.get(candidate.name, 0.0), evidence.details["reduction"])


def main(argv: list[str] | None = None) -> int:
    import torch

    from recon.config import config_hash, load_config, to_dict
    from recon.config.run_config import DecisionConfig, RunConfig
    from recon.diagnose.decision import absorption_threshold
    from recon.diagnose.records import Diagnosis
    from recon.io.run_folder import open_run_folder
    from recon.stages.diagnose import run_diagnosis

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", help="run folders fitted on clean data")
    parser.add_argument(
        "--stored",
        action="store_true",
        help="read each run's diagnosis.json instead of diagnosing again (the evidence is the "
        "same; only the decision depends on the thresholds)",
    )
    parser.add_argument(
        "--write",
        help="also write the allowances as a config fragment (diagnose.decision) with their "
        "provenance (commit, the runs' config hashes and seeds)",
    )
    arguments = parser.parse_args(argv)
    probe, absorption, relight, shares, provenance = {}, {}, {}, [], []
    for run in arguments.runs:
        paths = open_run_folder(Path(run))
        config = load_config(paths.resolved_config, RunConfig)
        if arguments.stored and paths.diagnosis.exists():
            diagnosis = Diagnosis.from_json(json.loads(paths.diagnosis.read_text()))
        else:
            diagnosis = run_diagnosis(paths, config, torch.device("cpu"), refit="none")
        _largest(diagnosis.candidates, "probe", probe)
        _largest(diagnosis.candidates, "absorption", absorption)
        _largest(diagnosis.candidates, "relight", relight)
        shares.append(diagnosis.gap["visibility_fingerprint"]["share"])
        provenance.append(
            {"run": str(paths.root), "config_hash": config_hash(config), "seed": config.seed}
        )

    defaults = DecisionConfig()

    def allowance(values: dict, floor) -> dict:
        return {name: round(max(floor(name), 2 * value), 3) for name, value in values.items()}

    def absorption_floor(name: str) -> float:
        # The floor of the evidence's own kind (closed form or refit), without the allowance.
        return absorption_threshold(name, DecisionConfig(absorption_allowance={}, minimum_share=0))

    probe_allowance = allowance(probe, lambda name: defaults.minimum_share)
    absorption_allowance = allowance(absorption, absorption_floor)
    relight_allowance = allowance(relight, lambda name: defaults.minimum_share)
    decision = to_dict(defaults)
    decision["probe_allowance"] = {
        name: value for name, value in probe_allowance.items() if value > defaults.minimum_share
    }
    decision["absorption_allowance"] = absorption_allowance
    if relight_allowance:
        decision["relight_allowance"] = max(relight_allowance.values())
    record = {
        "runs": len(arguments.runs),
        "probe_largest": probe,
        "probe_allowance": probe_allowance,
        "absorption_largest": absorption,
        "absorption_allowance": absorption_allowance,
        "relight_largest": relight,
        "relight_allowance": relight_allowance,
        "visibility_share_largest": max(shares),
        "decision": decision,
    }
    print(json.dumps(record, indent=2))
    if arguments.write:
        from benchmarks.sweep import commit as git_commit
        from recon.io.atomic import atomic_write_text

        header = [
            "# diagnose.decision allowances written by `recon-bench calibrate` (twice the largest",
            "# clean reduction, floored). Provenance:",
            f"# commit: {git_commit()}",
        ] + [
            f"# run: {item['run']} config_hash {item['config_hash']} seed {item['seed']}"
            for item in provenance
        ]
        body = yaml.safe_dump({"diagnose": {"decision": decision}}, sort_keys=False)
        atomic_write_text(Path(arguments.write), "\n".join(header) + "\n" + body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
