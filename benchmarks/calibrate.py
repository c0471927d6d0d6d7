"""Null allowances of the gap diagnosis from clean calibration fits.

Diagnoses run folders fitted on clean data (no effect injected) and prints, per candidate
effect, the largest held-out reduction its probe reached and the largest bootstrap lower bound
of its absorption refit and relight probe (CALIBRATED_STATISTIC), and the allowance the config
section diagnose.decision takes (twice that, floored at its minimum_share), plus the
visibility fingerprint's largest share. A probe its own run's null vetoes (a failed "null" or
"edge_blur" evidence: its reduction is a misfit the null recognised) counts only where every
clean probe of that effect is vetoed. The runs must not be cases the blind benchmark scores.

    recon-bench calibrate RUN [RUN ...]

For example the clean calibration seeds of the benchmark (fitted with
``recon-bench diagnose --fits-only --clean 6``; seeds 103-105 calibrate,
100-102 are scored):

    recon-bench calibrate runs/bench_diagnose/*/none_seed10[345]

``calibrate_thresholds`` is the same rule as a function over stored diagnoses, returning the
flat threshold set of benchmarks.blind.decide (``diagnose_section`` turns it into a
``diagnose:`` config section); the broadened blind check (recon-bench diagnose-blind --worlds)
calls it once per held-out scene, on the other scenes' clean cases only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import yaml

from benchmarks.record import commit as record_commit

# An allowance is this many times the largest statistic seen on the clean calibration fits.
CALIBRATION_MARGIN = 2.0

# The statistic of each evidence kind an allowance is calibrated on ('per_rule'). The absorption
# refit and the relight probe are calibrated on the bootstrap lower bound, the statistic the
# decision compares with their allowance (twice a clean *point* reduction, compared with a lower
# bound, missed 3 of 10 response curves in each synthetic world). The probes stay on the point
# reduction: their clean lower bounds follow the scene's misfit (the path-traced teapot's
# clean pose probe reaches 0.044, the other scenes' at most 0.021), and calibrated on them the
# held-out teapot's non-pose cases (pose lower bounds 0.03-0.085) name 10 spurious pose errors
# (docs/decisions/0197-diagnosis-camera-effects-calibration.md).
CALIBRATED_STATISTIC = {"probe": "reduction", "absorption": "lower_bound", "relight": "lower_bound"}
STATISTICS = ("per_rule", "reduction", "lower_bound")


def evidence_statistic(evidence, statistic: str) -> float | None:
    """The value of one probe, absorption or relight Evidence an allowance is calibrated on:
    'reduction' its point reduction, 'lower_bound' its bootstrap lower bound (the Evidence's
    statistic), 'per_rule' the one CALIBRATED_STATISTIC names for its kind; None when missing."""
    if statistic not in STATISTICS:
        from recon.errors import ReconError

        raise ReconError(f"calibration statistic: expected one of {STATISTICS}, got {statistic!r}")
    if statistic == "per_rule":
        statistic = CALIBRATED_STATISTIC[evidence.kind]
    if statistic == "lower_bound":
        value = evidence.statistic
    else:
        value = evidence.details.get("reduction")
    if value is None or value != value:
        return None
    return float(value)


def beyond_statistic(candidate) -> float | None:
    """The point reduction a geometric candidate's probe keeps on top of its strongest confuser
    (the least over its specificity pair records; the statistic of its "beyond_confusers"
    evidence, whose lower bound the decision compares), or None without records."""
    check = candidate.evidence_of("specificity")
    records = (check.details.get("pairs") if check is not None else None) or []
    values = [record["on_top_of_confuser"]["reduction"] for record in records]
    values = [value for value in values if value is not None and value == value]
    return min(values) if values else None


def bounce_otherwise_passes(evidence) -> bool:
    """Whether a bounce Evidence passes every test of its decision row but the floor (the
    placebo level and the strength bounced light can have, at the defaults): only such a clean
    case shows how high the floor must be; one the strength refuses is silent at any floor
    (docs/decisions/0215-interreflection-blind.md)."""
    from recon.config.run_config import DecisionConfig

    config = DecisionConfig()
    p_value = evidence.details.get("p_value", 1.0)
    strength = evidence.details.get("strength", 0.0)
    return p_value < config.bounce_alpha and 0.0 < strength <= config.bounce_maximum_strength


# The evidence kinds that keep a probe from clearing when they fail (the decision's "raise bar"
# rows, recon.diagnose.decision): the run's own null for that probe.
PROBE_NULL_KINDS = ("null", "edge_blur")


def probe_vetoed_by_null(candidate) -> bool:
    """Whether a failed null of the run itself (PROBE_NULL_KINDS) keeps the candidate's probe
    from clearing at any allowance: such a clean probe shows nothing about how high the
    allowance must be (the argument bounce_otherwise_passes makes for the bounce floor), and
    its reduction is the misfit the null recognised (docs/decisions/0228-blur-nulls.md)."""
    return any(
        evidence.kind in PROBE_NULL_KINDS and evidence.passed is False
        for evidence in candidate.evidence
    )


def clean_statistics(
    diagnosis: dict,
    present: tuple[str, ...] = (),
    statistic: str = "per_rule",
    skip_vetoed_probes: bool = False,
) -> dict[str, float]:
    """The statistics of one clean diagnosis (diagnosis.json, either schema) that its thresholds
    are compared with, by threshold name (benchmarks.blind.decide): each probe's, absorption
    refit's and relight probe's reduction, each geometric probe's point reduction on top of its
    strongest confuser (beyond_statistic), the agreement's shared colour spread, the flat
    field's deviation, the visibility fingerprint's excess over its placebo lights and the
    bounce evidence's excess where it otherwise passes (bounce_otherwise_passes). present: effects the data
    holds although nothing was injected (a
    path tracer's cast shadows): their statistics measure the effect, not the null, and are left
    out (the visibility fingerprint with shadows or interreflection).

    statistic: 'per_rule' (default) takes each kind's CALIBRATED_STATISTIC (the absorption's
    and relight probe's bootstrap lower bound, the statistic the decision compares; the probes'
    point reduction); 'reduction' every kind's point reduction (the rule the code's defaults
    were measured with: a lower bound compared with twice a clean point estimate, doubly
    conservative); 'lower_bound' every kind's lower bound (tried on the blind check: more
    effects found, but spurious pose errors on the path tracer's scenes, see
    docs/decisions/0191-blind-misses.md).

    skip_vetoed_probes: leave out the probes a failed null of the run vetoes
    (probe_vetoed_by_null)."""
    from recon.diagnose.records import Diagnosis

    found: dict[str, float] = {}

    def keep(name: str, value: float | None) -> None:
        if value is not None:
            found[name] = max(found.get(name, float("-inf")), float(value))

    stored = Diagnosis.from_json(diagnosis)
    for candidate in stored.candidates:
        if candidate.name in present:
            continue
        probe_silenced = skip_vetoed_probes and probe_vetoed_by_null(candidate)
        for kind, name in (
            ("probe", f"probe.{candidate.name}"),
            ("absorption", f"absorption.{candidate.name}"),
            ("relight", "relight"),
        ):
            evidence = candidate.evidence_of(kind)
            if evidence is not None and not (kind == "probe" and probe_silenced):
                keep(name, evidence_statistic(evidence, statistic))
        agreement = candidate.evidence_of("agreement")
        if agreement is not None:
            keep(f"agreement.{candidate.name}", agreement.statistic)
        lobe = candidate.evidence_of("lobe")
        if lobe is not None:
            keep(f"lobe.{candidate.name}", lobe.statistic)
        beyond = beyond_statistic(candidate)
        if beyond is not None:
            keep(f"beyond.{candidate.name}", beyond)
        flat_field = candidate.evidence_of("flat_field")
        if flat_field is not None:
            keep("flat_field", flat_field.statistic)
        bounce = candidate.evidence_of("bounce")
        if bounce is not None and bounce_otherwise_passes(bounce):
            keep("bounce", bounce.statistic)
    fingerprint = (stored.gap or {}).get("visibility_fingerprint") or {}
    excess = fingerprint.get("excess")
    if (
        excess is not None
        and excess == excess
        and not {"shadows", "interreflection"} & set(present)
    ):
        keep("fingerprint", excess)
    return found


def threshold_floors() -> dict[str, float]:
    """The least value of each threshold, whatever the clean fits show: the decision config's
    floors (minimum_share, the absorption evidence's own), its flat-field allowance and
    fingerprint minimum."""
    from benchmarks.blind.decide import code_thresholds
    from recon.config.run_config import DecisionConfig

    defaults = DecisionConfig()
    return code_thresholds(
        DecisionConfig(
            probe_allowance={},
            absorption_allowance={},
            agreement_allowance={},
            lobe_allowance={},
            beyond_confusers_allowance={name: 0.0 for name in defaults.beyond_confusers_allowance},
            relight_allowance=defaults.minimum_share,
        )
    )


def calibrate_thresholds(
    diagnoses: list[dict],
    present: list[tuple[str, ...]] | None = None,
    margin: float = CALIBRATION_MARGIN,
    statistic: str = "per_rule",
) -> dict[str, float]:
    """Thresholds from clean diagnoses: margin x the largest statistic of each (clean_statistics),
    floored at threshold_floors(), leaving out each diagnosis' present effects and the probes
    their own null vetoes (where any clean probe of that effect passes its null); thresholds no
    clean diagnosis measured keep the default's value (benchmarks.blind.decide.code_thresholds),
    and so does shadow_share (a physical split, not a null)."""
    from benchmarks.blind.decide import code_thresholds

    if not diagnoses:
        from recon.errors import ReconError

        raise ReconError("calibrate_thresholds: no clean diagnoses to calibrate on")
    present = present or [()] * len(diagnoses)

    def largest_over(skip_vetoed_probes: bool) -> dict[str, float]:
        largest: dict[str, float] = {}
        for diagnosis, held in zip(diagnoses, present, strict=True):
            measured = clean_statistics(diagnosis, held, statistic, skip_vetoed_probes)
            for name, value in measured.items():
                largest[name] = max(largest.get(name, float("-inf")), value)
        return largest

    # A probe is calibrated on the clean probes its own null lets clear; where the null vetoes
    # every clean probe of an effect, on all of them (nothing says how high it must be, so the
    # old, conservative rule stands).
    largest = largest_over(skip_vetoed_probes=True)
    for name, value in largest_over(skip_vetoed_probes=False).items():
        largest.setdefault(name, value)
    floors = threshold_floors()
    thresholds = code_thresholds()
    for name, value in largest.items():
        if name in thresholds and name != "shadow_share":
            thresholds[name] = round(max(floors[name], margin * value), 4)
    return thresholds


def calibration_record(
    thresholds: dict[str, float], calibrated_on: list[dict], base_config: dict
) -> dict:
    """thresholds with their provenance: the commit, the hash of the base config the cases were
    made from, and the clean cases (world, scene, seed) they were calibrated on."""
    from benchmarks.blind.decide import diagnose_section

    canonical = json.dumps(base_config, sort_keys=True, separators=(",", ":"), default=str)
    return {
        "thresholds": thresholds,
        # The same values as a run config's `diagnose:` section.
        "diagnose": diagnose_section(thresholds) if thresholds else {},
        "provenance": {
            "commit": record_commit(),
            "base_config_sha256": hashlib.sha256(canonical.encode()).hexdigest()[:12],
            "rule": f"max(floor, {CALIBRATION_MARGIN:g} x largest clean statistic)",
            "probes": "those their run's null lets clear, where any does (else all)",
            "statistic": dict(CALIBRATED_STATISTIC),
            "calibrated_on": calibrated_on,
            "scenes": sorted({case["scene"] for case in calibrated_on}),
            "seeds": sorted({case["seed"] for case in calibrated_on}),
        },
    }


def _largest(candidates, kind: str, into: dict) -> None:
    """The largest calibrated statistic (CALIBRATED_STATISTIC) of one evidence kind per
    candidate, accumulated into `into`."""
    for candidate in candidates:
        evidence = candidate.evidence_of(kind)
        value = None if evidence is None else evidence_statistic(evidence, "per_rule")
        if value is not None:
            into[candidate.name] = max(into.get(candidate.name, 0.0), value)


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
    probe, probe_all, absorption, relight, shares, provenance = {}, {}, {}, {}, [], []
    for run in arguments.runs:
        paths = open_run_folder(Path(run))
        config = load_config(paths.resolved_config, RunConfig)
        if arguments.stored and paths.diagnosis.exists():
            diagnosis = Diagnosis.from_json(json.loads(paths.diagnosis.read_text()))
        else:
            diagnosis = run_diagnosis(paths, config, torch.device("cpu"), refit="none")
        _largest(diagnosis.candidates, "probe", probe_all)
        _largest(
            [item for item in diagnosis.candidates if not probe_vetoed_by_null(item)],
            "probe",
            probe,
        )
        _largest(diagnosis.candidates, "absorption", absorption)
        _largest(diagnosis.candidates, "relight", relight)
        shares.append(diagnosis.gap["visibility_fingerprint"]["share"])
        provenance.append(
            {"run": str(paths.root), "config_hash": config_hash(config), "seed": config.seed}
        )

    for name, value in probe_all.items():  # the null vetoed every clean probe of it
        probe.setdefault(name, value)
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
        from recon.io.atomic import atomic_write_text

        header = [
            "# diagnose.decision allowances written by `recon-bench calibrate` (twice the largest",
            "# clean reduction, floored). Provenance:",
            f"# commit: {record_commit()}",
        ] + [
            f"# run: {item['run']} config_hash {item['config_hash']} seed {item['seed']}"
            for item in provenance
        ]
        body = yaml.safe_dump({"diagnose": {"decision": decision}}, sort_keys=False)
        atomic_write_text(Path(arguments.write), "\n".join(header) + "\n" + body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
