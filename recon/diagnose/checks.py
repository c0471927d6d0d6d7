"""Issue 20's checks as evidence producers (recon.diagnose.producers): nulls from the run,
specificity, identifiability and capture metadata.

Each producer is ``producer(inputs, candidates, settings) -> list[Evidence]`` and runs after the
built-in evidence; the decision table (recon.diagnose.decision) says what each kind does:

- null (recon.diagnose.nulls): for a candidate that only its probe made significant, the
  probe's held-out reduction against placebo effects of its size on this run (and, for the
  per-view gains, split-half agreement); a failed one keeps the probe from clearing.
- specificity (recon.diagnose.specificity): a gain-like candidate whose gain follows a
  confusable domain is vetoed; details["instead"] names the base-model mismatch (e.g.
  view_dependent_reflectance) when that domain is a mismatch's and the held-out pixels agree.
- identifiability (recon.diagnose.identifiability): a tone curve with no second intensity of any
  surface point, a falloff the albedo can absorb, a directional blur with edges one way only:
  "not identifiable from this data, because ..." with details["capture"] (what would settle it).
- metadata (recon.diagnose.metadata_check): the recovered exposure against EXIF exposure when
  every held-out view has it (informs the verdict, never decides it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.identifiability import (
    CaptureConditions,
    IdentifiabilityOptions,
    motion_blur_evidence,
    radius_spread,
    response_curve_evidence,
)
from recon.diagnose.metadata_check import exif_exposure_gains, metadata_evidence
from recon.diagnose.nulls import NullOptions, null_evidence, split_half_evidence
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.specificity import SIGNATURES, SpecificityOptions, specificity_evidence
from recon.effects.registry import MODEL_EFFECTS

if TYPE_CHECKING:  # producers imports this module to register the checks
    from recon.diagnose.producers import EvidenceInputs

# Clearing evidence besides the probe: a candidate they made significant is not the probe's
# claim, so the probe's null does not apply to it.
OTHER_CLEARING = ("absorption", "relight", "flat_field", "fingerprint")


def _cleared(candidate: Candidate, kind: str) -> bool:
    evidence = candidate.evidence_of(kind)
    return evidence is not None and evidence.counts and evidence.passed


def null_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Placebo nulls (and split-half agreement of per-view gains) for the candidates whose
    probe alone clears its allowance."""
    options = NullOptions(block_pixels=settings.block_pixels)
    evidence = []
    for candidate in candidates:
        probe = candidate.evidence_of("probe")
        if candidate.name not in MODEL_EFFECTS or probe is None or not _cleared(candidate, "probe"):
            continue
        if any(_cleared(candidate, kind) for kind in OTHER_CLEARING):
            continue
        interval = probe.interval or (probe.statistic, probe.statistic)
        reduction = float(probe.details.get("reduction", interval[0]))
        evidence.append(null_evidence(inputs.data, candidate.name, reduction, interval, options))
        agreement = split_half_evidence(inputs.data, candidate.name, options)
        if agreement is not None:
            evidence.append(agreement)
    return evidence


def specificity_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Specificity of the gain-like candidates against their confusable domains."""
    names = [candidate.name for candidate in candidates if candidate.name in SIGNATURES]
    significant = {candidate.name for candidate in candidates if candidate.significant}
    options = SpecificityOptions(
        block_pixels=settings.block_pixels, bootstrap_samples=settings.bootstrap_samples
    )
    return specificity_evidence(inputs.data, names, options, significant)


def _exposure_gains(inputs: EvidenceInputs):
    metadata = inputs.heldout.metadata if inputs.heldout is not None else None
    return exif_exposure_gains(metadata)


def identifiability_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Identifiability of the candidates whose identifiability the capture decides."""
    names = {candidate.name for candidate in candidates}
    options = IdentifiabilityOptions()
    flat_field = any(candidate.evidence_of("flat_field") for candidate in candidates)
    conditions = CaptureConditions(
        relight=inputs.relight is not None,
        exposure_gains=_exposure_gains(inputs),
        flat_field=flat_field,
    )
    evidence = []
    if "response_curve" in names:
        evidence.append(_as_condition(response_curve_evidence(inputs.data, conditions, options)))
    if "vignetting" in names and not flat_field:
        spread = radius_spread(inputs.data, options)
        if spread < options.minimum_radius_spread:
            evidence.append(
                Evidence(
                    "identifiability",
                    "vignetting",
                    spread,
                    options.minimum_radius_spread,
                    False,
                    "each surface region is seen at nearly one distance from the image centre "
                    f"in every view (median spread {spread:.2f} of the half diagonal), so the "
                    "albedo absorbs any falloff",
                    {
                        "radius_spread": spread,
                        "capture": "flat-field frames, or views with the object moving across "
                        "the image",
                    },
                )
            )
    if "motion_blur" in names:
        evidence.append(_as_condition(motion_blur_evidence(inputs.data, options)))
    return evidence


def _as_condition(evidence: Evidence) -> Evidence:
    """The identifiability module's Evidence in the decision's form: a failed one's reason is
    the "because" part and details["capture"] what would settle it."""
    if evidence.passed:
        return evidence
    reason = evidence.reason
    because = reason.split(", because ", 1)[1] if ", because " in reason else reason
    capture = None
    if "; " in because and because.endswith("would settle it"):
        because, capture = because.rsplit("; ", 1)
        capture = capture.removesuffix(" would settle it")
    details = dict(evidence.details)
    if capture:
        details["capture"] = capture
    return Evidence(
        evidence.kind,
        evidence.candidate,
        evidence.statistic,
        evidence.threshold,
        False,
        because,
        details,
    )


def metadata_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The recovered exposure against the held-out views' EXIF exposure, when they have it."""
    known = _exposure_gains(inputs)
    exposure = next((item for item in candidates if item.name == "exposure"), None)
    probe = exposure.evidence_of("probe") if exposure is not None else None
    ratios = (probe.details.get("parameters") or {}).get("ratios") if probe else None
    if known is None or ratios is None or len(ratios) != len(known):
        return []
    return [metadata_evidence(ratios, known, "exposure")]


CHECK_PRODUCERS = [null_producer, specificity_producer, identifiability_producer, metadata_producer]
