"""The geometric specificity checks as evidence producers (recon.diagnose.producers).

- geometric_specificity_producer: every cleared lens distortion, motion blur, defocus blur and
  pose error against the effects it is most often confused with
  (recon.diagnose.geometric_specificity); a failed check vetoes it (decision row
  "specificity").
- restore_unconditioned_producer: a candidate the others were measured on top of
  (recon.diagnose.which.conditional_probes) that a check then vetoed is no longer a cause, so
  the others' probes on top of it no longer apply: their probes alone come back (with the
  placebo null a probe alone gets, recon.diagnose.checks.null_producer). Without it, a motion
  blur whose lens-distortion imitation was vetoed would stay measured on top of that
  imitation and go unnamed.
"""

from __future__ import annotations

from copy import deepcopy
from typing import TYPE_CHECKING

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.decision import RULES, decide
from recon.diagnose.geometric_specificity import geometric_specificity
from recon.diagnose.records import Candidate, Evidence

if TYPE_CHECKING:  # producers imports this module to register the checks
    from recon.diagnose.producers import EvidenceInputs


def geometric_specificity_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Specificity of the cleared geometric candidates against their confusers."""
    return geometric_specificity(inputs.probe, candidates, settings)


def _vetoed(candidate: Candidate, settings: DiagnoseConfig) -> bool:
    """Whether the decision, with the evidence gathered so far, vetoes the candidate (decided
    on a copy: the decision table says which evidence a veto overturns). A veto on data that
    cannot identify the candidate reads "not identifiable" (recon.diagnose.decision): it is
    no cause either, so it counts as vetoed here."""
    if not any(
        RULES.get(item.kind) and RULES[item.kind].role == "veto" for item in candidate.evidence
    ):
        return False
    decided = decide(deepcopy(candidate), settings.decision)
    if decided.status == "vetoed":
        return True
    failed_veto = any(
        item.counts and item.kind in RULES and RULES[item.kind].role == "veto" and not item.passed
        for item in decided.evidence
    )
    return decided.status == "not_identifiable" and failed_veto


def restore_unconditioned_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The probes alone of the candidates measured on top of a vetoed candidate, with the
    placebo null of those that clear alone."""
    from recon.diagnose.checks import null_producer

    vetoed = {candidate.name for candidate in candidates if _vetoed(candidate, settings)}
    if not vetoed:
        return []
    evidence: list[Evidence] = []
    restored_candidates: dict[str, Candidate] = {}
    for candidate in candidates:
        probe = candidate.evidence_of("probe")
        if probe is None or probe.details.get("conditional_on") not in vetoed:
            continue
        alone = probe.details.get("alone")
        if not alone:
            continue
        restored = Evidence.from_json(alone)
        restored.details["restored"] = (
            f"measured alone again: {probe.details['conditional_on']}, which it had been "
            "measured on top of, is vetoed"
        )
        evidence.append(restored)
        copy = deepcopy(candidate)
        copy.add(restored)
        copy.evidence = [item for item in copy.evidence if item.kind != "null"]
        decide(copy, settings.decision)
        evidence.extend(null_producer(inputs, [copy], settings))
        restored_candidates[copy.name] = copy
    if restored_candidates:
        # Cleared alone, they face the same specificity check as the others did.
        merged = [restored_candidates.get(item.name, item) for item in candidates]
        evidence.extend(
            geometric_specificity(inputs.probe, merged, settings, set(restored_candidates))
        )
    return evidence


GEOMETRIC_PRODUCERS = [geometric_specificity_producer, restore_unconditioned_producer]
