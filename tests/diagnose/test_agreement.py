"""A per-view white balance on a fit with a large misfit: named by the agreement of separate
halves of each view; a constant one (or none) reported not identifiable, not silently missed.

Built to fool the probe: a 32-px torus whose fitted texture is wrong by small grey patches (a
~17 dB fit) under a white balance that changes by a few per cent from view to view: no share of
the held-out error the probe can vouch for, but the same in both halves of every view.
"""

from __future__ import annotations

import torch
from diagnose_scenes import albedo_error_views, glossy_torus_views

from recon.config.run_config import DiagnoseConfig, NullConfig
from recon.diagnose.agreement import agreement_evidence, shared_spread
from recon.diagnose.checks import _as_condition
from recon.diagnose.decision import decide
from recon.diagnose.identifiability import white_balance_evidence
from recon.diagnose.records import Candidate
from recon.diagnose.specificity import specificity_evidence
from recon.diagnose.which import rank_candidates

SETTINGS = DiagnoseConfig(nulls=NullConfig(permutations=300))
VIEWS = 12


def white_balance(spread: float, varying: bool, seed: int = 4) -> torch.Tensor:
    """[VIEWS, 3] red and blue gains exp(spread N(0, 1)) per view (or one for every view)."""
    generator = torch.Generator().manual_seed(seed)
    red_blue = torch.exp(spread * torch.randn(VIEWS if varying else 1, 2, generator=generator))
    red_blue = red_blue.expand(VIEWS, 2)
    return torch.stack([red_blue[:, 0], torch.ones(VIEWS), red_blue[:, 1]], dim=-1)


def misfit(gains: torch.Tensor | None):
    """The ~17 dB fit: a grey albedo error on 16 x 16 cells, the views times gains [VIEWS, 3]."""
    return albedo_error_views(seed=1, error=0.8, cells=16, grey=True, channel_gains=gains)


def diagnosed(data, with_specificity: bool = False) -> Candidate:
    """The white_balance candidate with its probe, agreement and identifiability evidence (and
    its specificity checks with_specificity), decided."""
    candidate = next(
        c for c in rank_candidates(data, ["white_balance"]) if c.name == "white_balance"
    )
    agreement = agreement_evidence(data, "white_balance", SETTINGS)
    candidate.add(agreement)
    if with_specificity:
        for evidence in specificity_evidence(data, ["white_balance"], SETTINGS):
            candidate.add(evidence)
    details = agreement.details
    condition = white_balance_evidence(
        details["detectable"], details["noise"], details["views"], SETTINGS.identifiability
    )
    candidate.add(_as_condition(condition))
    return decide(candidate, SETTINGS.decision)


def test_a_white_balance_that_varies_across_views_is_named_through_a_large_misfit():
    data = misfit(white_balance(0.06, varying=True))
    candidate = diagnosed(data)
    probe = candidate.evidence_of("probe")
    # The probe alone does not clear: the white balance is a small share of the misfit.
    assert probe.statistic < SETTINGS.decision.minimum_share, probe.statistic
    agreement = candidate.evidence_of("agreement")
    assert agreement.passed and agreement.details["p_value"] < 0.01, agreement.reason
    assert candidate.significant and candidate.decided_by == "agreement", candidate.why
    assert "separate halves" in candidate.why


def test_a_constant_white_balance_or_none_is_not_named_and_only_the_common_cast_is_unknowable():
    # A grey misfit: the views' colours are measured well, so a per-view change would show; the
    # constant cast (or none) is no per-view change. Identifiability is the data's, not the
    # effect's: it passes, and says that a cast common to every view is the albedo's.
    for gains in (white_balance(0.06, varying=False), None):
        data = misfit(gains)
        spread, _, _, _ = shared_spread(data, 300, 0)
        assert spread < SETTINGS.decision.agreement_allowance["white_balance"]
        candidate = diagnosed(data)
        assert not candidate.significant
        assert candidate.status == "not_significant", candidate.why
        condition = candidate.evidence_of("identifiability")
        assert condition.passed, condition.reason
        assert "absorbed by the albedo" in condition.reason and "grey card" in condition.reason


def test_a_white_balance_hidden_in_colour_noise_is_reported_not_identifiable():
    # Colour patches of the albedo error: the halves of each view disagree in colour by more
    # than the per-view change of a 1 % white balance, which the test then cannot name.
    data = albedo_error_views(seed=2, error=0.8, channel_gains=white_balance(0.01, varying=True))
    candidate = diagnosed(data)
    agreement = candidate.evidence_of("agreement")
    assert agreement.details["detectable"] > SETTINGS.identifiability.white_balance_reference_spread
    assert agreement.details["noise"] > 0.01
    condition = candidate.evidence_of("identifiability")
    assert not condition.passed
    assert "colour noise" in condition.reason and "grey card" in condition.reason
    assert not candidate.evidence_of("agreement").passed


def test_a_local_colour_misfit_is_not_a_white_balance():
    # Large colour patches of the albedo error, no white balance: each view's colour error
    # differs between its halves.
    data = albedo_error_views(seed=2, error=0.8)
    evidence = agreement_evidence(data, "white_balance", SETTINGS)
    assert not evidence.passed, evidence.reason


GOLD = (1.0, 0.7, 0.25)


