"""Issue 20's checks as evidence producers (recon.diagnose.producers): nulls from the run,
specificity, identifiability and capture metadata.

Each producer is ``producer(inputs, candidates, settings) -> list[Evidence]`` and runs after the
built-in evidence; the decision table (recon.diagnose.decision) says what each kind does:

- agreement (recon.diagnose.agreement): a per-view colour gain (white_balance) shared by
  separate halves of each view clears the candidate even where it is a small share of a large
  misfit (a local colour misfit differs between the halves).

- null (recon.diagnose.nulls): for every candidate whose probe could clear under some
  calibration (its lower bound above minimum_share), the probe's held-out reduction against
  placebo effects of its size on this run (and, for the per-view gains, split-half
  agreement); a failed one keeps the probe from clearing where it clears.
- specificity (recon.diagnose.specificity): a gain-like candidate whose gain follows a
  confusable domain is vetoed; details["instead"] names the base-model mismatch (e.g.
  view_dependent_reflectance) when that domain is a mismatch's and the held-out pixels agree.
- identifiability (recon.diagnose.identifiability): a tone curve with no second intensity of any
  surface point, a falloff measured short of the corners or absorbable by the albedo, a lens
  distortion a per-view pose correction reproduces (judged at its recovered size when it
  cleared), a directional blur with edges one way only, a defocus of the reference radius
  that would not clear its probe's allowance over the fit's own misfit, a white balance whose change from view
  to view hides in the fit's per-view colour noise: details["capture"] says what would
  settle it; the decision makes a miss "not identifiable from this data, because ..." and a
  cleared candidate confusable with a named effect ambiguous.
- backdrop (recon.diagnose.backdrop): a per-view gain (exposure, white balance) recovered on the
  object against the same views' static backdrop, where the photos have one: a gain the
  backdrop does not show is not the camera's (a veto); where the backdrop changes itself, the
  camera's gain is hidden by the object's own change (an identifiability condition).
- metadata (recon.diagnose.metadata_check): the recovered exposure against EXIF exposure when
  every held-out view has it, or against equal gains when the images were already divided by
  it (dataset.exposure 'exif'); a disagreement vetoes exposure (the camera's own record says it was not the exposure).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.agreement import agreement_evidence
from recon.diagnose.backdrop import (
    GAIN_CANDIDATES,
    backdrop_condition,
    backdrop_evidence,
    object_log_gains,
    read_backdrop,
)
from recon.diagnose.camera_gain import gain_evidence
from recon.diagnose.decision import DECISION_TABLE, probe_threshold
from recon.diagnose.geometric_specificity import could_clear
from recon.diagnose.identifiability import (
    CaptureConditions,
    defocus_blur_evidence,
    lens_distortion_evidence,
    motion_blur_evidence,
    response_curve_evidence,
    vignetting_evidence,
    white_balance_evidence,
)
from recon.diagnose.metadata_check import (
    exif_exposure_gains,
    metadata_evidence,
    white_balance_record_evidence,
)
from recon.diagnose.nulls import null_evidence, split_half_evidence
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.specificity import SIGNATURES, specificity_evidence
from recon.effects.registry import MODEL_EFFECTS

if TYPE_CHECKING:  # producers imports this module to register the checks
    from recon.diagnose.producers import EvidenceInputs


def agreement_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Agreement of the per-view colour gain between separate halves of each view, for the
    candidates with an agreement allowance (white_balance)."""
    names = {candidate.name for candidate in candidates}
    return [
        agreement_evidence(inputs.data, name, settings)
        for name in settings.decision.agreement_allowance
        if name in names
    ]


def null_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Placebo nulls (and split-half agreement of per-view gains) for the candidates whose
    probe could clear under any calibration (its lower bound above the floor of every probe
    allowance, recon.diagnose.geometric_specificity.could_clear): a calibration that names it
    finds its null in the stored evidence. A failed null takes only the probe out of the
    decision (recon.diagnose.decision), so it is measured whatever else cleared."""
    evidence = []
    for candidate in candidates:
        probe = candidate.evidence_of("probe")
        if candidate.name not in MODEL_EFFECTS or not could_clear(probe, settings):
            continue
        interval = probe.interval or (probe.statistic, probe.statistic)
        reduction = float(probe.details.get("reduction", interval[0]))
        evidence.append(null_evidence(inputs.data, candidate.name, reduction, interval, settings))
        agreement = split_half_evidence(inputs.data, candidate.name, settings)
        if agreement is not None:
            evidence.append(agreement)
    return evidence


def specificity_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Specificity of the gain-like candidates against their confusable domains. A candidate
    that a direct measurement decides (flat-field frames measure a falloff itself) is not
    checked: its residual signature is not what names it."""
    names = [
        candidate.name
        for candidate in candidates
        if candidate.name in SIGNATURES and not _measured_directly(candidate)
    ]
    if not names:  # (specificity_evidence reads an empty list as "every signature")
        return []
    significant = {candidate.name for candidate in candidates if candidate.significant}
    return specificity_evidence(inputs.data, names, settings, significant)


