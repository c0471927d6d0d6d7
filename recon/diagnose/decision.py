"""The decision rule as one table: which evidence makes a candidate significant, and how it ranks.

Every check of the diagnosis ends as ``recon.diagnose.records.Evidence`` on a ``Candidate``.
``decide`` reads only that evidence, the effect's diagnosis facts (recon.effects.facts) and the
allowances of ``DecisionConfig`` (config ``diagnose.decision``), so a stored diagnosis can be
re-decided with other allowances (``redecide``) and a new kind of check is one producer plus,
at most, one row here.

The rows (``DECISION_TABLE``), in the order they are consulted:

============  ============  =================================================================
kind          role          effect on the decision
============  ============  =================================================================
flat_field    overrule      measures the falloff itself: decides alone, either way
line_target   overrule      measures the lens itself (the plumb-line frames' corner shift,
                            above its allowance and line_target_z standard errors): decides
                            alone, either way (contradicting rows do not veto it)
probe         clear         held-out reduction's lower bound above its allowance: significant
                            (a geometric probe is voided beside a confuser an independent row
                            found, where on top of it it keeps no more than its beyond
                            allowance: _void_probe_beside_measured)
absorption    clear         the same for the absorption refit (unless voided; a refit that
                            moves the vertices, measured alone, is voided beside a confuser
                            its probe made significant: _void_beside_confusers)
relight       clear         the same for the relight split's probe; for an effect only the
                            relight split identifies (DiagnosisFacts.relight_exponent: under
                            one light the albedo absorbs a curve), an exponent measured there
                            that removes no error beyond the light's balance vetoes whatever
                            else cleared (the split shows no curve)
beyond_       clear         a geometric probe's least reduction on top of each confuser's
confusers                   probe above its allowance (derived again at every decision from
                            the specificity records; recon.diagnose.geometric_judgement); for
                            an effect no confuser can imitate (DiagnosisFacts.
                            distinct_from_confusers: a pose error), a least lower bound not
                            above 0 vetoes what its probe cleared
agreement     clear         a per-view colour gain shared by separate halves of each view
                            above its allowance, beyond permuted views (recon.diagnose.agreement);
                            its halves split the image position, intensity, n.h and n.v, so a
                            specificity veto in the domains whose splits agreed on their own
                            (below agreement_alpha) does not overturn it
lobe          clear         the view-to-view residual (training and held-out views) follows a
                            highlight's lobe under the fitted light beyond placebo lights
                            (recon.diagnose.lobe); ranks after clearing residual evidence
line_target_  clear         the response's exponent over the line target's two known levels
levels                      further from 1 than its allowance (the larger of the config's and
                            the card's contrast tolerance's) and line_target_z standard errors
                            over the frames (measured on other data: independent); read
                            so precisely that no curve the relight split could name fits it,
                            it vetoes what the held-out residual or the relight split cleared
                            (the card measures the camera on known radiances)
relight_lobe  clear         the same lobe test on the relight split under its known light
                            (recon.diagnose.lobe); measured on other data (independent)
cast_shadow   clear         the relight split's residual is darker where the fitted mesh
                            shadows the relight sun, beyond placebo directions
                            (recon.diagnose.cast_shadow); measured on other data than the
                            held-out residual (independent)
bounce        clear         the relight split's residual is brighter where the fitted mesh
                            bounces the relight sun's light (one diffuse bounce, less the
                            training light's the albedo absorbed), beyond placebo suns, with a
                            strength bounced light can have (recon.diagnose.bounce);
                            independent like cast_shadow
fingerprint   name          the fitted albedo is darker where the fitted mesh hides the fitted
                            light, beyond placebo lights (recon.diagnose.fingerprint); its
                            slope picks shadows or interreflection (ranks after the above)
null          raise bar     a failed null from the run (placebo, permutation, split half)
                            keeps the probe from making the candidate significant (the
                            other clearing rows still decide without it)
edge_blur     raise bar     the same for a blur probe whose blur the data's silhouette edges
                            do not show (at least edge_blur_minimum_ratio of the widening it
                            gives the render's edges; recon.diagnose.edge_width): its
                            reduction is the fit's silhouette misfit
specificity   veto          a failed check says the signature is not the candidate's: it is not
                            significant, and ``details["instead"]`` (a base-model mismatch
                            such as view_dependent_reflectance) is named in its place, with the
                            vetoed candidate's rank, when the vetoed one had cleared; a
                            candidate that also cleared on other data than the held-out
                            residual (flat_field, relight: ``Rule.independent``) is not
                            vetoed by it, whichever row decided;
                            a geometric check (details["pairs"]) is judged again with the
                            config's probe allowances, and applies only where the probe
                            clears (recon.diagnose.geometric_judgement)
identifiability  qualify    a failed check on a candidate that did not clear, or that cleared
                            and was vetoed by specificity or the backdrop alone: "not
                            identifiable from this data, because ..." (not a silent miss, nor
                            a claim that it is not there; the veto's mismatch is still named); on
                            one that cleared and whose condition names a confusable effect
                            (details["confused_with"]): significant but ambiguous, "A or B:
                            not separable from this data, because ..."; otherwise the
                            condition qualifies its why
metadata      veto          the capture's own record (EXIF exposure) disagrees with what the
                            candidate recovered, or (EXIF white-balance mode) says the camera
                            held its colour gains: the camera did not do it, so it is not named
                            (the gains are some other per-view change, e.g. the model's
                            mismatch); an agreeing record changes nothing
backdrop      veto          the static backdrop in the same frames does not show the per-view
                            gain the candidate (exposure, white balance) recovered on the
                            object (recon.diagnose.backdrop): a camera's gain scales the whole
                            frame, so the gain is the object's own change (its view-dependent
                            reflectance); a backdrop that shows it supplies the parameters
                            reported (read off the backdrop) and, measured on other pixels
                            than the object's residual (independent), keeps a specificity veto
                            from overturning the candidate its probe cleared. Where
                            the backdrop changes itself, an identifiability condition beside
                            the veto makes it "not identifiable" (as for specificity)
gain          inform        the exposure's per-view gains read apart from a highlight lobe
                            (recon.diagnose.camera_gain): the parameters it reports, before
                            the probe's
edges         inform        the data's silhouette edges widened as wide in every direction
                            (defocus) or wider across one direction per view (motion blur)
                            (recon.diagnose.edge_width): settles a tie of the two blurs'
                            probes in the geometric specificity check
============  ============  =================================================================

Evidence of a kind without a row is recorded and informs nothing.

The producer contract (how a new check plugs in, recon.diagnose.producers): a producer is
``producer(inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig) ->
list[Evidence]``; append it to ``recon.diagnose.producers.PRODUCERS``. Each Evidence names its
candidate (an effect or a mismatch; a mismatch candidate is created when first named), a kind
above, ``passed`` (for null, specificity and identifiability: whether the candidate survives the
check) and a one-line ``reason``; ``details["instead"]`` on a failed specificity check names the
mismatch, ``details["capture"]`` on a failed identifiability check the capture that would settle
it, and its ``details["settled_by"]`` the evidence kinds that measured that capture's answer (a
significant candidate for which one of them passed is not qualified by it). The table keeps the producer's ``threshold`` and ``passed`` for these kinds (only the built-in
rows are re-thresholded from ``DecisionConfig``).

Ranking (``rank_key``): significant first; then evidence from a held-out residual or a direct
measurement before the fingerprint alone; then by how far the residual evidence clears its own
allowance (the fingerprint: by its placebo excess). The ranks and verdicts on recon's own world are the
ones the hand-ordered rule gave before this table (tests/diagnose/test_decision.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal

from recon.config.run_config import DecisionConfig, DiagnoseConfig, LineTargetConfig
from recon.diagnose.geometric_judgement import (
    BEYOND,
    beyond_confusers,
    measured_condition,
    rejudge,
    with_edges_favour,
)
from recon.diagnose.identifiability import judge_expected_share
from recon.diagnose.line_target import card_exponent_allowance
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.effects.registry import diagnosis_facts

Role = Literal["overrule", "clear", "name", "null", "veto", "qualify", "inform"]
NOTHING_SIGNIFICANT = "no significant unmodelled effect"


def probe_threshold(effect: str, config: DecisionConfig) -> float:
    """The held-out reduction a probe's bootstrap lower bound must clear."""
    return max(config.minimum_share, config.probe_allowance.get(effect, config.minimum_share))


