"""The diagnosis's typed records: one piece of evidence about one candidate.

Every check the diagnosis runs (a probe's held-out reduction, an absorption refit, a specificity
check against a confusable effect or the base model's mismatch, a null derived from the run,
an identifiability condition, a comparison with capture metadata) ends as one ``Evidence``: what
was measured, what it had to clear, whether it did, and one line a user can read. The decision
rule reads Evidence only, so a new kind of check is one new producer of Evidence.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

# Bumped whenever a record's JSON form changes incompatibly.
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class Evidence:
    """One measurement about one candidate (an effect name, or a base-model mismatch such as
    ``view_dependent_reflectance``).

    kind: what produced it ("probe", "absorption", "relight", "flat_field", "fingerprint",
        "specificity", "null", "identifiability", "metadata", ...).
    statistic: the measured value (e.g. the lower bound of a held-out reduction, a p-value, a
        correlation), in the unit ``reason`` states.
    threshold: what the statistic had to clear (a null derived from the run, or a configured
        bound); NaN where the check is a condition, not a comparison.
    passed: whether the check speaks for the candidate.
    reason: one line a user can read, saying what was measured against what.
    details: JSON-serialisable extras (per-view gains, bin statistics, ...).
    """

    kind: str
    candidate: str
    statistic: float
    threshold: float
    passed: bool
    reason: str
    details: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        record = asdict(self)
        for key in ("statistic", "threshold"):
            value = record[key]
            record[key] = None if value is None or math.isnan(value) else float(value)
        return record

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Evidence:
        return cls(
            kind=record["kind"],
            candidate=record["candidate"],
            statistic=math.nan if record["statistic"] is None else float(record["statistic"]),
            threshold=math.nan if record["threshold"] is None else float(record["threshold"]),
            passed=bool(record["passed"]),
            reason=record["reason"],
            details=dict(record.get("details") or {}),
        )
