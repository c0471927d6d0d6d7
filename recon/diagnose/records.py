"""The diagnosis's typed records: Evidence about a candidate, the Candidate, the Diagnosis.

Every check the diagnosis runs (a probe's held-out reduction, an absorption refit, a specificity
check against a confusable effect or the base model's mismatch, a null derived from the run,
an identifiability condition, a comparison with capture metadata) ends as one ``Evidence``: what
was measured, what it had to clear, whether it did, and one line a user can read. The decision
rule (recon.diagnose.decision) reads Evidence only, so a new kind of check is one new producer
of Evidence. ``Diagnosis`` is diagnosis.json; docs/diagnosis/schema.md is generated from these
dataclasses' field docs (``python -m recon.diagnose.schema_doc > docs/diagnosis/schema.md``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

# Bumped whenever a record's JSON form changes incompatibly (1: Evidence alone, before the
# typed Candidate and Diagnosis; 2: diagnosis.json as a Diagnosis).
SCHEMA_VERSION = 2


def doc(text: str, **options: Any) -> Any:
    """A dataclass field with a user-facing doc (docs/diagnosis/schema.md is built from it)."""
    return field(metadata={"doc": text}, **options)


def _number_or_nan(value: Any) -> float:
    return math.nan if value is None else float(value)


def _number_or_none(value: float) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


@dataclass(frozen=True)
class Evidence:
    """One measurement about one candidate (an effect name, or a base-model mismatch such as
    ``view_dependent_reflectance``)."""

    kind: str = doc(
        "What produced it: probe, absorption, relight, flat_field, fingerprint, specificity, "
        "null, identifiability, metadata, ... (the decision table's rows, recon.diagnose.decision)."
    )
    candidate: str = doc("The effect or base-model mismatch it is about.")
    statistic: float = doc(
        "The measured value (a held-out reduction's lower bound, a deviation, a share, a "
        "p-value, a correlation) in the unit `reason` states; null where there is none."
    )
    threshold: float = doc(
        "What the statistic had to clear (a configured allowance or a null from the run); null "
        "where the check is a condition, not a comparison."
    )
    passed: bool = doc("Whether the check speaks for the candidate.")
    reason: str = doc("One line a user can read: what was measured against what.")
    details: dict[str, Any] = doc(
        "JSON extras: interval [low, high], reduction, parameters (recovered effect parameters), "
        "conditional_on (the effect it was measured on top of), per-view gains, ...",
        default_factory=dict,
    )
    void: str = doc(
        "Why this evidence no longer counts (kept for the record), or empty.", default=""
    )

    @property
    def interval(self) -> tuple[float, float] | None:
        """details['interval'] as a tuple, or None."""
        interval = self.details.get("interval")
        return None if interval is None else (float(interval[0]), float(interval[1]))

    @property
    def counts(self) -> bool:
        """Whether the decision may use it (not voided)."""
        return not self.void

    def to_json(self) -> dict[str, Any]:
        record = asdict(self)
        record["statistic"] = _number_or_none(self.statistic)
        record["threshold"] = _number_or_none(self.threshold)
        return record

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Evidence:
        return cls(
            kind=record["kind"],
            candidate=record["candidate"],
            statistic=_number_or_nan(record["statistic"]),
            threshold=_number_or_nan(record["threshold"]),
            passed=bool(record["passed"]),
            reason=record["reason"],
            details=dict(record.get("details") or {}),
            void=record.get("void") or "",
        )


Status = Literal["significant", "ambiguous", "not_significant", "vetoed", "not_identifiable"]


@dataclass
class Candidate:
    """One possible cause of the gap and everything measured about it."""

    name: str = doc(
        "An effect of the catalogue (`recon effects`) or a base-model mismatch (e.g. "
        "view_dependent_reflectance)."
    )
    evidence: list[Evidence] = doc(
        "Every check's Evidence about it (at most one per kind; a later one replaces it).",
        default_factory=list,
    )
    significant: bool = doc("Whether the decision names it as a cause.", default=False)
    status: Status = doc(
        "significant, ambiguous (significant, but the data cannot tell it from the effect its "
        "identifiability evidence names; scored as naming this candidate), not_significant, "
        "vetoed (a specificity check says the signature is another cause's) or "
        "not_identifiable (it did not clear and the data cannot tell it apart).",
        default="not_significant",
    )
    decided_by: str = doc(
        "The kind of the evidence that decided it (empty when nothing made it significant).",
        default="",
    )
    why: str = doc("One line a user can read: why it is or is not significant.", default="")
    parameters: dict[str, Any] = doc(
        "The recovered parameters of the deciding evidence (the probe's when nothing decided).",
        default_factory=dict,
    )

    def evidence_of(self, kind: str) -> Evidence | None:
        """The candidate's evidence of one kind, or None."""
        return next((item for item in self.evidence if item.kind == kind), None)

    def add(self, evidence: Evidence) -> None:
        """Record evidence, replacing any earlier evidence of the same kind."""
        self.evidence = [item for item in self.evidence if item.kind != evidence.kind]
        self.evidence.append(evidence)

    @property
    def conditional_on(self) -> str | None:
        """The effect its probe evidence was measured on top of (None: alone)."""
        probe = self.evidence_of("probe")
        return None if probe is None else probe.details.get("conditional_on")

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "significant": self.significant,
            "status": self.status,
            "decided_by": self.decided_by,
            "why": self.why,
            "parameters": self.parameters,
            "evidence": [item.to_json() for item in self.evidence],
        }

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Candidate:
        return cls(
            name=record["name"],
            evidence=[Evidence.from_json(item) for item in record.get("evidence", [])],
            significant=bool(record.get("significant", False)),
            status=record.get("status", "not_significant"),
            decided_by=record.get("decided_by", ""),
            why=record.get("why", ""),
            parameters=dict(record.get("parameters") or {}),
        )


