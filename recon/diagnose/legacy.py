"""diagnosis.json written before the typed records (no schema_version: a "ranking" of flat
entries) read as a Diagnosis, so stored diagnoses can still be re-decided
(recon.diagnose.decision.redecide): every measurement becomes the Evidence it was."""

from __future__ import annotations

import math
from typing import Any

from recon.diagnose.records import Candidate, Diagnosis, Evidence


def _evidence(kind: str, name: str, statistic: float, reason: str, **details) -> Evidence:
    return Evidence(kind, name, statistic, math.nan, False, reason, details)


def legacy_candidate(record: dict[str, Any]) -> Candidate:
    """One ranking entry of the old form as a Candidate with its evidence (undecided)."""
    name = record["effect"]
    candidate = Candidate(name)
    interval = record.get("interval")
    if interval is not None:
        candidate.add(
            _evidence(
                "probe",
                name,
                interval[0],
                "probe: held-out reduction's lower bound",
                reduction=record.get("heldout_reduction"),
                interval=list(interval),
                score=record.get("score"),
                parameters=record.get("probe_parameters", record.get("parameters")) or {},
                conditional_on=record.get("conditional_on"),
            )
        )
    absorption = record.get("absorption_interval")
    if absorption is not None:
        discounted = record.get("absorption_discounted_by")
        evidence = _evidence(
            "absorption",
            name,
            absorption[0],
            "absorption refit: held-out reduction over the control's lower bound",
            reduction=record.get("absorption"),
            interval=list(absorption),
            parameters=record.get("absorption_parameters") or {},
            conditional_on=record.get("conditional_on"),
            discounted_by=discounted,
        )
        if discounted:
            evidence = Evidence(
                **{
                    **evidence.__dict__,
                    "void": f"absorption measured alone: void beside {discounted}",
                }
            )
        candidate.add(evidence)
    relight = record.get("relight_interval")
    if relight is not None:
        candidate.add(
            _evidence(
                "relight",
                name,
                relight[0],
                "relight split's response probe: reduction's lower bound",
                reduction=record.get("relight_reduction"),
                interval=list(relight),
                parameters=record.get("relight_parameters") or {},
            )
        )
    flat_field = record.get("flat_field")
    if flat_field is not None:
        candidate.add(
            _evidence(
                "flat_field",
                name,
                flat_field["deviation"],
                "flat-field frames: deviation of the corner or half-way falloff from 1",
                **{
                    key: flat_field[key]
                    for key in ("corner_falloff", "half_radius_falloff", "frames")
                    if key in flat_field
                },
            )
        )
    fingerprint = record.get("fingerprint")
    if fingerprint is not None and "share" in fingerprint:
        # The old share had no null from the run (no placebo lights): recorded, not measured
        # against anything, so it names nothing when re-decided.
        candidate.add(
            _evidence(
                "fingerprint",
                name,
                math.nan,
                f"visibility fingerprint of an old diagnosis: slope {fingerprint['share']:.2f} "
                "of the fitted mesh's self-shadowing in the albedo, without placebo lights (no "
                "null from the run: diagnose the run again)",
                slope=fingerprint["share"],
                share=min(1.0, max(0.0, fingerprint["share"])),
                interval=list(fingerprint.get("interval", [fingerprint["share"]] * 2)),
                coverage=fingerprint.get("coverage", 1.0),
            )
        )
    return candidate


def from_legacy(record: dict[str, Any]) -> Diagnosis:
    """An old diagnosis.json as an (undecided) Diagnosis; redecide decides it."""
    return Diagnosis(
        gap=record.get("gap", {}),
        where=record.get("where", {}),
        candidates=[legacy_candidate(item) for item in record["ranking"]],
        refits=record.get("refits", []),
        verdict=record.get("verdict", ""),
        confirmed_by_refit=record.get("confirmed_by_refit", []),
        timings=record.get("timings", {}),
        figures=record.get("figures", {}),
    )
