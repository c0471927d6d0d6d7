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

The check, for each candidate T that cleared and each effect C it is most often confused with
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
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.which import (
    EffectProbe,
    block_halves,
    bootstrap_reduction,
    fit_on_halves,
    probe_effect,
)

KIND = "specificity"

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


def _excess(entry: dict, allowance: float) -> float:
    return entry["interval"][0] - allowance


def swapped(record: dict) -> dict:
    """The pair record seen from the confuser's side."""
    return {
        **record,
        "confuser": record.get("candidate"),
        "alone": record["confuser_alone"],
        "confuser_alone": record["alone"],
        "on_top_of_confuser": record["confuser_on_top"],
        "confuser_on_top": record["on_top_of_confuser"],
        "allowance": record["confuser_allowance"],
        "confuser_allowance": record["allowance"],
    }


def redundant(record: dict, margin: float) -> bool:
    """Whether the pair cannot be told apart and the confuser explains more: both clear alone,
    neither clears its allowance on top of the other, neither takes the other's place
    (``dominated``), and the confuser alone clears its allowance by more than the candidate
    alone (one cause suffices; the stronger is named)."""
    if dominated(swapped(record), margin):
        return False
    confuser_excess = _excess(record["confuser_alone"], record["confuser_allowance"])
    own_excess = _excess(record["alone"], record["allowance"])
    neither_adds = (
        _excess(record["on_top_of_confuser"], record["allowance"]) <= 0
        and _excess(record["confuser_on_top"], record["confuser_allowance"]) <= 0
    )
    return confuser_excess > 0 and own_excess > 0 and neither_adds and confuser_excess > own_excess


def dominated(record: dict, margin: float) -> bool:
    """Whether the confuser takes the candidate's place: it clears its own allowance alone, the
    candidate on top of it does not clear the candidate's, and the confuser adds more on top of
    the candidate than the candidate adds on top of it (lower bound above upper bound + margin)."""
    confuser_clears = record["confuser_alone"]["interval"][0] > record["confuser_allowance"]
    candidate_adds = record["on_top_of_confuser"]["interval"][0] > record["allowance"]
    separated = (
        record["confuser_on_top"]["interval"][0]
        > record["on_top_of_confuser"]["interval"][1] + margin
    )
    return confuser_clears and not candidate_adds and separated


def _percent(entry: dict) -> str:
    low, high = entry["interval"]
    return f"{100 * entry['reduction']:.1f} % ({100 * low:.1f} to {100 * high:.1f})"


def _kept_because(name: str, record: dict) -> str:
    """Why the confuser of the least clear pair does not take the candidate's place."""
    confuser, on_top = record["confuser"], record["on_top_of_confuser"]
    if _excess(on_top, record["allowance"]) > 0:
        return (
            f"on top of every confuser it still clears its allowance (least: on top of "
            f"{confuser}, {_percent(on_top)} of the held-out error)"
        )
    if _excess(record["confuser_alone"], record["confuser_allowance"]) <= 0:
        return (
            f"on top of {confuser} it removes {_percent(on_top)}, but {confuser} alone "
            f"({_percent(record['confuser_alone'])}) does not clear its own allowance "
            f"{100 * record['confuser_allowance']:.1f} %, so it cannot take its place"
        )
    return (
        f"on top of {confuser} it removes {_percent(on_top)}, {confuser} on top of it "
        f"{_percent(record['confuser_on_top'])}: not separable, and {name} alone explains "
        f"as much or more ({_percent(record['alone'])} against "
        f"{_percent(record['confuser_alone'])})"
    )


def geometric_evidence(
    name: str, probe: EffectProbe, settings: DiagnoseConfig, confusers: list[str]
) -> Evidence:
    """The specificity Evidence of one geometric candidate against the confusers given."""
    options = settings.geometric_specificity
    base = _base(probe)
    records = [pair_record(name, confuser, probe, base, settings) for confuser in confusers]
    details = {"pairs": records}
    losing = [record for record in records if dominated(record, options.margin)]
    tied = [
        record for record in records if record not in losing and redundant(record, options.margin)
    ]
    if not losing and tied:
        stronger = max(
            tied, key=lambda record: _excess(record["confuser_alone"], record["confuser_allowance"])
        )
        confuser = stronger["confuser"]
        details["alternative"] = confuser
        reason = (
            f"{name} and {confuser} are not separable here (on top of each other they remove "
            f"{_percent(stronger['on_top_of_confuser'])} and {_percent(stronger['confuser_on_top'])}"
            f", neither clearing its allowance), and {confuser} alone explains more "
            f"({_percent(stronger['confuser_alone'])} against {_percent(stronger['alone'])}): "
            f"one cause suffices, {confuser}"
        )
        statistic = stronger["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, stronger["allowance"], False, reason, details)
    if not losing:
        closest = min(
            records,
            key=lambda record: _excess(record["on_top_of_confuser"], record["allowance"]),
        )
        reason = f"{name} is specific: " + _kept_because(name, closest)
        statistic = closest["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, closest["allowance"], True, reason, details)
    # The confuser that leaves the candidate least.
    worst = min(losing, key=lambda record: record["on_top_of_confuser"]["reduction"])
    confuser = worst["confuser"]
    details["alternative"] = confuser
    reason = (
        f"on top of {confuser} (alone {_percent(worst['confuser_alone'])}), {name} removes only "
        f"{_percent(worst['on_top_of_confuser'])} of the held-out error, while {confuser} on "
        f"top of {name} removes {_percent(worst['confuser_on_top'])}: the signature is "
        f"{confuser}'s, not {name}'s"
    )
    statistic = worst["on_top_of_confuser"]["interval"][0]
    return Evidence(KIND, name, statistic, worst["allowance"], False, reason, details)


def geometric_specificity(
    probe: EffectProbe,
    candidates: list[Candidate],
    settings: DiagnoseConfig,
    names: set[str] | None = None,
) -> list[Evidence]:
    """Specificity Evidence for every significant geometric candidate (CONFUSERS; only those
    in names when given) whose probe cleared, against the confusers among the probed
    candidates."""
    if not settings.geometric_specificity.enabled or probe.data.view_count < 2:
        return []
    probed = {candidate.name for candidate in candidates if candidate.evidence_of("probe")}
    evidence = []
    for candidate in candidates:
        if candidate.name not in CONFUSERS or not candidate.significant:
            continue
        probe_evidence = candidate.evidence_of("probe")
        if probe_evidence is None or not (probe_evidence.counts and probe_evidence.passed):
            # Cleared by other evidence (an absorption refit sees a distortion the fit bent into
            # the geometry, which the probes cannot): the probes' comparison does not speak to it.
            continue
        if names is not None and candidate.name not in names:
            continue
        confusers = [name for name in CONFUSERS[candidate.name] if name in probed]
        if confusers:
            evidence.append(geometric_evidence(candidate.name, probe, settings, confusers))
    return evidence