def absorption_threshold(effect: str, config: DecisionConfig) -> float:
    """The reduction over the control refit the absorption lower bound must clear (the
    closed-form evidence, a share of a smaller error, has its own floor)."""
    facts = diagnosis_facts(effect)
    closed_form = facts is not None and facts.absorption == "closed_form"
    floor = config.regression_minimum_share if closed_form else config.absorption_minimum_share
    return max(floor, config.absorption_allowance.get(effect, config.minimum_share))


def beyond_threshold(effect: str, config: DecisionConfig) -> float | None:
    """What a geometric probe must keep on top of every confuser's (floored); None for an effect
    without such an allowance (its records derive no "beyond_confusers" evidence)."""
    if effect not in config.beyond_confusers_allowance:
        return None
    return max(config.minimum_share, config.beyond_confusers_allowance[effect])


def agreement_threshold(effect: str, config: DecisionConfig) -> float:
    """The per-view colour spread an agreement evidence must clear (floored)."""
    return max(config.agreement_minimum, config.agreement_allowance.get(effect, 0.0))


def lobe_threshold(effect: str, config: DecisionConfig) -> float:
    """The partial correlation a lobe evidence must clear (floored)."""
    return max(config.lobe_minimum, config.lobe_allowance.get(effect, 0.0))


