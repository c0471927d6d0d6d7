"""Null allowances of the gap diagnosis from clean calibration fits.

Diagnoses run folders fitted on clean data (no effect injected) and prints, per candidate
effect, the largest held-out reduction its probe and its absorption refit reached, and the
allowance recon.diagnose.calibration uses (twice that, floored at MINIMUM_SHARE), plus the
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


def main(argv: list[str] | None = None) -> int:
    import torch

    from recon.config import load_config
    from recon.config.run_config import RunConfig
    from recon.diagnose.calibration import MINIMUM_SHARE, absorption_minimum_share
    from recon.diagnose.diagnose import diagnose_run
    from recon.io.run_folder import open_run_folder

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", help="run folders fitted on clean data")
    parser.add_argument(
        "--stored",
        action="store_true",
        help="read each run's diagnosis.json instead of diagnosing again (the evidence is the "
        "same; only the decision depends on the thresholds)",
    )
    arguments = parser.parse_args(argv)
    probe, absorption, relight, shares = {}, {}, {}, []
    for run in arguments.runs:
        paths = open_run_folder(Path(run))
        stored = paths.diagnosis
        if arguments.stored and stored.exists():
            result = json.loads(stored.read_text())
        else:
            config = load_config(paths.resolved_config, RunConfig)
            result = diagnose_run(paths, config, torch.device("cpu"), refit="none")
        for item in result["ranking"]:
            name = item["effect"]
            probe[name] = max(probe.get(name, 0.0), item["heldout_reduction"])
            if item["absorption"] is not None:
                absorption[name] = max(absorption.get(name, 0.0), item["absorption"])
            if item.get("relight_reduction") is not None:
                relight[name] = max(relight.get(name, 0.0), item["relight_reduction"])
        shares.append(result["gap"]["visibility_fingerprint"]["share"])

    def allowance(values: dict, floor=lambda name: MINIMUM_SHARE) -> dict:
        return {name: round(max(floor(name), 2 * value), 3) for name, value in values.items()}

    print(
        json.dumps(
            {
                "runs": len(arguments.runs),
                "probe_largest": probe,
                "probe_allowance": allowance(probe),
                "absorption_largest": absorption,
                "absorption_allowance": allowance(absorption, absorption_minimum_share),
                "relight_largest": relight,
                "relight_allowance": allowance(relight),
                "visibility_share_largest": max(shares),
            },
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
