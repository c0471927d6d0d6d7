"""The diagnosis's second opinion on its ranking: nulls from the run, specificity, capture
metadata and identifiability (issue 20, items 2, 3, 4 and 6), as one call.

run_checks takes the ranked candidates (what the probes and the other evidence decided), the
held-out views and what is known about the capture, and returns every Evidence with the vetoes
it implies:

- null (recon.diagnose.nulls): a candidate made significant by its probe must also clear the
  placebo null of this run (effects of its size that mean nothing); else it is vetoed.
- specificity (recon.diagnose.specificity): a significant gain-like candidate whose gain follows
  a confusable domain is vetoed; a base-model mismatch it names (view-dependent reflectance, a
  light that turns with the camera) becomes part of the verdict ("the base model cannot
  represent ...").
- metadata (recon.diagnose.metadata_check): with EXIF exposure known, a recovered exposure that
  does no better than equal exposure in every view is vetoed.
- identifiability (recon.diagnose.identifiability): reported ("not identifiable from this data,
  because ..."), never a veto here: whether it overrides other evidence is the decision rule's.

The decision stays a short list of rules in apply_rules, so the evidence engine can take the
Evidence as is and replace the rules with its table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from recon.diagnose.data import DiagnosisData
from recon.diagnose.identifiability import (
    CaptureConditions,
    IdentifiabilityOptions,
    identifiability_evidence,
)
from recon.diagnose.metadata_check import MetadataOptions, metadata_evidence
from recon.diagnose.nulls import NullOptions, null_evidence, split_half_evidence
from recon.diagnose.records import Evidence
from recon.diagnose.specificity import (
    CAMERA_FIXED_LIGHT,
    SIGNATURES,
    VIEW_DEPENDENT_REFLECTANCE,
    SpecificityOptions,
    specificity_evidence,
)

# What the base model cannot represent (verdicts that are not catalogue effects).
MISMATCHES = (VIEW_DEPENDENT_REFLECTANCE, CAMERA_FIXED_LIGHT)


@dataclass(frozen=True)
class CheckOptions:
    """The options of every check (each movable to the `diagnose:` config section)."""

    specificity: SpecificityOptions = field(default_factory=SpecificityOptions)
    nulls: NullOptions = field(default_factory=NullOptions)
    identifiability: IdentifiabilityOptions = field(default_factory=IdentifiabilityOptions)
    metadata: MetadataOptions = field(default_factory=MetadataOptions)


@dataclass(frozen=True)
class CandidateState:
    """What the ranking says of one candidate, as the checks need it.

    name: the effect; significant: decided so far; decided_by: the evidence that decided it
    ("probe", "absorption", ...; "" when none); reduction, interval: the probe's held-out
    reduction and its bootstrap interval; parameters: the probe's recovered parameters.
    """

    name: str
    significant: bool
    decided_by: str
    reduction: float
    interval: tuple[float, float]
    parameters: dict = field(default_factory=dict)


@dataclass
class CheckReport:
    """Every Evidence the checks produced, and what it implies for the verdict."""

    evidence: list[Evidence] = field(default_factory=list)
    vetoed: dict[str, str] = field(default_factory=dict)  # candidate -> the failed reason
    mismatches: list[dict[str, Any]] = field(default_factory=list)
    not_identifiable: list[dict[str, Any]] = field(default_factory=list)

    def for_candidate(self, name: str) -> list[dict]:
        return [item.to_json() for item in self.evidence if item.candidate == name]

    def to_json(self) -> dict:
        return {
            "vetoed": dict(self.vetoed),
            "mismatches": list(self.mismatches),
            "not_identifiable": list(self.not_identifiable),
            "evidence": [item.to_json() for item in self.evidence],
        }

    def verdict(self, significant: list[str]) -> str:
        """The verdict: significant effects, the base model's mismatches, or neither."""
        parts = []
        if significant:
            parts.append("significant unmodelled effects: " + ", ".join(significant))
        if self.mismatches:
            names = ", ".join(item["name"] for item in self.mismatches)
            parts.append(f"the base model cannot represent: {names}")
        return "; ".join(parts) if parts else "no significant unmodelled effect"