def _measured_directly(candidate: Candidate) -> bool:
    """Whether the candidate has evidence of a kind that overrules the rest (decision table)."""
    overruling = {rule.kind for rule in DECISION_TABLE if rule.role == "overrule"}
    return any(item.kind in overruling for item in candidate.evidence)


def _exposure_gains(inputs: EvidenceInputs):
    metadata = inputs.heldout.metadata if inputs.heldout is not None else None
    return exif_exposure_gains(metadata)


def identifiability_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Identifiability of the candidates whose identifiability the capture decides."""
    names = {candidate.name for candidate in candidates}
    options = settings.identifiability
    flat_field = any(candidate.evidence_of("flat_field") for candidate in candidates)
    conditions = CaptureConditions(
        relight=inputs.relight is not None,
        exposure_gains=_exposure_gains(inputs),
        flat_field=flat_field,
    )
    evidence = []
    by_name = {candidate.name: candidate for candidate in candidates}
    if "response_curve" in names:
        evidence.append(_as_condition(response_curve_evidence(inputs.data, conditions, options)))
    if "vignetting" in names:
        # Corner coverage and regions seen at one radius (flat-field frames settle both).
        evidence.append(_as_condition(vignetting_evidence(inputs.data, conditions, options)))
    if "lens_distortion" in names:
        shift, radial = _recovered_distortion(by_name["lens_distortion"])
        evidence.append(
            _as_condition(lens_distortion_evidence(inputs.data, options, shift, radial))
        )
    if "motion_blur" in names:
        evidence.append(_as_condition(motion_blur_evidence(inputs.data, options)))
    if "defocus_blur" in names:
        allowance = probe_threshold("defocus_blur", settings.decision)
        explained = _strongest_other_probe(candidates, "defocus_blur")
        condition = defocus_blur_evidence(inputs.data, options, allowance, explained)
        evidence.append(_as_condition(condition))
    agreement = (
        by_name["white_balance"].evidence_of("agreement") if "white_balance" in names else None
    )
    if agreement is not None and agreement.details.get("too_few_views"):
        condition = white_balance_evidence(
            math.inf, math.nan, int(agreement.details["views"]), options
        )
        evidence.append(_as_condition(condition))
    elif agreement is not None and "detectable" in agreement.details:
        # Judged by the smallest per-view change the agreement's test names on this data (the
        # fit's per-view colour noise); a change it found at least that large was identified.
        condition = white_balance_evidence(
            float(agreement.details["detectable"]),
            float(agreement.details["noise"]),
            int(agreement.details.get("views", 0)),
            options,
            found=float(agreement.statistic) if agreement.passed else None,
        )
        evidence.append(_as_condition(condition))
    return evidence


def _strongest_other_probe(candidates: list[Candidate], name: str) -> float:
    """The largest held-out reduction (point estimate, alone) of the other candidates' probes:
    the part of the misfit that is another effect's, not the fit's own."""
    best = 0.0
    for candidate in candidates:
        probe = candidate.evidence_of("probe")
        if candidate.name == name or probe is None or not probe.counts:
            continue
        alone = probe.details.get("alone")
        details = (
            alone.get("details", {})
            if probe.details.get("conditional_on") and alone
            else probe.details
        )
        best = max(best, float(details.get("reduction") or 0.0))
    return best


def _recovered_distortion(
    candidate: Candidate,
) -> tuple[float | None, tuple[float, float] | None]:
    """(corner displacement in pixels, (k1, k2)) of the distortion a significant
    lens_distortion candidate recovered (its absorption's or probe's parameters), to judge that
    distortion against a pose correction by its flow over the object (its corner shift is an
    extrapolation, reported only); (None, None) for one that did not clear (then the condition
    judges the reference strength: whether even a strong distortion would hide in a pose
    error). A record without k1 is judged by its corner shift alone. A probe whose null from
    this run passed (it removes more than placebo fields of its size) measured a distortion
    too: that one is judged, not the reference (a 7 px one is not a 3 px one)."""
    null = candidate.evidence_of("null")
    measured = null is not None and null.counts and null.passed
    if not (candidate.significant or measured):
        return None, None
    for kind in ("absorption", "probe"):
        item = candidate.evidence_of(kind)
        parameters = (item.details.get("parameters") or {}) if item is not None else {}
        if parameters.get("corner_shift_px") is not None:
            shift = float(parameters["corner_shift_px"])
            if parameters.get("k1") is None:
                return shift, None
            return shift, (float(parameters["k1"]), float(parameters.get("k2") or 0.0))
    return None, None


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
        capture = capture.removesuffix(" would settle it").rstrip(", ")
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


def gain_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The exposure's per-view gains read apart from a highlight lobe (recon.diagnose.camera_gain):
    the exposure's recovered parameters."""
    if not any(candidate.name == "exposure" for candidate in candidates):
        return []
    return [gain_evidence(inputs.data, settings)]


