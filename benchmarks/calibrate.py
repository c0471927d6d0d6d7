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

``calibrate_thresholds`` is the same rule as a function over stored diagnoses, returning the
flat threshold set of benchmarks.blind.decide (the form the diagnosis' ``diagnose:`` config
section takes); the broadened blind check (recon-bench diagnose-blind --worlds) calls it once per
held-out scene, on the other scenes' clean cases only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

# An allowance is this many times the largest statistic seen on the clean calibration fits.
CALIBRATION_MARGIN = 2.0


def clean_statistics(diagnosis: dict, present: tuple[str, ...] = ()) -> dict[str, float]:
    """The statistics of one clean diagnosis that its thresholds are compared with, by
    threshold name (benchmarks.blind.decide): each probe's held-out reduction, each absorption
    refit's reduction, the relight probe's, the flat field's deviation and the visibility
    fingerprint's lower bound. present: effects the data holds although nothing was injected
    (a path tracer's cast shadows): their statistics measure the effect, not the null, and are
    left out (the visibility fingerprint with shadows or interreflection)."""
    found: dict[str, float] = {}

    def keep(name: str, value: float | None) -> None:
        if value is not None:
            found[name] = max(found.get(name, float("-inf")), float(value))

    for item in diagnosis["ranking"]:
        effect = item["effect"]
        if effect in present:
            continue
        keep(f"probe.{effect}", item.get("heldout_reduction"))
        keep(f"absorption.{effect}", item.get("absorption"))
        keep("relight", item.get("relight_reduction"))
        if item.get("flat_field"):
            keep("flat_field", item["flat_field"].get("deviation"))
    fingerprint = (diagnosis.get("gap") or {}).get("visibility_fingerprint") or {}
    if fingerprint.get("interval") and not {"shadows", "interreflection"} & set(present):
        keep("visibility_share", fingerprint["interval"][0])
    return found


def threshold_floors() -> dict[str, float]:
    """The least value of each threshold, whatever the clean fits show: the code's floors
    (recon.diagnose.calibration), the flat field's allowance and the fingerprint's minimum."""
    from benchmarks.blind.decide import code_thresholds
    from recon.diagnose import calibration
    from recon.effects.registry import MODEL_EFFECTS

    floors = dict(code_thresholds())
    for effect in MODEL_EFFECTS:
        floors[f"probe.{effect}"] = calibration.MINIMUM_SHARE
        floors[f"absorption.{effect}"] = calibration.absorption_minimum_share(effect)
    floors["relight"] = calibration.MINIMUM_SHARE
    return floors


def calibrate_thresholds(
    diagnoses: list[dict],
    present: list[tuple[str, ...]] | None = None,
    margin: float = CALIBRATION_MARGIN,
) -> dict[str, float]:
    """Thresholds from clean diagnoses: margin x the largest statistic of each (clean_statistics),
    floored at threshold_floors(), leaving out each diagnosis' present effects
    (clean_statistics); thresholds no clean diagnosis measured keep the code's value
    (benchmarks.blind.decide.code_thresholds), and so does shadow_share (a physical split, not a
    null)."""
    if not diagnoses:
        from recon.errors import ReconError

        raise ReconError("calibrate_thresholds: no clean diagnoses to calibrate on")
    largest: dict[str, float] = {}
    present = present or [()] * len(diagnoses)
    for diagnosis, held in zip(diagnoses, present, strict=True):
        for name, value in clean_statistics(diagnosis, held).items():
            largest[name] = max(largest.get(name, float("-inf")), value)
    from benchmarks.blind.decide import code_thresholds

    floors = threshold_floors()
    thresholds = code_thresholds()
    for name, value in largest.items():
        if name in thresholds and name != "shadow_share":
            thresholds[name] = round(max(floors[name], margin * value), 4)
    return thresholds


def git_commit(folder: Path) -> str:
    """HEAD of the repository at folder (with '+dirty' when the tree has changes), or
    'unknown'."""
    try:
        head = subprocess.run(
            ["git", "-C", str(folder), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def calibration_record(
    thresholds: dict[str, float], calibrated_on: list[dict], base_config: dict
) -> dict:
    """thresholds with their provenance: the commit, the hash of the base config the cases were
    made from, and the clean cases (world, scene, seed) they were calibrated on."""
    from benchmarks.blind.decide import diagnose_section

    canonical = json.dumps(base_config, sort_keys=True, separators=(",", ":"), default=str)
    return {
        "thresholds": thresholds,
        # The same values as a run config's `diagnose:` section (the diagnosis engine's form).
        "diagnose": diagnose_section(thresholds) if thresholds else {},
        "provenance": {
            "commit": git_commit(Path(__file__).resolve().parents[1]),
            "base_config_sha256": hashlib.sha256(canonical.encode()).hexdigest()[:12],
            "rule": f"max(floor, {CALIBRATION_MARGIN:g} x largest clean statistic)",
            "calibrated_on": calibrated_on,
            "scenes": sorted({case["scene"] for case in calibrated_on}),
            "seeds": sorted({case["seed"] for case in calibrated_on}),
        },
    }


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