def run_checks(
    candidates: list[CandidateState],
    data: DiagnosisData,
    conditions: CaptureConditions | None = None,
    known_exposure: torch.Tensor | None = None,
    options: CheckOptions | None = None,
) -> CheckReport:
    """Every check's Evidence for the ranked candidates and the vetoes they imply.

    data: the held-out views; conditions: what the capture holds (relight, flat field, EXIF);
    known_exposure: the per-view gains [B] the recovered exposure should equal up to scale
    (EXIF exposure, or ones when the images were already divided by it), or None."""
    options = options or CheckOptions()
    conditions = conditions or CaptureConditions()
    report = CheckReport()
    by_name = {candidate.name: candidate for candidate in candidates}

    for candidate in candidates:
        if candidate.significant and candidate.decided_by == "probe":
            evidence = null_evidence(
                data, candidate.name, candidate.reduction, candidate.interval, options.nulls
            )
            report.evidence.append(evidence)
            if not evidence.passed:
                report.vetoed[candidate.name] = evidence.reason
        agreement = split_half_evidence(data, candidate.name, options.nulls)
        if agreement is not None and candidate.significant:
            report.evidence.append(agreement)

    significant = {c.name for c in candidates if c.significant and c.name not in report.vetoed}
    gain_like = [name for name in by_name if name in SIGNATURES]
    for evidence in specificity_evidence(data, gain_like, options.specificity, significant):
        report.evidence.append(evidence)
        if evidence.candidate in significant and not evidence.passed:
            report.vetoed.setdefault(evidence.candidate, evidence.reason)
        if evidence.candidate in MISMATCHES and evidence.passed:
            report.mismatches.append(
                {
                    "name": evidence.candidate,
                    "from": evidence.details.get("from"),
                    "reason": evidence.reason,
                }
            )

    exposure = by_name.get("exposure")
    ratios = (exposure.parameters or {}).get("ratios") if exposure else None
    if known_exposure is not None and ratios is not None and len(ratios) == len(known_exposure):
        evidence = metadata_evidence(ratios, known_exposure, "exposure", options.metadata)
        report.evidence.append(evidence)
        if exposure.significant and not evidence.passed:
            report.vetoed.setdefault("exposure", evidence.reason)

    for evidence in identifiability_evidence(data, conditions, options.identifiability):
        report.evidence.append(evidence)
        if not evidence.passed:
            report.not_identifiable.append({"name": evidence.candidate, "reason": evidence.reason})
    return report


def capture_facts(
    dataset: Path, split: str, dataset_options: Any, has_relight: bool, has_flat_field: bool
) -> tuple[CaptureConditions, torch.Tensor | None]:
    """What the capture holds besides the views (for run_checks): relight split and flat field
    as the diagnosis found them, and the EXIF exposure of the split's images when every one
    has it (ones when the dataset was read with dataset.exposure 'exif': the images are then
    already divided by it)."""
    from recon.diagnose.metadata_check import exif_exposure_gains
    from recon.io.datasets import read_captures

    captures = read_captures(dataset, split, dataset_options)
    gains = exif_exposure_gains(captures.metadata)
    known = gains
    if gains is not None and getattr(dataset_options, "exposure", "none") == "exif":
        known = torch.ones_like(gains)
    conditions = CaptureConditions(
        relight=has_relight, exposure_gains=gains, flat_field=has_flat_field
    )
    return conditions, known


def apply_checks(
    ranking: list,
    data: DiagnosisData,
    conditions: CaptureConditions | None = None,
    known_exposure: torch.Tensor | None = None,
    options: CheckOptions | None = None,
) -> CheckReport:
    """run_checks on a ranking of candidate records (recon.diagnose.which.CandidateResult or
    anything with effect, significant, evidence, heldout_reduction, interval and parameters),
    with its vetoes applied in place: a vetoed candidate is no longer significant and its
    evidence reads "vetoed". Returns the report (to store beside the ranking)."""
    states = [
        CandidateState(
            name=candidate.effect,
            significant=bool(candidate.significant),
            decided_by=candidate.evidence,
            reduction=float(candidate.heldout_reduction),
            interval=(float(candidate.interval[0]), float(candidate.interval[1])),
            parameters=candidate.parameters or {},
        )
        for candidate in ranking
    ]
    report = run_checks(states, data, conditions, known_exposure, options)
    for candidate in ranking:
        if candidate.effect in report.vetoed and candidate.significant:
            candidate.significant = False
            candidate.evidence = "vetoed"
    return report