def test_a_coloured_highlight_with_a_constant_white_balance_is_not_a_white_balance():
    # A gold torus (its highlight has the metal's colour) under a colour cast common to every
    # view: views facing the light show more of the gold lobe, so their colour changes from
    # view to view although the camera's white balance does not. A broad lobe tints the whole
    # object; a narrow one a spot.
    cast = torch.tensor([1.15, 1.0, 0.85])
    for shininess in (3.0, 20.0):
        data, _ = glossy_torus_views(
            views=12,
            size=32,
            specular=0.5,
            shininess=shininess,
            specular_colour=GOLD,
            transform=lambda observed, output: observed * cast,
        )
        agreement = agreement_evidence(data, "white_balance", SETTINGS)
        assert not agreement.passed, agreement.reason
        candidate = diagnosed(data, with_specificity=True)
        assert not candidate.significant, candidate.why


def test_a_white_balance_on_a_coloured_highlight_is_named():
    # The same gold torus, its views' white balance changing by 4 % (RMS log gain).
    for shininess in (3.0, 20.0):
        data, _ = glossy_torus_views(
            views=12,
            size=32,
            specular=0.5,
            shininess=shininess,
            specular_colour=GOLD,
            white_balance_sigma=0.04,
        )
        agreement = agreement_evidence(data, "white_balance", SETTINGS)
        assert agreement.passed and agreement.details["p_value"] < 0.01, agreement.reason
        candidate = diagnosed(data, with_specificity=True)
        assert candidate.significant, candidate.why


def test_one_held_out_view_says_why_a_change_from_view_to_view_cannot_be_seen():
    # A real capture's LLFF test split may hold a single view: no change from view to view to
    # agree over, which must be said, not divided by zero.
    data = albedo_error_views(seed=2, views=1, error=0.8)
    agreement = agreement_evidence(data, "white_balance", SETTINGS)
    assert not agreement.passed and agreement.details["too_few_views"]
    assert "at least 3 held-out views" in agreement.reason and "got 1" in agreement.reason
    condition = white_balance_evidence(
        float("inf"), float("nan"), agreement.details["views"], SETTINGS.identifiability
    )
    assert not condition.passed
    assert "needs at least 3 held-out views" in condition.reason and "got 1" in condition.reason


def test_split_gains_read_the_colour_ratios_once_with_the_same_gains():
    """split_gains computes the colour ratios once for every half: the same gains as
    colour_gains of each half on its own."""
    from recon.diagnose.agreement import (
        colour_gains,
        half_masks,
        interior,
        residual_projection,
        split_gains,
        view_covariates,
    )

    data, _ = glossy_torus_views(views=5, size=32, specular=0.5, white_balance_sigma=0.1)
    settings = DiagnoseConfig()
    first, second, _ = split_gains(data, settings)
    projection, _ = residual_projection(view_covariates(data, settings))
    halves = half_masks(data, interior(data, settings.colour_erode_pixels))
    dark = settings.colour_dark_fraction
    plain_first = torch.cat([colour_gains(data, one, dark) for one, _ in halves], dim=1)
    plain_second = torch.cat([colour_gains(data, other, dark) for _, other in halves], dim=1)
    assert torch.equal(first, projection @ plain_first)
    assert torch.equal(second, projection @ plain_second)
    assert float(first.abs().max()) > 1e-4


def test_a_colour_change_only_in_the_bright_half_of_each_view_does_not_settle_the_intensity():
    # A per-view colour change confined to the pixels brighter than the view's median rendered
    # intensity (what a channel clipping in the brighter views leaves): the angle halves each
    # hold bright pixels and agree, the intensity split's halves do not.
    # Pooled, the halves still agree; the intensity is not a domain the agreement tested.
    data = misfit(None)
    gains = white_balance(0.08, varying=True)
    brightness = data.rendered.mean(dim=-1)
    inside = (data.observed_alpha[..., 0] > 0.5) & (data.rendered_alpha[..., 0] > 0.5)
    bright = torch.zeros_like(brightness, dtype=torch.bool)
    for view in range(brightness.shape[0]):
        bright[view] = brightness[view] > brightness[view][inside[view]].median()
    data.observed = torch.where(
        bright[..., None], data.observed * gains[:, None, None, :], data.observed
    )
    evidence = agreement_evidence(data, "white_balance", SETTINGS)
    per_domain = evidence.details["domain_p_values"]
    alpha = SETTINGS.decision.agreement_alpha
    assert evidence.details["p_value"] < alpha, evidence.reason
    assert per_domain["intensity"] > alpha, per_domain
    assert per_domain["n_dot_h"] < alpha and per_domain["n_dot_v"] < alpha, per_domain
    split = evidence.details["per_split"]
    assert split["intensity"]["correlation"] < split["n.v"]["correlation"], split


def test_a_colour_change_over_the_whole_view_settles_every_domain_it_splits():
    data = misfit(white_balance(0.08, varying=True))
    evidence = agreement_evidence(data, "white_balance", SETTINGS)
    per_domain = evidence.details["domain_p_values"]
    assert set(per_domain) == {"image_position", "intensity", "n_dot_h", "n_dot_v"}
    assert max(per_domain.values()) < SETTINGS.decision.agreement_alpha, per_domain