@dataclass
class Diagnosis:
    """diagnosis.json: where the gap lies, which causes it, how far it shrinks."""

    gap: dict[str, Any] = doc(
        "Held-out rmse, psnr, mse and per-view values (linear); noise_floor {a, b, floor_rmse, "
        "gap_above_floor}; relight (the relight split's gap, or why it is skipped); "
        "visibility_fingerprint {share (0..1), slope, interval (the slope's), coverage, "
        "correlation, placebo_quantile, excess, p_value, placebo_lights, names}; "
        "flat_field {corner_falloff, "
        "half_radius_falloff, deviation, allowance, frames, profile...} or flat_field_error; "
        "line_target {corner_shift_pixels, standard_error, parameters (k1, k2, p1, p2), "
        "straightness_before_pixels, straightness_after_pixels, lines, frames, allowance, z} or "
        "line_target_error; "
        "parameters.geometry {chamfer_l1, normal_consistency, f1@1%} against a ground truth; "
        "heldout_mse (with a refit mode: the held-out MSE the refits are measured against); "
        "how_far_relight_skipped when a pbr model's refits are measured on the held-out views "
        "only.",
        default_factory=dict,
    )
    where: dict[str, Any] = doc(
        "Per residual domain (image position, surface, view, intensity, light geometry, edges, "
        "frequency): {score, score_in_sample, summary}.",
        default_factory=dict,
    )
    candidates: list[Candidate] = doc(
        "Every candidate, best first (recon.diagnose.decision.rank_key).", default_factory=list
    )
    refits: list[dict[str, Any]] = doc(
        "How far: per refit {effects, before, after, floor, closed_fraction, confirmed, "
        "parameters, relight_* and geometry_* where measured}.",
        default_factory=list,
    )
    verdict: str = doc(
        "The significant causes in order, or 'no significant unmodelled effect'; then the "
        "candidates the data cannot identify.",
        default="",
    )
    confirmed_by_refit: list[str] = doc(
        "The refitted effects whose refit closed at least diagnose.confirming_share of the gap.",
        default_factory=list,
    )
    model: dict[str, Any] = doc(
        "The model the diagnosis started from: the fit's material, light frame and effects "
        "(not candidates: already modelled).",
        default_factory=dict,
    )
    settings: dict[str, Any] = doc(
        "The diagnose config section it was decided with (recon.config.run_config."
        "DiagnoseConfig), so a stored diagnosis can be re-decided and compared.",
        default_factory=dict,
    )
    timings: dict[str, Any] = doc(
        "diagnose_seconds, refit_seconds and per-stage seconds.", default_factory=dict
    )
    figures: dict[str, str] = doc(
        "Figure names to paths relative to the run folder.", default_factory=dict
    )
    schema_version: int = doc(
        "The JSON form's version (recon.diagnose.records.SCHEMA_VERSION).",
        default=SCHEMA_VERSION,
    )

    def candidate(self, name: str) -> Candidate | None:
        """The candidate of that name, or None."""
        return next((item for item in self.candidates if item.name == name), None)

    @property
    def significant(self) -> list[str]:
        """The significant candidates' names, best first."""
        return [item.name for item in self.candidates if item.significant]

    def to_json(self) -> dict[str, Any]:
        record = {item.name: getattr(self, item.name) for item in fields(self)}
        record["candidates"] = [candidate.to_json() for candidate in self.candidates]
        return record

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Diagnosis:
        from recon.errors import ReconError

        version = record.get("schema_version")
        if version is None and "ranking" in record:
            # Written before the typed records: its measurements become Evidence.
            from recon.diagnose.legacy import from_legacy

            return from_legacy(record)
        if version != SCHEMA_VERSION:
            raise ReconError(
                f"diagnosis.json: schema_version expected {SCHEMA_VERSION}, got {version} "
                "(diagnose the run again with this recon)"
            )
        known = {item.name for item in fields(cls)}
        values = {key: value for key, value in record.items() if key in known}
        values["candidates"] = [Candidate.from_json(item) for item in record["candidates"]]
        return cls(**values)