def metadata_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The recovered exposure against the held-out views' EXIF exposure, and a white balance
    against their EXIF white-balance mode, where they have them.

    The gains compared are the ones the exposure reports: read apart from the highlight (the
    gain evidence) where that ran, else the probe's."""
    evidence = []
    if any(candidate.name == "white_balance" for candidate in candidates):
        metadata = inputs.heldout.metadata if inputs.heldout is not None else None
        recorded = white_balance_record_evidence(metadata)
        evidence += [recorded] if recorded is not None else []
    return evidence + _exposure_metadata(inputs, candidates, settings)


def _exposure_metadata(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The metadata producer's exposure part: [] without EXIF exposure or an exposure reading."""
    known = _exposure_gains(inputs)
    exposure = next((item for item in candidates if item.name == "exposure"), None)
    source, ratios = _reported_exposure_ratios(exposure) if exposure is not None else ("", None)
    if known is None or ratios is None or len(ratios) != len(known):
        return []
    if len(known) < settings.metadata.minimum_views:
        # A correlation across views needs several views; a run with one or two held-out views
        # (a small capture) has no metadata evidence, which is not an error.
        return []
    # With dataset.exposure 'exif' the held-out images were already divided by these gains:
    # the exposure left to recover is none, so equal gains are the truth to compare with.
    divided = inputs.heldout.known_gains is not None
    if divided:
        known = torch.ones_like(known)
    evidence = metadata_evidence(ratios, known, "exposure", settings.metadata, divided=divided)
    evidence.details["recovered_from"] = source
    return [evidence]


def _reported_exposure_ratios(exposure: Candidate) -> tuple[str, list[float] | None]:
    """The evidence kind and per-view ratios [B] the exposure candidate reports (decision
    table: the gain evidence informs the parameters before the probe's); ("", None) when
    neither measured them."""
    for kind in ("gain", "probe"):
        evidence = exposure.evidence_of(kind)
        ratios = (evidence.details.get("parameters") or {}).get("ratios") if evidence else None
        if ratios is not None:
            return kind, ratios
    return "", None


def backdrop_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The per-view gains recovered on the object (exposure: the ratios it reports; white
    balance: its probe's gains) against the held-out views' static backdrop, where the photos
    have one (CaptureSet.frames)."""
    gained = [candidate for candidate in candidates if candidate.name in GAIN_CANDIDATES]
    heldout = inputs.heldout
    if not gained or heldout is None or heldout.frames is None:
        return []
    reading = read_backdrop(heldout.frames, heldout.masks, settings.backdrop)
    if reading is None:
        return []
    evidence = []
    for candidate in gained:
        if candidate.name == "exposure":
            ratios = _reported_exposure_ratios(candidate)[1]
            parameters = {"ratios": ratios} if ratios is not None else {}
        else:
            probe = candidate.evidence_of("probe")
            parameters = (probe.details.get("parameters") or {}) if probe is not None else {}
        recovered = object_log_gains(candidate.name, parameters)
        if recovered is None:
            continue
        found = backdrop_evidence(candidate.name, recovered, reading, settings.backdrop)
        if found is None:
            continue
        condition = backdrop_condition(found, reading, settings.backdrop)
        evidence += [found] if condition is None else [found, condition]
    return evidence


CHECK_PRODUCERS = [
    agreement_producer,
    null_producer,
    specificity_producer,
    identifiability_producer,
    gain_producer,
    metadata_producer,
    backdrop_producer,
]
