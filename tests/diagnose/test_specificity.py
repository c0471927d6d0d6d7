"""Specificity: a per-view gain that follows n.h is the base model's mismatch, not exposure.

The key pair (issue 20, item 2): a glossy torus fitted with a diffuse model, at constant
exposure, fools the exposure probe (its per-view gains absorb how much highlight each view
shows); the specificity check must veto exposure and name view-dependent reflectance. The same
glossy torus with a real per-view exposure must pass.
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from diagnose_scenes import glossy_torus_views

from recon.diagnose.specificity import (
    VIEW_DEPENDENT_REFLECTANCE,
    SpecificityOptions,
    specificity_evidence,
)
from recon.diagnose.which import rank_candidates


def by_candidate(evidence):
    return {item.candidate: item for item in evidence}


def test_a_glossy_object_at_constant_exposure_does_not_get_exposure():
    data, gains = glossy_torus_views(exposure_sigma=0.0)
    assert torch.allclose(gains, torch.ones_like(gains))
    # Today's probe is fooled: the per-view gain removes a significant share of the error.
    probe = {item.name: item for item in rank_candidates(data, ["exposure"])}
    assert probe["exposure"].significant
    assert probe["exposure"].evidence_of("probe").interval[0] > 0.03
    evidence = by_candidate(specificity_evidence(data, ["exposure"]))
    exposure = evidence["exposure"]
    assert exposure.kind == "specificity"
    assert not exposure.passed, exposure.reason
    # The statistic is the least clear domain's p-value: no evidence of a gain of its own.
    assert exposure.statistic > exposure.threshold
    assert exposure.details["worst_domain"] == "n_dot_h"
    assert "n.h" in exposure.reason and VIEW_DEPENDENT_REFLECTANCE in exposure.reason
    slope = exposure.details["domains"]["n_dot_h"]["view_slope"]
    assert slope["slope"] > 3 * slope["slope_error"] and slope["correlation"] > 0.8
    assert exposure.details["instead"] == VIEW_DEPENDENT_REFLECTANCE


def test_a_real_exposure_on_the_same_glossy_object_passes():
    data, gains = glossy_torus_views(exposure_sigma=0.3)
    assert float(gains.log().std()) > 0.2
    evidence = by_candidate(specificity_evidence(data, ["exposure"]))
    exposure = evidence["exposure"]
    assert exposure.passed, exposure.reason
    assert exposure.statistic < exposure.threshold
    assert "instead" not in exposure.details
    # In every confusable domain the per-view gain stands out above its scatter across bins,
    # and keeps most of its held-out reduction.
    for domain, record in exposure.details["domains"].items():
        assert record["p_value"] < 1e-6 and record["share"] > 0.5, (domain, record)


def test_exposure_made_of_a_tone_curve_is_named_the_curve():
    # A response curve leaves per-view gains (views differ in how bright they are); they follow
    # the rendered intensity, and the curve itself is specific against image position.
    data, _ = glossy_torus_views(specular=0.0, transform=lambda image, _: image.clamp_min(0) ** 1.8)
    evidence = by_candidate(specificity_evidence(data, ["exposure", "response_curve"]))
    assert not evidence["exposure"].passed
    assert evidence["exposure"].details["worst_domain"] == "intensity"
    assert evidence["response_curve"].candidate == "response_curve"
    assert evidence["response_curve"].passed, evidence["response_curve"].reason


def test_vignetting_is_image_bound_and_takes_the_per_view_gains_with_it():
    def vignette(image, _):
        steps = torch.linspace(-1, 1, image.shape[1])
        radius2 = (steps[None, :] ** 2 + steps[:, None] ** 2) / 2
        return image * (1 - 0.5 * radius2)[None, :, :, None]

    data, _ = glossy_torus_views(specular=0.0, transform=vignette)
    evidence = specificity_evidence(data, ["exposure", "vignetting", "response_curve"])
    exposure = next(e for e in evidence if e.candidate == "exposure")
    assert not exposure.passed and exposure.details["alternative"] == "vignetting"
    vignetting = [e for e in evidence if e.candidate == "vignetting"]
    assert all(e.passed for e in vignetting), [e.reason for e in vignetting]
    curve = next(e for e in evidence if e.candidate == "response_curve")
    assert not curve.passed, curve.reason


def test_white_balance_on_a_glossy_object_passes_and_clean_data_is_not_tested():
    data, _ = glossy_torus_views(white_balance_sigma=0.2)
    white = by_candidate(specificity_evidence(data, ["white_balance"]))["white_balance"]
    assert white.passed and white.statistic < white.threshold, white.reason
    clean, _ = glossy_torus_views(specular=0.0)
    evidence = specificity_evidence(clean, ["exposure", "white_balance", "vignetting"])
    assert all(item.passed and not item.details.get("domains") for item in evidence)
    assert all(math.isnan(item.statistic) for item in evidence)
    assert {item.candidate for item in evidence} == {"exposure", "white_balance", "vignetting"}


def test_geometric_candidates_get_no_evidence_and_records_are_json():
    data, _ = glossy_torus_views(size=32, views=8)
    assert specificity_evidence(data, ["lens_distortion", "pose_error"]) == []
    options = SpecificityOptions(bootstrap_samples=50)
    for item in specificity_evidence(data, ["exposure", "specular"], options):
        json.dumps(item.to_json())


@pytest.mark.parametrize("seed", [1, 3])
def test_the_key_pair_holds_for_other_noise_and_exposure_draws(seed):
    constant, _ = glossy_torus_views(seed=seed)
    varied, _ = glossy_torus_views(exposure_sigma=0.3, seed=seed)
    assert not by_candidate(specificity_evidence(constant, ["exposure"]))["exposure"].passed
    assert by_candidate(specificity_evidence(varied, ["exposure"]))["exposure"].passed


def test_an_insignificant_candidate_names_nothing():
    data, _ = glossy_torus_views(exposure_sigma=0.0)
    evidence = by_candidate(specificity_evidence(data, ["exposure"], significant=set()))
    assert not evidence["exposure"].passed
    assert "instead" not in evidence["exposure"].details
