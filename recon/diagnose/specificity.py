"""Specificity: before a gain-like camera effect is named, its signature must be its own.

An exposure is one gain per view that is the same in every surface region, normal direction,
intensity and image position of that view. The base model's mismatch can look like one: a
diffuse model of a glossy object leaves, in each view, a residual that follows the highlight
(n.h against the light, the surface under it), and a per-view gain absorbs part of it because
views differ in how much highlight they show. The two differ in what the gain follows.

The check (recon.diagnose.pixel_table): additive log-gain models on the held-out pixel blocks.
The candidate's own term (one gain per view for exposure) removes some error on held-out pixels
alone (E_base - E_own); the same term is added again on top of a confusable domain's common
profile (one gain per bin of n.h, surface region, intensity or image position, shared by the
views), and what it still removes (E_domain - E_domain+own) is its retained share. A real
exposure keeps its whole reduction whatever else is modelled (its gains are per view, not per
bin); a per-view gain made of highlight composition loses it to the n.h profile. The share
and its bootstrap interval over views are the statistic: no tuned allowance, only the
retained-share bar (a majority of the reduction survives) in the `diagnose.specificity` config.
An F-test on all pixels (the gain against its scatter across the domain's bins) also speaks,
but it cannot overrule held-out pixels that keep most of the reduction with confidence
(domain_explains; docs/decisions/0222-blind-unseen-draws.md).

Producers here return recon.diagnose.records.Evidence of kind "specificity": a failed one
vetoes its candidate, and details["instead"] names the base-model mismatch (e.g.
view_dependent_reflectance) that explains it, which the decision table names in its place.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from scipy import stats

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.pixel_table import GainModels, PixelTable, Term, pixel_table
from recon.diagnose.records import Evidence
from recon.effects.registry import diagnosis_facts

KIND = "specificity"

# Base-model mismatches the diagnosis can name (they are not effects the forward model can add;
# "the base model cannot represent X").
VIEW_DEPENDENT_REFLECTANCE = "view_dependent_reflectance"
CAMERA_FIXED_LIGHT = "camera_fixed_light"
MISMATCHES = (VIEW_DEPENDENT_REFLECTANCE, CAMERA_FIXED_LIGHT)

DOMAIN_WORDS = {
    "n_dot_h": "n.h",
    "n_dot_v": "n.v",
    "surface": "the surface region",
    "intensity": "the rendered intensity",
    "image_position": "the image position",
    "radius": "the distance from the image centre",
    "camera_normal": "the normal in camera axes",
}


@dataclass(frozen=True)
class Signature:
    """What a gain-like candidate's gain follows and what it is confused with.

    own: the candidate's model terms (e.g. (("view",),): one gain per view).
    base: terms every compared model has (the albedo x light gauge per channel, and for
        effects other than exposure a per-view gain, so an exposure does not pollute them).
    confusers: conditioning domain -> the candidate named instead when the gain follows that
        domain's common profile (None: vetoed, nothing named).
    names_alternative: whether a failed check names the confuser (a positive Evidence for
        it). Only a per-view gain's confusions name one: a global curve or falloff explained
        by another domain is vetoed, but what explains it is a guess.
    """

    own: tuple[Term, ...]
    base: tuple[Term, ...]
    confusers: dict[str, str | None]
    names_alternative: bool = False


# Not against the surface region: a per-view gain explained by a common surface profile would
# be made of which regions each view shows, but with few views each region is seen by a subset
# of them, so a region profile is confounded with the per-view gains themselves (a real
# exposure on the 4-view blind benchmark fails that F-test, p = 0.08) and it names nothing.
_PER_VIEW_CONFUSERS: dict[str, str | None] = {
    "n_dot_h": VIEW_DEPENDENT_REFLECTANCE,
    "n_dot_v": CAMERA_FIXED_LIGHT,
    "intensity": "response_curve",
    "image_position": "vignetting",
}

# Per candidate: its gain's signature (the diagnosis facts of the gain-like effects). Geometric
# effects (distortion, blurs, pose) move pixels rather than scale them and are not checked here.
SIGNATURES: dict[str, Signature] = {
    "exposure": Signature(
        own=(("view",),),
        base=(("channel",),),
        confusers=dict(_PER_VIEW_CONFUSERS),
        names_alternative=True,
    ),
    "white_balance": Signature(
        own=(("view", "channel"),),
        base=(("channel",), ("view",)),
        confusers=dict(_PER_VIEW_CONFUSERS),
        names_alternative=True,
    ),
    # Not against the surface: under one light a tone curve is a per-texel change the albedo
    # absorbs (recon.diagnose.identifiability says so); a surface profile would always veto it.
    "response_curve": Signature(
        own=(("intensity",),),
        base=(("channel",), ("view",)),
        confusers={"image_position": "lens_distortion", "radius": "vignetting"},
    ),
    "vignetting": Signature(
        own=(("radius",),),
        base=(("channel",), ("view",)),
        confusers={"intensity": "response_curve", "surface": "shadows"},
    ),
    "shadows": Signature(
        own=(("surface", "channel"),),
        base=(("channel",), ("view",)),
        confusers={"image_position": "lens_distortion"},
    ),
    "interreflection": Signature(
        own=(("surface", "channel"),),
        base=(("channel",), ("view",)),
        confusers={"image_position": "lens_distortion"},
    ),
    "specular": Signature(
        own=(("n_dot_h", "channel"),),
        base=(("channel",), ("view",)),
        confusers={"surface": "shadows"},
    ),
}


def share_interval(
    gained: torch.Tensor, reference: torch.Tensor, settings: DiagnoseConfig
) -> tuple[float, float, float]:
    """sum(gained) / sum(reference) over per-view values [B] and its bootstrap interval over
    views (resampling views keeps each view's pixels together: they share one exposure)."""
    gained, reference = gained.double(), reference.double()
    share = float(gained.sum() / reference.sum())
    generator = torch.Generator().manual_seed(settings.specificity.seed)
    count = gained.shape[0]
    picks = torch.randint(0, count, (settings.bootstrap_samples, count), generator=generator)
    sampled = gained[picks].sum(1) / reference[picks].sum(1)
    sampled = torch.nan_to_num(sampled, nan=0.0, posinf=0.0, neginf=0.0)
    tail = (1 - settings.specificity.interval) / 2
    low, high = torch.quantile(sampled, torch.tensor([tail, 1 - tail], dtype=sampled.dtype))
    return share, float(low), float(high)


def view_covariate_slope(table: PixelTable, models: GainModels, domain: str) -> dict | None:
    """How the per-view log gains (one gain per view, fitted on the first half) follow the
    view's mean covariate (weighted by rendered energy): slope per unit with its standard
    error and the correlation over views; None for a domain with no numeric covariate."""
    if domain not in table.values:
        return None
    gains = models.view_log_gains([("channel",), ("view",)])
    weight = (table.rendered**2).sum(dim=1)
    total = torch.zeros(table.view_count, dtype=torch.float64)
    norm = torch.zeros(table.view_count, dtype=torch.float64)
    total.index_add_(0, table.view, table.values[domain].double() * weight)
    norm.index_add_(0, table.view, weight)
    seen = norm > 0
    x, y = (total / norm.clamp_min(1e-30))[seen], gains[seen]
    if x.numel() < 3 or float(x.std()) <= 1e-12:
        return None
    xc, yc = x - x.mean(), y - y.mean()
    slope = float((xc * yc).sum() / (xc * xc).sum())
    residual = yc - slope * xc
    error = float((residual.pow(2).sum() / (x.numel() - 2) / (xc * xc).sum()).sqrt())
    correlation = float(
        (xc * yc).sum() / ((xc * xc).sum() * (yc * yc).sum()).sqrt().clamp_min(1e-30)
    )
    return {"slope": slope, "slope_error": error, "correlation": correlation}


# Confusers of a gain tied to the image when the fit's light turns with the camera (a turntable
# capture): such a light's shading and highlights follow the normal in camera axes, and with the
# object held at the image centre they land at the same image radii in every view. A falloff is
# one gain per radius whatever the normal there; the object's mismatch under that light is not.
# (The fitted light's own direction cannot stand in for it: a diffuse fit of a glossy object puts
# its light where the diffuse shading wants it; the untouched real capture's points up from
# below while its highlights sit on the crown.)
_CAMERA_LIGHT_CONFUSERS: dict[str, dict[str, str | None]] = {
    "vignetting": {
        "camera_normal": VIEW_DEPENDENT_REFLECTANCE,
        "n_dot_v": VIEW_DEPENDENT_REFLECTANCE,
    },
}


def _confusers(name: str, signature: Signature, data: DiagnosisData) -> dict[str, str | None]:
    confusers = dict(signature.confusers)
    if data.lighting.frame == "camera":
        if confusers.get("n_dot_v") == CAMERA_FIXED_LIGHT:
            # The fit already turns its light with the camera: n.v is then a highlight's angle.
            confusers["n_dot_v"] = VIEW_DEPENDENT_REFLECTANCE
        confusers.update(_CAMERA_LIGHT_CONFUSERS.get(name, {}))
    return confusers


def f_test(
    models: GainModels, base: list[Term], own: list[Term], domain: str
) -> tuple[float, float, int, int]:
    """Whether the candidate's own term stands out above its interaction with a domain.

    On the cells' log gains (all pixels): base + the domain's profile, plus the own term, plus
    the own term x domain interaction (the own gain differing from bin to bin). F is the own
    term's mean square over the interaction's: a real exposure is one gain per view far above
    how the per-view gains scatter between bins; a highlight's composition is no larger than
    that scatter. Returns (F, p-value, numerator and denominator degrees of freedom)."""
    conditioned = base + [(domain, "channel")]
    interaction = [term + (domain,) for term in own]
    without, rank_without = models.residual_sum(conditioned)
    with_own, rank_own = models.residual_sum(conditioned + own)
    full, rank_full = models.residual_sum(conditioned + own + interaction)
    numerator_df, denominator_df = rank_own - rank_without, rank_full - rank_own
    if numerator_df <= 0 or denominator_df <= 0:
        return float("nan"), 1.0, numerator_df, denominator_df
    numerator = (without - with_own) / numerator_df
    denominator = max((with_own - full) / denominator_df, 1e-300)
    statistic = numerator / denominator
    return (
        statistic,
        float(stats.f.sf(statistic, numerator_df, denominator_df)),
        (numerator_df),
        denominator_df,
    )


def domain_explains(record: dict, settings: DiagnoseConfig) -> bool:
    """Whether a confusable domain explains a candidate's gain (record: one entry of
    signature_evidence's details["domains"]).

    It does when, on held-out pixels, less than the retained share of the gain's reduction
    survives the domain's profile with confidence (the interval's upper end below it); or when
    the gain does not stand out of its scatter across the domain's bins (F-test) and the
    held-out pixels do not show with confidence that most of its reduction survives. An F-test
    failure beside a confidently retained held-out share is the fit's own misfit raising the
    interaction: a fitted texture that averaged differently exposed training views is wrong by
    a different factor in each surface region, so a real per-view gain differs from bin to bin
    in every domain while still removing its whole held-out error."""
    low, high = record["interval"]
    retained = settings.specificity.retained_share
    if high < retained:
        return True
    return record["p_value"] >= settings.specificity.alpha and low < retained


def signature_evidence(
    name: str,
    table: PixelTable,
    data: DiagnosisData,
    settings: DiagnoseConfig,
    significant: bool = True,
) -> list[Evidence]:
    """The specificity Evidence of one gain-like candidate (details["instead"]: the mismatch
    that explains it, when one does and the candidate was significant)."""
    signature = SIGNATURES[name]
    confusers = _confusers(name, signature, data)
    base = list(signature.base)
    own = list(signature.own)
    factors = sorted({f for term in base + own for f in term if f != "channel"} | {"view"})
    own_models = GainModels(table, factors)
    before = own_models.heldout_errors(base)
    alone = before - own_models.heldout_errors(base + own)
    views = table.view_count
    relative, relative_low, _ = share_interval(alone, before, settings)
    if relative_low <= 0:
        # Without a reduction of its own there is no signature to check (and naming a
        # mismatch from a ratio of two noises would be a false alarm). But a camera gain
        # (facts.gain_signature: one gain per view, a curve of intensity, a radial falloff)
        # whose own signature removes no held-out error did not remove its error through that
        # signature: a refit's or probe's freedom absorbed something else (under a light that
        # turns with the camera, the diffuse model's rim and highlight mismatch), so it is not
        # specific, whatever the light. A light-transport effect's gain signature is not its
        # evidence (its fingerprint is): not tested. (Whether the candidate is significant is
        # decided after this check; an insignificant one names nothing either way.)
        facts = diagnosis_facts(name)
        camera_gain = facts is not None and facts.gain_signature
        reason = (
            f"{name}: its signature's gain removes no held-out error "
            f"({100 * relative:.1f} %, interval from {100 * relative_low:.1f} %)"
        )
        if not camera_gain:
            reason += "; not tested"
        elif data.lighting.frame == "camera":
            reason += (
                "; under a light that turns with the camera a refit's gain absorbs the diffuse "
                "model's mismatch instead, so it is not specific"
            )
        else:
            reason += "; what removed its error is not its signature, so it is not specific"
        return [
            Evidence(
                kind=KIND,
                candidate=name,
                statistic=float("nan"),
                threshold=settings.specificity.alpha,
                passed=not camera_gain,
                reason=reason,
                details={"tested": False, "heldout_reduction": relative},
            )
        ]
    domains = {}
    for domain in confusers:
        factors_here = sorted(set(factors) | {domain})
        models = GainModels(table, factors_here)
        conditioned = base + [(domain, "channel")]
        given = models.heldout_errors(conditioned) - models.heldout_errors(conditioned + own)
        share, low, high = share_interval(given, alone, settings)
        statistic, p_value, numerator_df, denominator_df = f_test(
            GainModels(table, factors_here, all_pixels=True), base, own, domain
        )
        record = {
            "f": statistic,
            "p_value": p_value,
            "degrees_of_freedom": [numerator_df, denominator_df],
            "share": share,
            "interval": [low, high],
            "alternative": confusers[domain],
        }
        slope = view_covariate_slope(table, models, domain) if name == "exposure" else None
        if slope is not None:
            record["view_slope"] = slope
        domains[domain] = record
    failing = [domain for domain, record in domains.items() if domain_explains(record, settings)]
    passed = not failing
    if passed:
        worst = max(domains, key=lambda domain: domains[domain]["p_value"])
    else:
        # The domain that explains most of it names the alternative.
        worst = min(failing, key=lambda domain: domains[domain]["share"])
    record = domains[worst]
    p_value = record["p_value"]
    details = {
        "heldout_reduction": relative,
        "domains": domains,
        "failing_domains": failing,
        "worst_domain": worst,
        "views": views,
        "light_direction": table.light_source,
    }
    word = DOMAIN_WORDS[worst]
    share, (low, high) = record["share"], record["interval"]
    kept = f"keeps {100 * share:.0f} % (interval {100 * low:.0f} to {100 * high:.0f} %)"
    test = f"F = {record['f']:.1f}, p = {p_value:.2g}"
    if passed:
        if p_value >= settings.specificity.alpha:  # held-out pixels overruled the F-test
            reason = (
                f"{name} is specific: once a common profile of {word} is modelled, it {kept} "
                f"of its held-out reduction of {100 * relative:.1f} %, although its gain does "
                f"not stand out of its scatter across those bins ({test}): the fit's own "
                f"misfit varies from bin to bin there"
            )
        else:
            reason = (
                f"{name} is specific: its gain stands out above how it varies across bins of "
                f"every domain (least clear: {word}, {test}; it {kept} of its held-out "
                f"reduction of {100 * relative:.1f} % there)"
            )
        return [Evidence(KIND, name, p_value, settings.specificity.alpha, True, reason, details)]
    alternative = record["alternative"]
    details["alternative"] = alternative
    slope = record.get("view_slope")
    follows = ""
    if slope is not None:
        follows = (
            f"per-view gains vary with {word} (slope {slope['slope']:.2f} +- "
            f"{slope['slope_error']:.2f} per unit, r = {slope['correlation']:.2f}) across "
            f"{views} views; "
        )
    # A mismatch is named in the vetoed candidate's place (details["instead"], read by the
    # decision table) only when the held-out pixels agree that the domain takes most of the
    # reduction, and only for a significant candidate: an insignificant gain explains nothing.
    named = (
        bool(alternative)
        and signature.names_alternative
        and alternative in MISMATCHES
        and significant
        and share < settings.specificity.retained_share
    )
    if named:
        details["instead"] = alternative
    instead = f"{alternative}, not {name}" if alternative else f"not {name}"
    reason = (
        f"{follows}once a common profile of {word} is modelled, {name}'s gain no longer "
        f"stands out ({test} against its scatter across the bins; it {kept} of its held-out "
        f"reduction of {100 * relative:.1f} %): {instead}"
    )
    return [Evidence(KIND, name, p_value, settings.specificity.alpha, False, reason, details)]


def specificity_evidence(
    data: DiagnosisData,
    candidates: list[str] | None = None,
    settings: DiagnoseConfig | None = None,
    significant: set[str] | None = None,
) -> list[Evidence]:
    """Specificity Evidence for each gain-like candidate (default: every one in SIGNATURES):
    whether its gain follows its own factor or a confusable domain's profile.

    data: the held-out views (observations beside the fitted scene's render). Candidates
    without a gain signature (lens distortion, blurs, pose error) get no Evidence here.
    significant: the candidates found significant so far; a vetoed one names a mismatch
    instead only if it is among them (None: every candidate counts as significant)."""
    settings = settings or DiagnoseConfig()
    names = [name for name in (candidates or list(SIGNATURES)) if name in SIGNATURES]
    if not names:
        return []
    table = pixel_table(
        data,
        angle_bins=settings.specificity.angle_bins,
        intensity_bins=settings.specificity.intensity_bins,
        surface_cells=settings.specificity.surface_cells,
        position_cells=settings.specificity.position_cells,
        block_pixels=settings.block_pixels,
        normal_cells=settings.specificity.normal_cells,
    )
    evidence: list[Evidence] = []
    for name in names:
        counts = significant is None or name in significant
        evidence.extend(signature_evidence(name, table, data, settings, counts))
    return evidence