def _beats_placebos(alpha: Callable[[DecisionConfig], float]) -> Callable[..., bool]:
    """A rule's passes for a placebo-excess evidence (lobe, cast shadow): the statistic clears
    its threshold and the measured pattern beats its placebo directions at the level alpha."""

    def passes(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
        p_value = evidence.details.get("p_value", 1.0)
        return evidence.statistic > threshold and p_value < alpha(config)

    return passes


def _bounces(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
    """The relight residual follows the relight sun's bounce beyond placebo suns, with a
    strength that bounced light can have (above 0, at most bounce_maximum_strength)."""
    strength = evidence.details.get("strength", 0.0)
    placebo = _beats_placebos(lambda settings: settings.bounce_alpha)
    return placebo(evidence, threshold, config) and 0.0 < strength <= config.bounce_maximum_strength


def _agrees(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
    """The halves share a spread above the allowance, and more than permuted views do."""
    p_value = evidence.details.get("p_value", 1.0)
    return evidence.statistic > threshold and p_value < config.agreement_alpha


def _edges_show_blur(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
    """The data's silhouette edges show at least the threshold's share of the probe's blur."""
    return evidence.statistic >= threshold


def _lower_bound_clears(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
    return evidence.statistic > threshold


def _fingerprint_names(evidence: Evidence, threshold: float, config: DecisionConfig) -> bool:
    """The fingerprint names a candidate when it is testable (the fitted mesh shadows enough of
    the pixels, and the fitted light has a direction to turn), its partial correlation beats
    the placebo lights (excess above the threshold, p below fingerprint_alpha), and its slope
    falls on the candidate's side of the shadow share."""
    testable = evidence.details.get("coverage", 0.0) >= config.fingerprint_minimum_coverage
    statistic = evidence.statistic
    if not testable or statistic != statistic:
        return False
    if not (
        statistic > threshold and evidence.details.get("p_value", 1.0) < config.fingerprint_alpha
    ):
        return False
    side = "blocked" if evidence.details.get("slope", 0.0) >= config.shadow_share else "bounced"
    facts = diagnosis_facts(evidence.candidate)
    return facts is not None and facts.fingerprint_side == side


@dataclass(frozen=True)
class Rule:
    """One row of the decision table.

    kind: the Evidence kind it reads. role: see the module docstring.
    measured: whether evidence of this kind is a held-out residual or a direct measurement
        (ranks before evidence that is not).
    strength: whether its excess over the allowance counts toward the rank.
    threshold: the allowance from the config (None: keep the producer's threshold).
    passes: whether the evidence clears the allowance (None: keep the producer's passed).
    parameters_from: evidence kinds whose parameters are reported when this row decides, in
        order of preference.
    independent: whether it measures the effect on other data than the held-out residual
        (flat-field frames, the relight split under its own light, the static backdrop around
        the object): a specificity veto, a pattern of the held-out residual, does not overturn
        a candidate such evidence passed for (a veto row's passing: it showed the effect).
    settles: specificity domains (recon.diagnose.specificity) this evidence can test itself: a
        specificity veto whose failing domains (details["failing_domains"]) all lie among
        those it tested does not overturn a candidate this evidence passed for (whichever row
        decided it). The agreement splits each view's halves by image position, intensity,
        n.h and n.v; it records a p-value per domain (details["domain_p_values"]), and only
        the domains whose splits agreed on their own are settled (a pooled agreement can
        come from four splits while the fifth disagrees).
    outlives_null: whether it still decides when the probe's null from the run failed (the
        null tests the probe's claim; these rows measure on their own terms). The rows
        without it are the ones a failed null blocked before the null was measured for
        every probe that could clear (lobe, cast shadow: kept as they were).
    revise: judges a stored evidence again under the config when its verdict depends on the
        allowances in a way threshold and passes cannot say (the geometric specificity
        check compares two probes, each with its own allowance).
    contradicts: for evidence of this row that measured the candidate's own signature on
        data of its own and found none, the reason it vetoes whatever other row cleared the
        candidate (None: it does not contradict them). Relight: a tone curve shows only under
        a second light, so a relight split without one overrules a held-out probe.
    outweighs_independent: whether its contradiction also stands against another independent
        row that cleared the candidate (else such a row, measured on other data, overrules
        it): for a row that measures the camera itself on known radiances, where the other
        infers the effect through the fitted model (the card's levels against the relight
        split).
    """

    kind: str
    role: Role
    measured: bool = False
    strength: bool = False
    threshold: Callable[[str, DecisionConfig], float] | None = None
    passes: Callable[[Evidence, float, DecisionConfig], bool] | None = None
    parameters_from: tuple[str, ...] = ()
    independent: bool = False
    settles: tuple[str, ...] = ()
    revise: Callable[[Evidence, DecisionConfig], Evidence] | None = None
    outlives_null: bool = False
    contradicts: Callable[[Evidence], str | None] | None = None
    outweighs_independent: bool = False


def _rejudge_geometric(evidence: Evidence, config: DecisionConfig) -> Evidence:
    """A geometric specificity check judged again with the config's probe allowances (its pair
    records are stored); the gain-like checks keep their producer's verdict."""
    return rejudge(evidence, lambda effect: probe_threshold(effect, config))


def _rejudge_expected_share(evidence: Evidence, config: DecisionConfig) -> Evidence:
    """An identifiability condition judged by the share of the held-out error the effect's
    reference strength would remove (details["judged_against"] == "probe") judged again with
    the config's probe allowance; other conditions keep their producer's verdict."""
    if evidence.details.get("judged_against") != "probe":
        return evidence
    share = float(evidence.details["expected_share"])
    allowance = probe_threshold(evidence.candidate, config)
    return replace(
        judge_expected_share(evidence.candidate, share, allowance, evidence.details),
        void=evidence.void,
    )


def _judged_beyond_its_errors(allowance: Callable[[Evidence, DecisionConfig], float]):
    """Rule.revise for a measurement on calibration frames that carries its own standard error
    (details["standard_error"]; None: unknown): the statistic must clear the larger of the
    allowance and line_target_z standard errors (a null from the run: noisy or blurred frames
    raise it). details["precise"] records whether the errors alone stay within the allowance,
    so that a reading within it says "nothing there" rather than "too noisy to tell"."""

    def judge(evidence: Evidence, config: DecisionConfig) -> Evidence:
        error = evidence.details.get("standard_error")
        spread = config.line_target_z * (math.inf if error is None else float(error))
        least = allowance(evidence, config)
        threshold = max(least, spread)
        return replace(
            evidence,
            threshold=threshold,
            passed=bool(evidence.statistic > threshold),
            details={**evidence.details, "precise": bool(spread < least)},
        )

    return judge


def _card_allowance(evidence: Evidence) -> float:
    """How far from 1 the card's recorded contrast tolerance lets a linear camera read on row
    line_target_levels (evidence from before the card was recorded: the default card's)."""
    card = LineTargetConfig()
    dark_share = float(evidence.details.get("dark_share", card.dark_share))
    tolerance = float(evidence.details.get("contrast_tolerance", card.contrast_tolerance))
    return card_exponent_allowance(dark_share, tolerance)


def _levels_allowance(evidence: Evidence, config: DecisionConfig) -> float:
    """Row line_target_levels' allowance: the larger of the config's least one and the card's."""
    return max(config.line_target_levels_allowance, _card_allowance(evidence))


def _levels_judged(evidence: Evidence, config: DecisionConfig) -> Evidence:
    """Row line_target_levels judged again: beyond its errors and the card's allowance
    (_judged_beyond_its_errors), and whether the reading excludes every curve the relight split
    could name (details["precise"]): its distance from 1 plus line_target_z standard errors plus
    what the card's contrast leaves unknown (details["upper_bound"]) within the relight split's
    least compression (relight_allowance, the same exponent's distance from 1 under a power
    curve). A reading that excludes them says "no curve there", not "too noisy to tell"."""
    judged = _judged_beyond_its_errors(_levels_allowance)(evidence, config)
    error = evidence.details.get("standard_error")
    spread = config.line_target_z * (math.inf if error is None else float(error))
    bound = evidence.statistic + spread + _card_allowance(evidence)
    return replace(
        judged,
        details={
            **judged.details,
            "upper_bound": round(bound, 5) if math.isfinite(bound) else None,
            "precise": bool(bound <= config.relight_allowance),
        },
    )


def _levels_show_no_curve(evidence: Evidence) -> str | None:
    """Row line_target_levels' contradiction: the card's two levels keep their printed ratio
    so precisely that no curve the relight split could name fits the reading
    (details["precise"], _levels_judged): over that range the camera has no curve, and what the
    held-out residual or the relight split cleared is the fit's own misfit
    (Rule.outweighs_independent: the card measures the camera on two known radiances; the
    relight split infers a curve through the fitted surface's shading ratio, which unmodelled
    shadows and a pose error bend too). The card speaks for the range between its levels only:
    a curve that bends only beyond them is vetoed wrongly, which a card whose white reaches the
    object's highlights avoids."""
    if evidence.passed or not evidence.details.get("precise", False):
        return None
    gamma = (evidence.details.get("parameters") or {}).get("effective_gamma")
    bound = evidence.details.get("upper_bound")
    measured = f" (exponent {gamma:.3f})" if gamma is not None else ""
    excluded = f", no curve beyond {bound:.4f} of 1" if bound is not None else ""
    return (
        f"the line target's two levels keep their printed ratio{measured}{excluded}: the camera "
        "shows no response curve over them; what the held-out residual or the relight split "
        "removed is the fit's own misfit"
    )


def _relight_shows_no_curve(evidence: Evidence) -> str | None:
    """Row relight's contradiction: for an effect the relight split identifies
    (DiagnosisFacts.relight_exponent: a response curve, which under one light the albedo
    absorbs), the relight split is the one place its curve shows, the same surface under a
    second, known light. When the exponent fitted there removes no held-out error beyond the
    first light's balance (details["specific"] False), the split shows no curve, and what a
    held-out probe under the training light removed is the fit's own misfit (beside a strong
    exposure, texels at the albedo's ceiling bend the intensities; decision 0224)."""
    facts = diagnosis_facts(evidence.candidate)
    if facts is None or not facts.relight_exponent or evidence.details.get("specific", True):
        return None
    gamma = (evidence.details.get("parameters") or {}).get("gamma")
    measured = f" (its exponent {gamma:.2f} on the shading ratio)" if gamma is not None else ""
    return (
        f"the relight split, where a tone curve cannot hide in the albedo, shows none"
        f"{measured}: the exponent removes no held-out error beyond the fitted light's own "
        "balance; what the other evidence removed is the fit's own misfit"
    )


def _nothing_beyond_confusers(evidence: Evidence) -> str | None:
    """Row beyond_confusers' contradiction, for an effect distinct from its confusers
    (DiagnosisFacts.distinct_from_confusers: a pose error): what its probe removed, one
    confuser's probe removes as well (the least lower bound of what it keeps on top of one is
    not above 0), so its probe fitted the silhouettes' misfit that any warp or blur reduces,
    not a turn of the camera, which no confuser can imitate."""
    facts = diagnosis_facts(evidence.candidate)
    if facts is None or not facts.distinct_from_confusers or evidence.statistic > 0:
        return None
    confuser = evidence.details.get("confuser", "a confuser")
    return (
        f"on top of {confuser}'s probe it removes nothing with confidence (lower bound "
        f"{100 * evidence.statistic:.1f} %): its probe removed the fit's own misfit, which "
        f"{confuser} removes as well and a real {evidence.candidate} would not leave"
    )


DECISION_TABLE: tuple[Rule, ...] = (
    Rule(
        "flat_field",
        "overrule",
        measured=True,
        threshold=lambda effect, config: config.flat_field_allowance,
        passes=_lower_bound_clears,
        parameters_from=("absorption", "probe"),
        independent=True,
        outlives_null=True,
    ),
    Rule(
        "line_target",
        "overrule",
        measured=True,
        threshold=lambda effect, config: config.line_target_allowance,
        parameters_from=("line_target",),
        independent=True,
        outlives_null=True,
        revise=_judged_beyond_its_errors(lambda evidence, config: config.line_target_allowance),
    ),
    Rule(
        "probe",
        "clear",
        measured=True,
        strength=True,
        threshold=probe_threshold,
        passes=_lower_bound_clears,
        parameters_from=("backdrop", "gain", "probe"),
    ),
    Rule(
        "absorption",
        "clear",
        measured=True,
        strength=True,
        threshold=absorption_threshold,
        passes=_lower_bound_clears,
        parameters_from=("absorption", "probe"),
        outlives_null=True,
    ),
    Rule(
        "relight",
        "clear",
        measured=True,
        strength=True,
        threshold=lambda effect, config: config.relight_allowance,
        passes=_lower_bound_clears,
        parameters_from=("relight", "probe"),
        independent=True,
        outlives_null=True,
        contradicts=_relight_shows_no_curve,
    ),
    Rule(
        "line_target_levels",
        "clear",
        measured=True,
        threshold=lambda effect, config: config.line_target_levels_allowance,
        parameters_from=("line_target_levels", "relight"),
        independent=True,
        outlives_null=True,
        contradicts=_levels_show_no_curve,
        revise=_levels_judged,
        outweighs_independent=True,
    ),
    Rule(
        BEYOND,
        "clear",
        measured=True,
        strength=True,
        threshold=beyond_threshold,
        passes=_lower_bound_clears,
        parameters_from=("gain", "probe"),
        contradicts=_nothing_beyond_confusers,
    ),
    Rule(
        "agreement",
        "clear",
        measured=True,
        threshold=agreement_threshold,
        passes=_agrees,
        parameters_from=("backdrop", "probe"),
        settles=("image_position", "intensity", "n_dot_h", "n_dot_v"),
        outlives_null=True,
    ),
    Rule(
        "lobe",
        "clear",
        measured=True,
        threshold=lobe_threshold,
        passes=_beats_placebos(lambda config: config.lobe_alpha),
        parameters_from=("lobe", "absorption", "probe"),
    ),
    Rule(
        "relight_lobe",
        "clear",
        measured=True,
        threshold=lambda effect, config: max(
            lobe_threshold(effect, config), config.relight_lobe_minimum
        ),
        passes=_beats_placebos(lambda config: config.lobe_alpha),
        parameters_from=("relight_lobe", "lobe", "absorption", "probe"),
        independent=True,
    ),
    Rule(
        "cast_shadow",
        "clear",
        measured=True,
        threshold=lambda effect, config: config.cast_shadow_minimum,
        passes=_beats_placebos(lambda config: config.cast_shadow_alpha),
        parameters_from=("cast_shadow",),
        independent=True,
    ),
    Rule(
        "bounce",
        "clear",
        measured=True,
        threshold=lambda effect, config: config.bounce_minimum,
        passes=_bounces,
        parameters_from=("bounce",),
        independent=True,
    ),
    Rule(
        "fingerprint",
        "name",
        threshold=lambda effect, config: config.fingerprint_minimum,
        passes=_fingerprint_names,
        parameters_from=("probe",),
        outlives_null=True,
    ),
    Rule("null", "null"),
    Rule(
        "edge_blur",
        "null",
        threshold=lambda effect, config: config.edge_blur_minimum_ratio,
        passes=_edges_show_blur,
    ),
    Rule(
        "specificity",
        "veto",
        measured=True,
        parameters_from=("specificity", "probe"),
        revise=_rejudge_geometric,
    ),
    Rule("identifiability", "qualify", revise=_rejudge_expected_share),
    Rule("metadata", "veto"),
    # A backdrop that shows the object's per-view gain in the static frame around it measured
    # the camera's gain on other pixels than the object's residual: independent.
    Rule("backdrop", "veto", independent=True),
    Rule("gain", "inform"),
    Rule("edges", "inform"),
)
RULES: dict[str, Rule] = {rule.kind: rule for rule in DECISION_TABLE}
# Vetoes that say the recovered pattern is the base model's (the residual's profile, a gain the
# backdrop does not share) rather than what the camera recorded (metadata): with a failed
# identifiability condition beside them the answer is "not identifiable", not "not there".
PATTERN_VETOES = ("specificity", "backdrop")
# Whose parameters a candidate that nothing decided reports: the relight split's estimate when
# it has one (the one estimate of a response curve the albedo cannot absorb), else the exposure's
# highlight-free gains, else the probe's.
UNDECIDED_PARAMETERS = ("relight", "gain", "probe")


def rethreshold(evidence: Evidence, config: DecisionConfig) -> Evidence:
    """The evidence with its threshold and passed taken from the config (built-in rows only;
    a row with ``revise`` judges its stored records again)."""
    rule = RULES.get(evidence.kind)
    if rule is not None and rule.revise is not None:
        return rule.revise(evidence, config)
    if rule is None or rule.threshold is None or rule.passes is None:
        return evidence
    threshold = rule.threshold(evidence.candidate, config)
    return replace(
        evidence, threshold=threshold, passed=bool(rule.passes(evidence, threshold, config))
    )


def _parameters(candidate: Candidate, kinds: tuple[str, ...]) -> dict[str, Any]:
    for kind in kinds:
        evidence = candidate.evidence_of(kind)
        if evidence is not None and evidence.details.get("parameters"):
            return evidence.details["parameters"]
    return {}


def _role_evidence(candidate: Candidate, role: Role) -> list[Evidence]:
    return [
        item
        for item in candidate.evidence
        if item.counts and item.kind in RULES and RULES[item.kind].role == role
    ]


def _first_cleared(candidate: Candidate, skip: tuple[str, ...] = ()) -> Evidence | None:
    """The overruling evidence's verdict, else the first clearing row that passed, else the
    naming row (rows of the kinds in skip left out); None when nothing speaks for the
    candidate."""
    overruling = _role_evidence(candidate, "overrule")
    if overruling:
        return overruling[0] if overruling[0].passed else None
    for role in ("clear", "name"):
        for rule in DECISION_TABLE:
            if rule.role != role or rule.kind in skip:
                continue
            evidence = candidate.evidence_of(rule.kind)
            if evidence is not None and evidence.counts and evidence.passed:
                return evidence
    return None


def decide(candidate: Candidate, config: DecisionConfig) -> Candidate:
    """Decide one candidate in place from its evidence and the config; returns it."""
    candidate.evidence = with_edges_favour(candidate.evidence)
    candidate.evidence = [rethreshold(item, config) for item in candidate.evidence]
    allowance = beyond_threshold(candidate.name, config)
    candidate.evidence = beyond_confusers(
        candidate.evidence,
        lambda effect: probe_threshold(effect, config),
        None if allowance is None else (lambda effect: allowance),
    )
    candidate.evidence = measured_condition(candidate.evidence)
    probe_clears = any(
        item.counts and item.passed for item in candidate.evidence if item.kind in ("probe", BEYOND)
    )
    # (Measured for every probe that could clear: it matters where the probe clears.)
    failed_nulls = [
        item for item in _role_evidence(candidate, "null") if not item.passed and probe_clears
    ]
    # A null from the run tests the probe's claim (recon.diagnose.nulls): a failed one takes the
    # probe (and the rows without Rule.outlives_null) out, and the others decide without it.
    blocked_by_null = tuple(
        rule.kind
        for rule in DECISION_TABLE
        if rule.role in ("clear", "name") and not rule.outlives_null
    )
    skipped = blocked_by_null if failed_nulls else ()
    deciding = _first_cleared(candidate, skip=skipped)
    blocked = failed_nulls and deciding is None and _first_cleared(candidate) is not None
    if blocked:
        why = failed_nulls[0].reason
    elif deciding is None:
        why = _why_not(candidate)
    else:
        why = explain(deciding)
    status = "significant" if deciding is not None else "not_significant"
    vetoes = [item for item in _role_evidence(candidate, "veto") if not item.passed]
    independent = [
        item
        for role in ("overrule", "clear", "veto")
        for item in _role_evidence(candidate, role)
        if item.passed and RULES[item.kind].independent and item.kind not in skipped
    ]
    if deciding is not None and independent:
        # Measured on other data (flat-field frames, the relight split, the static backdrop
        # showing the per-view gain in the whole frame): the held-out residual's pattern
        # (specificity) does not overturn it, whichever passing row comes first in the table;
        # the capture's record does.
        vetoes = [item for item in vetoes if item.kind != "specificity"]
    if deciding is not None:
        # Any clearing evidence that passed and tests a domain itself settles a veto in it
        # (the probe may clear first, the agreement's halves still tested those domains).
        settled = {
            domain
            for item in _role_evidence(candidate, "clear")
            if item.passed
            for domain in _domains_tested(item, config)
        }
        settled |= set(_domains_tested(deciding, config))
        if settled:
            vetoes = [item for item in vetoes if not _settled(item, tuple(sorted(settled)))]
    if deciding is not None:
        # A row that found no signature where it looked (Rule.contradicts) vetoes what the
        # held-out residual cleared, not a measurement of another kind on other data.
        vetoes += [
            item
            for item in _contradictions(candidate, deciding)
            if RULES[item.kind].outweighs_independent
            or not any(other.kind != item.kind for other in independent)
        ]
    if vetoes and status == "significant":
        status, why = "vetoed", vetoes[0].reason
    # A capture that measures the effect itself (an overruling row the condition names as
    # settling it) answers the condition either way: found, or measured and not there.
    measured = {item.kind for item in _role_evidence(candidate, "overrule")}
    unidentifiable = [
        item
        for item in _role_evidence(candidate, "qualify")
        if not item.passed
        and not (
            status == "significant" and _settles(candidate, item.details.get("settled_by", ()))
        )
        and not measured & set(item.details.get("settled_by", ()))
    ]
    if unidentifiable:
        condition = unidentifiable[0]
        capture = condition.details.get("capture")
        settle = f"; {capture} would make it identifiable" if capture else ""
        confusable = _confusable(condition)
        if status == "vetoed" and all(item.kind in PATTERN_VETOES for item in vetoes):
            # Cleared, but its residual's pattern is also a mismatch's, and the data cannot
            # identify the effect anyway: neither "it is X" nor "it is not X" holds. (The
            # mismatch is still named in its place; a capture record's veto stays a veto.)
            status = "not_identifiable"
            why = (
                f"not identifiable from this data, because {condition.reason}{settle}; "
                f"and {vetoes[0].reason}"
            )
        elif status == "vetoed":
            pass  # the capture's record says the camera did not do it: that is the answer
        elif status != "significant":
            # A miss the data could not have avoided: say so instead of a silent miss.
            status = "not_identifiable"
            why = (
                f"not identifiable from this data, because {condition.reason}{settle}"
                f"{_probe_reading(candidate)}"
            )
        elif confusable is not None:
            # Cleared, but the data cannot tell it from a named effect: both are reported.
            status = "ambiguous"
            why = (
                f"{explain(deciding)}; {candidate.name} or {confusable}: not separable from "
                f"this data, because {condition.reason}{settle}"
            )
        else:
            # Cleared; the condition qualifies what was recovered (e.g. an extrapolation).
            measure = f"; {capture} would settle it" if capture else ""
            why = f"{explain(deciding)}; but {condition.reason}{measure}"
    candidate.status = status
    candidate.significant = status in ("significant", "ambiguous")
    candidate.decided_by = deciding.kind if candidate.significant else ""
    candidate.why = why
    kinds = RULES[deciding.kind].parameters_from if candidate.significant else ()
    candidate.parameters = _parameters(candidate, kinds or UNDECIDED_PARAMETERS)
    return candidate


def _probe_reading(candidate: Candidate) -> str:
    """What the candidate's probe recovered, for a verdict that cannot name it: "; its probe
    fits the held-out views with ..." (its first four scalar parameters and held-out reduction
    with its interval) where the interval's lower bound is above zero (a measurement the data
    supports but cannot attribute), "; its probe removes nothing beyond noise ..." where it is
    not, "; its " + the void where the decision voided it beside a confuser (VOIDED_BESIDE),
    or "" without a measured probe."""
    probe = candidate.evidence_of("probe")
    if probe is not None and VOIDED_BESIDE in probe.details:
        return f"; its {probe.void}"
    if probe is None or not probe.counts:
        return ""
    interval = probe.details.get("interval")
    reduction = probe.details.get("reduction")
    if not interval or reduction is None or math.isnan(reduction):
        return ""
    low, high = float(interval[0]), float(interval[1])
    if low <= 0.0:
        return f"; its probe removes nothing beyond noise (lower bound {100 * low:.2f} %)"
    scalars = [
        f"{name} {float(value):.3g}"
        for name, value in (probe.details.get("parameters") or {}).items()
        if isinstance(value, int | float)
    ][:4]
    fitted = f" with {', '.join(scalars)}" if scalars else ""
    return (
        f"; its probe fits the held-out views{fitted}, removing {100 * float(reduction):.2f} % "
        f"of their error ({100 * low:.2f} to {100 * high:.2f} %)"
    )


def _settles(candidate: Candidate, kinds: list[str] | tuple[str, ...]) -> bool:
    """Whether clearing evidence of one of the kinds passed: it measured the answer the
    condition predicts (whether or not its row is the one that decided)."""
    return any(
        item.counts and item.passed and RULES[item.kind].role == "clear"
        for item in candidate.evidence
        if item.kind in kinds and item.kind in RULES
    )


def _contradictions(candidate: Candidate, deciding: Evidence) -> list[Evidence]:
    """Vetoes from rows whose evidence measured the candidate's signature and found none
    (Rule.contradicts), other than the deciding row's own kind."""
    vetoes = []
    for item in candidate.evidence:
        rule = RULES.get(item.kind)
        if rule is None or rule.contradicts is None or not item.counts:
            continue
        if item.kind == deciding.kind:
            continue
        reason = rule.contradicts(item)
        if reason is not None:
            vetoes.append(replace(item, passed=False, reason=reason))
    return vetoes


def _domains_tested(evidence: Evidence, config: DecisionConfig) -> tuple[str, ...]:
    """The specificity domains the evidence tested itself: where it records a p-value per
    domain (details["domain_p_values"]: the agreement's splits), those below
    diagnose.decision.agreement_alpha; else its row's Rule.settles (records from before the
    evidence kept them)."""
    rule = RULES.get(evidence.kind)
    if rule is None:
        return ()
    recorded = evidence.details.get("domain_p_values")
    if recorded is None:
        return rule.settles
    return tuple(
        domain
        for domain in rule.settles
        if float(recorded.get(domain, 1.0)) < config.agreement_alpha
    )


def _settled(veto: Evidence, domains: tuple[str, ...]) -> bool:
    """Whether a failed specificity check failed only in domains the deciding evidence tested
    itself (a record without its failing domains is not settled)."""
    failing = veto.details.get("failing_domains")
    return veto.kind == "specificity" and bool(failing) and set(failing) <= set(domains)


def _confusable(condition: Evidence) -> str | None:
    """The first effect a failed identifiability condition names in details["confused_with"]
    (entries that are no effect, such as the albedo, are skipped), or None."""
    for name in condition.details.get("confused_with") or ():
        if diagnosis_facts(name) is not None:
            return name
    return None


def ambiguous_with(candidate: Candidate) -> str | None:
    """The effect an ambiguous candidate cannot be told from (None when it is not ambiguous)."""
    condition = candidate.evidence_of("identifiability")
    if candidate.status != "ambiguous" or condition is None:
        return None
    return _confusable(condition)


def _why_not(candidate: Candidate) -> str:
    """The closest miss: the built-in evidence with the largest excess (its reason says what it
    measured against what), or why there was none."""
    measured = [
        item
        for item in candidate.evidence
        if item.kind in RULES
        and RULES[item.kind].threshold is not None
        and RULES[item.kind].role in ("overrule", "clear", "name")
    ]
    if not measured:
        return "no evidence measured"
    overruling = [item for item in measured if item.counts and RULES[item.kind].role == "overrule"]
    if overruling:
        return explain(overruling[0])  # it decides alone
    voided = [item for item in measured if not item.counts]
    counted = [item for item in measured if item.counts]
    if not counted:
        return voided[0].void
    # (a statistic that could not be measured, NaN, says only its reason)
    numbers = [item for item in counted if item.statistic == item.statistic]
    if not numbers:
        return explain(counted[0])
    best = max(numbers, key=lambda item: item.statistic - item.threshold)
    return explain(best)


def explain(evidence: Evidence) -> str:
    """One line: the evidence's reason with its statistic against its threshold."""
    if evidence.threshold != evidence.threshold or evidence.statistic != evidence.statistic:
        return evidence.reason  # a condition (NaN threshold), not a comparison
    relation = "clears" if evidence.passed else "does not clear"
    return (
        f"{evidence.reason} {evidence.statistic:.3f} {relation} its allowance "
        f"{evidence.threshold:.3f}"
    )


def excess(candidate: Candidate) -> float:
    """How far the residual evidence clears its own allowance: the largest of the strength
    rows' lower bound minus threshold. Comparing raw reductions would favour the flexible
    probes (pose, blur), whose allowance is several times another's."""
    values = [
        item.statistic - item.threshold
        for item in candidate.evidence
        if item.counts and item.kind in RULES and RULES[item.kind].strength
    ]
    return max(values, default=float("-inf"))


def rank_key(candidate: Candidate) -> tuple:
    """Significant first; then held-out or direct evidence before the fingerprint alone (whose
    effect shows in no held-out residual); then by excess (the fingerprint: by its placebo excess). A
    mismatch named by a veto ranks where the vetoed candidate would have."""
    stand_in = candidate.evidence_of("specificity")
    if candidate.decided_by == "specificity" and stand_in is not None:
        return tuple(stand_in.details.get("rank", (True, True, 0.0)))
    deciding = RULES.get(candidate.decided_by)
    measured = deciding is not None and deciding.measured
    if candidate.decided_by == "fingerprint":
        strength = candidate.evidence_of("fingerprint").statistic
    else:
        strength = excess(candidate)
    return (candidate.significant, measured, strength)


def _name_mismatches(candidates: list[Candidate], config: DecisionConfig) -> list[Candidate]:
    """Mismatch candidates named by the vetoes: a failed specificity check with
    details['instead'] on a candidate that had cleared makes that mismatch significant in its
    place (ranked as the vetoed candidate would have been)."""
    by_name = {candidate.name: candidate for candidate in candidates}
    for candidate in list(candidates):
        cleared_by = _first_cleared(candidate)
        if candidate.status not in ("vetoed", "not_identifiable") or cleared_by is None:
            continue
        for veto in _role_evidence(candidate, "veto"):
            instead = veto.details.get("instead")
            if veto.passed or not instead:
                continue
            mismatch = by_name.get(instead)
            if mismatch is None:
                mismatch = by_name[instead] = Candidate(instead)
                candidates.append(mismatch)
            cleared = replace(candidate, significant=True, status="significant")
            rank = list(rank_key(replace(cleared, decided_by=cleared_by.kind)))
            mismatch.add(
                Evidence(
                    kind="specificity",
                    candidate=instead,
                    statistic=veto.statistic,
                    threshold=veto.threshold,
                    passed=True,
                    reason=f"{candidate.name}'s signature is {instead}'s: {veto.reason}",
                    details={**veto.details, "instead_of": candidate.name, "rank": rank},
                )
            )
            mismatch.status, mismatch.significant = "significant", True
            mismatch.decided_by, mismatch.why = "specificity", mismatch.evidence[-1].reason
            mismatch.parameters = veto.details.get("parameters", {})
    return candidates


def _derived(candidate: Candidate) -> bool:
    """A mismatch candidate that a veto named (re-derived at every decision)."""
    return diagnosis_facts(candidate.name) is None and candidate.decided_by == "specificity"


# details key of an absorption evidence voided by the decision itself (re-derived at every
# decision, unlike a void the diagnosis recorded when it measured the evidence).
VOIDED_BESIDE = "voided_beside"


def _restore_derived_voids(candidates: list[Candidate]) -> None:
    """Undo the voids an earlier decision derived (_void_beside_confusers): they hold only
    under the thresholds that made the confuser significant."""
    for candidate in candidates:
        candidate.evidence = [
            replace(
                item, void="", details={k: v for k, v in item.details.items() if k != VOIDED_BESIDE}
            )
            if VOIDED_BESIDE in item.details
            else item
            for item in candidate.evidence
        ]


def _void_beside_confusers(candidates: list[Candidate], config: DecisionConfig) -> None:
    """An absorption measured alone by a refit that moves the vertices (lens distortion's,
    DiagnosisFacts.absorption "geometry") does not count beside a significant confuser of the
    candidate that its probe found (a blur or a pose error, DiagnosisFacts.confusable): the
    fit bent that effect's misfit into the geometry too, and a distortion refit that moves the
    vertices takes part of it back (lower bounds of 0.04-0.14 on blurred teapots at 48 px).
    The diagnosis voids it when it measures with such an effect given (recon.diagnose.
    absorption); here the same holds whichever thresholds made the confuser significant, so
    that a stored diagnosis re-decided under another calibration is judged alike. The
    candidate is decided again on its other evidence (its probe, which the geometric
    specificity check compares with the confuser's)."""
    for candidate in candidates:
        facts = diagnosis_facts(candidate.name)
        absorption = candidate.evidence_of("absorption")
        if (
            facts is None
            or facts.absorption != "geometry"
            or absorption is None
            or not absorption.counts
            or absorption.details.get("conditional_on")
        ):
            continue
        beside = [
            other.name
            for other in candidates
            if other.name in facts.confusable
            and other.significant
            and other.decided_by in ("probe", BEYOND)
        ]
        if not beside:
            continue
        voided = replace(
            absorption,
            void=f"absorption measured alone: void beside {beside[0]}, which its probe found",
            details={**absorption.details, VOIDED_BESIDE: beside[0]},
        )
        candidate.evidence = [voided if item is absorption else item for item in candidate.evidence]
        decide(candidate, config)


def _void_probe_beside_measured(candidates: list[Candidate], config: DecisionConfig) -> None:
    """A probe that alone made a geometric candidate significant does not count where an
    independent measurement (a row measured on other data, Rule.independent: the line target's
    lens) made a confuser of it significant and the candidate's probe keeps no more than its
    beyond-confusers allowance on top of that confuser's probe (its specificity pair record):
    the confuser is established, and what the probe removes is the misfit the confuser left
    (a fit bent by an unmodelled lens leaves silhouettes that any blur smooths). A candidate
    its probe finds on top of the measured confuser as well stays. Derived again at every
    decision (the marker is undone by _restore_derived_voids)."""
    for candidate in candidates:
        facts = diagnosis_facts(candidate.name)
        probe = candidate.evidence_of("probe")
        allowance = beyond_threshold(candidate.name, config)
        check = next((item for item in candidate.evidence if item.kind == "specificity"), None)
        if (
            facts is None
            or allowance is None
            or probe is None
            or check is None
            or not candidate.significant
            or candidate.decided_by != "probe"
        ):
            continue
        records = {record["confuser"]: record for record in check.details.get("pairs", [])}
        measured = [
            other.name
            for other in candidates
            if other.name in facts.confusable
            and other.significant
            and other.decided_by in RULES
            and RULES[other.decided_by].independent
            and other.name in records
        ]
        beside = [
            name
            for name in measured
            if records[name]["on_top_of_confuser"]["interval"][0] <= allowance
        ]
        if not beside:
            continue
        on_top = records[beside[0]]["on_top_of_confuser"]["interval"][0]
        voided = replace(
            probe,
            void=(
                f"probe void beside {beside[0]}, which a measurement on other data found: on top "
                f"of its probe this one keeps {100 * on_top:.1f} % (lower bound), not above "
                f"{100 * allowance:.1f} %"
            ),
            details={**probe.details, VOIDED_BESIDE: beside[0]},
        )
        candidate.evidence = [voided if item is probe else item for item in candidate.evidence]
        decide(candidate, config)


def decide_all(candidates: list[Candidate], config: DecisionConfig) -> list[Candidate]:
    """Every candidate decided (mismatches named by vetoes and voids beside a confuser
    re-derived) and sorted best first; the list is changed in place and returned."""
    candidates[:] = [candidate for candidate in candidates if not _derived(candidate)]
    _restore_derived_voids(candidates)
    for candidate in candidates:
        decide(candidate, config)
    _void_beside_confusers(candidates, config)
    _void_probe_beside_measured(candidates, config)
    _name_mismatches(candidates, config)
    candidates.sort(key=rank_key, reverse=True)
    return candidates


def verdict_of(candidates: list[Candidate]) -> str:
    """The significant candidates in order (or that there is none; an ambiguous one as "A or
    B", with why the data cannot separate them), then the ones the data cannot identify."""
    significant = [
        f"{candidate.name} or {ambiguous_with(candidate)}"
        if ambiguous_with(candidate)
        else candidate.name
        for candidate in candidates
        if candidate.significant
    ]
    verdict = (
        "significant unmodelled effects: " + ", ".join(significant)
        if significant
        else NOTHING_SIGNIFICANT
    )
    for candidate in candidates:
        confusable = ambiguous_with(candidate)
        if confusable:
            condition = candidate.evidence_of("identifiability")
            verdict += (
                f"; {candidate.name} or {confusable}: not separable from this data, because "
                f"{condition.reason}"
            )
    unidentifiable = [item.name for item in candidates if item.status == "not_identifiable"]
    if unidentifiable:
        verdict += "; not identifiable from this data: " + ", ".join(unidentifiable)
    return verdict


def redecide(diagnosis: dict | Diagnosis, config: DiagnoseConfig | None = None) -> Diagnosis:
    """A stored diagnosis (diagnosis.json's dict or a Diagnosis) re-decided from its evidence
    with `config` (default: the settings it was decided with) and re-sorted; the evidence is
    kept, thresholds, verdicts and ranks recomputed. Returns a new Diagnosis whose settings
    are `config`'s. (Refits stay the ones that ran.)"""
    from recon.config import from_dict, to_dict

    record = diagnosis.to_json() if isinstance(diagnosis, Diagnosis) else diagnosis
    stored = Diagnosis.from_json(record)  # a copy
    if config is None:
        config = from_dict(stored.settings, DiagnoseConfig) if stored.settings else DiagnoseConfig()
    decide_all(stored.candidates, config.decision)
    stored.verdict = verdict_of(stored.candidates)
    stored.settings = to_dict(config)
    return stored
