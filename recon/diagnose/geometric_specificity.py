"""Specificity of the geometric and blur candidates: is a displacement or a blur its own?

The gain-like candidates have their check in recon.diagnose.specificity. Lens distortion,
motion blur, defocus blur and a pose error move or spread pixels instead of scaling them, and
their probes imitate each other: a lens-distortion probe resamples the image along a radial
field, which blurs it (bilinear interpolation of fractional shifts), so on a blurred capture it
removes part of the blur; a motion-blur kernel with a one-sided path shifts the image; a pose
correction moves it rigidly. Which one the capture holds shows in what each adds on top of the
other (the signature that is the candidate's own):

- a real lens distortion is one radial field for the camera: on top of a motion blur (whose
  per-view kernels cannot bend edges outward in proportion to the radius) it keeps a reduction;
- a motion blur is a per-view smear with no radial structure: on top of it a lens distortion
  has nothing left to remove, while the blur still removes error on top of the distortion.

The check, for each candidate T whose probe could clear under some calibration (its lower bound
above minimum_share, ``could_clear``) and each effect C it is most often confused with
(``CONFUSERS``; the issue's list: lens distortion named for a motion blur, a response curve or
interreflection; blurs and pose errors with spurious lens distortion): the probes of T and C
fitted jointly on the first half of each held-out view's pixel blocks (the probes' own
procedure, recon.diagnose.which.fit_on_halves), and on the second half, with bootstrap
intervals over views: what T removes on top of C alone, and what C removes on top of T alone.
T is vetoed in favour of C ("the signature is C's") when C alone clears its own allowance, T on
top of C does not clear T's, and what C adds on top of T is larger, with confidence, than what
T adds on top of C (C's lower bound above T's upper bound, by ``diagnose.geometric_specificity.
margin``). The allowances are the decision's probe allowances (diagnose.decision); no other
number is tuned. Evidence kind "specificity": the decision table's veto row.
"""

from __future__ import annotations

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.decision import probe_threshold
from recon.diagnose.geometric_judgement import KIND, dominated, judge, redundant, swapped
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.which import (
    EffectProbe,
    block_halves,
    bootstrap_reduction,
    fit_on_halves,
    probe_effect,
)

__all__ = ["KIND", "dominated", "redundant", "swapped"]

# Per candidate, the effects it is most often confused with (issue 20's confusions: a lens
# distortion named for a motion blur, a response curve or interreflection; defocus, exposure,
# pose and specular with a spurious lens distortion or motion blur). Only candidates moving or
# spreading pixels are checked here; the gain-like ones in recon.diagnose.specificity.
CONFUSERS: dict[str, tuple[str, ...]] = {
    "lens_distortion": (
        "motion_blur",
        "defocus_blur",
        "pose_error",
        "response_curve",
        "interreflection",
    ),
    "motion_blur": ("lens_distortion", "pose_error", "defocus_blur"),
    "defocus_blur": ("motion_blur", "lens_distortion", "pose_error"),
    "pose_error": ("motion_blur", "lens_distortion"),
}


def _alone(probe: EffectProbe, name: str) -> torch.Tensor:
    """Per-view held-out error sums [B] of one effect's probe alone (cached by the probe)."""
    errors = probe.heldout_errors.get(name)
    if errors is None:
        data = probe.data
        errors = fit_on_halves([probe_effect(name, data.view_count, data.observed.device)], probe)[
            0
        ]
        probe.heldout_errors[name] = errors
    return errors


def _base(probe: EffectProbe) -> torch.Tensor:
    """Per-view held-out error sums [B] of the model without any probe."""
    data = probe.data
    batch, height, width, _ = data.observed.shape
    _, second = block_halves(
        batch, height, width, data.observed.device, probe.settings.block_pixels
    )
    weight = second * data.region
    with torch.no_grad():
        squared = (probe.base_output.color - data.observed) ** 2 * weight
    return squared.sum(dim=(1, 2, 3))


def _reduction(before: torch.Tensor, after: torch.Tensor, settings: DiagnoseConfig) -> dict:
    reduction, (low, high) = bootstrap_reduction(before, after, settings.bootstrap_samples)
    return {"reduction": reduction, "interval": [low, high]}


def pair_record(
    name: str, confuser: str, probe: EffectProbe, base: torch.Tensor, settings: DiagnoseConfig
) -> dict:
    """What the candidate and a confuser each remove alone and on top of the other (held-out
    reductions with bootstrap intervals over views) and their probe allowances."""
    data = probe.data
    # Cached on the probe under the pair's joined names: the pair's other member checks it too.
    pair = sorted((name, confuser))
    key = "+".join(pair)
    joint = probe.heldout_errors.get(key)
    if joint is None:
        modules = [probe_effect(item, data.view_count, data.observed.device) for item in pair]
        joint = probe.heldout_errors[key] = fit_on_halves(modules, probe)[0]
    own, other = _alone(probe, name), _alone(probe, confuser)
    return {
        "candidate": name,
        "confuser": confuser,
        "alone": _reduction(base, own, settings),
        "confuser_alone": _reduction(base, other, settings),
        "on_top_of_confuser": _reduction(other, joint, settings),
        "confuser_on_top": _reduction(own, joint, settings),
        "allowance": probe_threshold(name, settings.decision),
        "confuser_allowance": probe_threshold(confuser, settings.decision),
    }


def geometric_evidence(
    name: str,
    probe: EffectProbe,
    settings: DiagnoseConfig,
    confusers: list[str],
    probe_lower_bound: float | None = None,
) -> Evidence:
    """The specificity Evidence of one geometric candidate against the confusers given
    (recon.diagnose.geometric_judgement.judge; probe_lower_bound: the candidate's probe lower
    bound, recorded so the decision judges the check only where the probe clears)."""
    base = _base(probe)
    records = [pair_record(name, confuser, probe, base, settings) for confuser in confusers]
    return judge(name, records, settings.geometric_specificity.margin, probe_lower_bound)


def could_clear(evidence: Evidence | None, settings: DiagnoseConfig) -> bool:
    """Whether a probe's lower bound clears the least allowance any calibration can set (the
    decision's minimum_share, the floor of every probe allowance): the checks of its claim run
    for it, so a calibration other than the code's (a leave-one-scene-out one, a user's
    config) that names it finds them in the stored evidence and judges them with its own
    allowances (recon.diagnose.geometric_judgement.rejudge)."""
    return (
        evidence is not None
        and evidence.counts
        and evidence.statistic > settings.decision.minimum_share
    )


def geometric_specificity(
    probe: EffectProbe,
    candidates: list[Candidate],
    settings: DiagnoseConfig,
    names: set[str] | None = None,
) -> list[Evidence]:
    """Specificity Evidence for every geometric candidate (CONFUSERS; only those in names when
    given) whose probe could clear (``could_clear``), against the confusers among the probed
    candidates. Whether the check applies (the probe clears its allowance) and whether it
    passes is judged with the decision's allowances, again at every re-decision."""
    if not settings.geometric_specificity.enabled or probe.data.view_count < 2:
        return []
    probed = {candidate.name for candidate in candidates if candidate.evidence_of("probe")}
    evidence = []
    for candidate in candidates:
        if candidate.name not in CONFUSERS:
            continue
        probe_evidence = candidate.evidence_of("probe")
        if not could_clear(probe_evidence, settings):
            continue
        if names is not None and candidate.name not in names:
            continue
        confusers = [name for name in CONFUSERS[candidate.name] if name in probed]
        if confusers:
            evidence.append(
                geometric_evidence(
                    candidate.name, probe, settings, confusers, probe_evidence.statistic
                )
            )
    return evidence
