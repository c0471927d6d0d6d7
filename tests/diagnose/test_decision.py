"""The decision table: the built-in evidence decides and ranks as the hand-ordered rule did
(flat field overrules either way, probe before absorption before relight, the fingerprint names
its effect and ranks after held-out evidence, voided absorption does not count), a stored
diagnosis is re-decided with other allowances, and the producer kinds (specificity, null,
identifiability, metadata) act as their rows say."""

from __future__ import annotations

import json
import math
from dataclasses import replace

from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.decision import (
    DECISION_TABLE,
    absorption_threshold,
    decide,
    decide_all,
    probe_threshold,
    rank_key,
    redecide,
    verdict_of,
)
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.effects.registry import MODEL_EFFECTS

CONFIG = DecisionConfig()


def evidence(kind, name, statistic, **details):
    return Evidence(kind, name, statistic, math.nan, False, kind, details)


def candidate(name, probe=None, absorption=None, relight=None, flat_field=None, share=None):
    """A candidate with the given evidence: probe/absorption/relight (low, high) intervals,
    flat_field a deviation, share a fingerprint share with a tight interval."""
    result = Candidate(name)
    for kind, interval in (("probe", probe), ("absorption", absorption), ("relight", relight)):
        if interval is not None:
            parameters = {"source": kind}
            result.add(
                evidence(
                    kind,
                    name,
                    interval[0],
                    interval=list(interval),
                    reduction=sum(interval) / 2,
                    parameters=parameters,
                )
            )
    if flat_field is not None:
        result.add(evidence("flat_field", name, flat_field))
    if share is not None:
        # A fingerprint that beats its placebo lights, with this slope.
        result.add(
            evidence(
                "fingerprint",
                name,
                0.1,
                slope=share,
                share=min(1.0, max(0.0, share)),
                interval=[share - 0.05, share + 0.05],
                coverage=0.3,
                p_value=0.005,
            )
        )
    return decide(result, CONFIG)


def test_every_effect_has_an_allowance_at_least_the_minimum():
    for effect in MODEL_EFFECTS:
        assert probe_threshold(effect, CONFIG) >= CONFIG.minimum_share


def test_a_probe_decides_by_its_lower_bound_against_the_allowance():
    threshold = probe_threshold("defocus_blur", CONFIG)
    assert threshold > CONFIG.minimum_share  # a flexible probe has a larger null
    above = candidate("defocus_blur", probe=(threshold + 0.01, 0.5))
    below = candidate("defocus_blur", probe=(threshold - 0.01, 0.5))
    assert above.significant and above.decided_by == "probe" and above.status == "significant"
    assert not below.significant and below.decided_by == "" and "does not clear" in below.why
    assert above.parameters == {"source": "probe"}


def test_the_flat_field_overrules_the_residual_evidence_either_way():
    loud = candidate("vignetting", probe=(0.3, 0.5), flat_field=CONFIG.flat_field_allowance / 2)
    assert not loud.significant and loud.decided_by == ""
    quiet = candidate("vignetting", probe=(-0.1, 0.5), flat_field=0.3)
    assert quiet.significant and quiet.decided_by == "flat_field"


def test_relight_evidence_decides_and_reports_its_parameters():
    quiet = candidate(
        "response_curve", probe=(-0.01, 0.01), relight=(CONFIG.relight_allowance + 0.1, 0.4)
    )
    assert quiet.significant and quiet.decided_by == "relight"
    assert quiet.parameters == {"source": "relight"}
    below = candidate("response_curve", probe=(-0.01, 0.01), relight=(0.02, 0.2))
    assert not below.significant
    # Nothing decided: the relight split's estimate is still the one reported.
    assert below.parameters == {"source": "relight"}


def test_the_closed_form_absorption_has_its_own_floor():
    """Vignetting's absorption evidence is a regression (its facts' absorption mode): its floor
    is the regression's, lower than the refits'; an interval between the two decides it only."""
    vignetting = absorption_threshold("vignetting", CONFIG)
    specular = absorption_threshold("specular", CONFIG)
    assert vignetting < CONFIG.absorption_minimum_share <= specular
    between = (0.5 * (vignetting + CONFIG.absorption_minimum_share), 0.02)
    assert candidate("vignetting", probe=(-0.01, 0.01), absorption=between).significant
    assert not candidate("specular", probe=(-0.01, 0.01), absorption=between).significant
    decided = candidate("vignetting", probe=(-0.01, 0.01), absorption=between)
    assert decided.decided_by == "absorption" and decided.parameters == {"source": "absorption"}


def test_voided_absorption_does_not_count_but_stays_recorded():
    lens = candidate("lens_distortion", probe=(-0.01, 0.01), absorption=(0.2, 0.4))
    assert lens.significant and lens.decided_by == "absorption"
    voided = replace(lens.evidence_of("absorption"), void="void beside defocus_blur")
    lens.add(voided)
    decide(lens, CONFIG)
    assert not lens.significant and lens.evidence_of("absorption") is not None


def test_the_fingerprint_names_shadows_or_interreflection_by_its_share():
    high = [
        candidate(name, probe=(-0.01, 0.0), share=0.8) for name in ("shadows", "interreflection")
    ]
    assert [item.significant for item in high] == [True, False]
    low = [
        candidate(name, probe=(-0.01, 0.0), share=0.4) for name in ("shadows", "interreflection")
    ]
    assert [item.significant for item in low] == [False, True]
    faint = candidate("shadows", probe=(-0.01, 0.0), share=0.1)
    assert not faint.significant


def test_the_fingerprint_needs_its_placebo_lights_and_never_flips_on_a_large_slope():
    """Named only when the correlation beats the placebo lights; a slope above 1 (a deeper
    baked shadow than predicted) is on the shadows side however large; an untestable one (the
    fitted mesh shadows nothing) names nothing, and its why says so; a fingerprint without
    placebo lights (statistic NaN) names nothing either."""

    def shadows(statistic, p_value, slope, coverage=0.3, reason="fingerprint"):
        result = Candidate("shadows")
        details = {"slope": slope, "coverage": coverage, "p_value": p_value}
        result.add(Evidence("fingerprint", "shadows", statistic, math.nan, False, reason, details))
        return decide(result, CONFIG)

    assert shadows(0.1, 0.005, 0.9).significant
    assert shadows(0.1, 0.005, 10.9).significant
    assert not shadows(0.1, 0.2, 10.9).significant  # placebo lights reach it
    assert not shadows(0.01, 0.005, 0.9).significant  # below the floor
    untestable = shadows(0.1, 0.005, 10.9, coverage=0.0, reason="not a share of anything")
    assert not untestable.significant and "not a share of anything" in untestable.why
    unmeasured = shadows(math.nan, 1.0, 2.0, reason="no placebo light")
    assert not unmeasured.significant and unmeasured.why.startswith("no placebo light")


def test_ranking_puts_residual_evidence_before_the_fingerprint():
    ranking = [
        candidate("shadows", probe=(-0.01, 0.0), share=0.8),
        candidate("pose_error", probe=(0.05, 0.3)),
        candidate("specular", probe=(0.2, 0.3)),
    ]
    decide_all(ranking, CONFIG)
    assert [item.name for item in ranking] == ["specular", "shadows", "pose_error"]


def test_significant_ones_rank_by_excess_over_their_own_allowance():
    """A flexible probe's raw reduction is larger, but clears less of its own null."""
    blur = candidate("defocus_blur", probe=(probe_threshold("defocus_blur", CONFIG) + 0.01, 0.3))
    exposure = candidate("exposure", probe=(0.1, 0.2))
    ranking = decide_all([blur, exposure], CONFIG)
    assert [item.name for item in ranking] == ["exposure", "defocus_blur"]
    assert rank_key(ranking[0]) > rank_key(ranking[1])
    assert verdict_of(ranking) == "significant unmodelled effects: exposure, defocus_blur"
    assert verdict_of([]) == "no significant unmodelled effect"


def test_a_failed_specificity_check_vetoes_and_names_the_mismatch_in_its_place():
    exposure = candidate("exposure", probe=(0.3, 0.5))
    white_balance = candidate("white_balance", probe=(0.05, 0.1))
    exposure.add(
        Evidence(
            "specificity",
            "exposure",
            0.6,
            0.2,
            False,
            "per-view gains follow n.h (r = 0.6)",
            {"instead": "view_dependent_reflectance", "parameters": {"r": 0.6}},
        )
    )
    ranking = decide_all([white_balance, exposure], CONFIG)
    names = [item.name for item in ranking]
    assert names[0] == "view_dependent_reflectance", names
    mismatch = ranking[0]
    assert mismatch.significant and mismatch.decided_by == "specificity"
    assert mismatch.parameters == {"r": 0.6} and "exposure" in mismatch.why
    vetoed = next(item for item in ranking if item.name == "exposure")
    assert vetoed.status == "vetoed" and not vetoed.significant and "n.h" in vetoed.why
    assert (
        verdict_of(ranking)
        == "significant unmodelled effects: view_dependent_reflectance, white_balance"
    )
    # A veto on a candidate that had not cleared names nothing.
    quiet = candidate("exposure", probe=(0.0, 0.01))
    quiet.add(replace(exposure.evidence_of("specificity")))
    assert [item.name for item in decide_all([quiet], CONFIG)] == ["exposure"]


def test_a_specificity_veto_does_not_overturn_a_measurement_on_other_data():
    # The held-out residual's pattern says "not vignetting" (a surface profile explains it),
    # but flat-field frames measured the falloff; the relight split measured the tone curve.
    def failed(name):
        reason = f"a surface profile explains {name}'s gain"
        return Evidence("specificity", name, 0.02, 0.01, False, reason, {})

    vignetting = candidate("vignetting", flat_field=0.39)
    vignetting.add(failed("vignetting"))
    assert decide(vignetting, CONFIG).significant and vignetting.decided_by == "flat_field"
    curve = candidate("response_curve", probe=(0.0, 0.01), relight=(0.1, 0.2))
    curve.add(failed("response_curve"))
    assert decide(curve, CONFIG).significant and curve.decided_by == "relight"
    # The same veto on a candidate the held-out probe decided stands.
    probed = candidate("vignetting", probe=(0.3, 0.5))
    probed.add(failed("vignetting"))
    assert decide(probed, CONFIG).status == "vetoed"
    # The capture's own record still vetoes a relight-decided candidate.
    curve.add(Evidence("metadata", "response_curve", 0.5, 0.0, False, "the record disagrees"))
    assert decide(curve, CONFIG).status == "vetoed"


def test_a_failed_null_from_the_run_raises_the_bar():
    exposure = candidate("exposure", probe=(0.1, 0.2))
    assert exposure.significant
    exposure.add(Evidence("null", "exposure", 0.1, 0.15, False, "placebo effects reach 0.15"))
    decide(exposure, CONFIG)
    assert not exposure.significant and exposure.why == "placebo effects reach 0.15"
    exposure.add(Evidence("null", "exposure", 0.1, 0.05, True, "placebo effects reach 0.05"))
    assert decide(exposure, CONFIG).significant


def test_a_failed_null_blocks_only_the_probe_and_only_where_it_clears():
    """Nulls are measured for every probe that could clear under some calibration; a failed
    one must not block a candidate its probe does not make significant, nor evidence that
    has its own null (an absorption refit), and must block the probe whatever else is
    recorded (built to fool a decision that treated the null as a veto of the candidate)."""
    failed = Evidence("null", "lens_distortion", 0.03, 0.05, False, "placebo effects reach 0.05")
    # Absorption clears, the probe clears but its null fails: the absorption decides.
    lens = candidate("lens_distortion", probe=(0.3, 0.4), absorption=(0.5, 0.6))
    lens.add(failed)
    decide(lens, CONFIG)
    assert lens.significant and lens.decided_by == "absorption", lens.why
    # The probe alone, null failed: not significant, and the null says why.
    alone = candidate("lens_distortion", probe=(0.3, 0.4))
    alone.add(failed)
    assert not decide(alone, CONFIG).significant and alone.why == failed.reason
    # A probe short of its allowance: the failed null is moot (the why is the probe's miss).
    short = candidate("lens_distortion", probe=(0.03, 0.04))
    short.add(failed)
    decide(short, CONFIG)
    assert not short.significant and "does not clear its allowance" in short.why
    # Re-decided with an allowance the probe clears, the stored null blocks it.
    lenient = replace(CONFIG, probe_allowance={"lens_distortion": 0.02})
    assert not decide(short, lenient).significant and short.why == failed.reason


def condition(name, reason, **details):
    """A failed identifiability condition on `name` (a condition: NaN statistic)."""
    return Evidence("identifiability", name, math.nan, math.nan, False, reason, details)


def test_a_miss_the_data_cannot_avoid_says_not_identifiable_and_the_capture():
    # The probe did not clear: without the condition this is a silent miss.
    curve = candidate("response_curve", probe=(0.005, 0.01))
    curve.add(
        condition("response_curve", "one light and no exposure change", capture="a second light")
    )
    ranking = decide_all([curve, candidate("exposure", probe=(0.0, 0.01))], CONFIG)
    assert curve.status == "not_identifiable" and not curve.significant
    assert curve.why == (
        "not identifiable from this data, because one light and no exposure change; "
        "a second light would make it identifiable; its probe fits the held-out views, "
        "removing 0.75 % of their error (0.50 to 1.00 %)"
    )
    assert verdict_of(ranking) == (
        "no significant unmodelled effect; not identifiable from this data: response_curve"
    )
    # Cleared but vetoed by its signature, on data that cannot identify it (the real capture:
    # the object never leaves the centre and the light turns with the camera): not a silent
    # "not there" but not identifiable, with both reasons; the veto's mismatch is still named.
    falloff = candidate("vignetting", probe=(0.3, 0.4))
    veto = {"instead": "view_dependent_reflectance"}
    falloff.add(Evidence("specificity", "vignetting", 0.5, 0.01, False, "follows n.v", veto))
    falloff.add(condition("vignetting", "the corner falloff is an extrapolation"))
    ranking = decide_all([falloff], CONFIG)
    assert falloff.status == "not_identifiable" and not falloff.significant
    assert falloff.why == (
        "not identifiable from this data, because the corner falloff is an extrapolation; "
        "and follows n.v"
    )
    assert [item.name for item in ranking if item.significant] == ["view_dependent_reflectance"]
    # The same veto where the data can identify it stays a veto; so does a capture record's.
    identifiable = candidate("vignetting", probe=(0.3, 0.4))
    identifiable.add(Evidence("specificity", "vignetting", 0.5, 0.01, False, "follows n.v"))
    assert decide(identifiable, CONFIG).status == "vetoed"
    recorded = candidate("exposure", probe=(0.3, 0.4))
    recorded.add(Evidence("metadata", "exposure", 0.5, 0.0, False, "EXIF disagrees"))
    recorded.add(condition("exposure", "one gain per view"))
    assert decide(recorded, CONFIG).status == "vetoed" and recorded.why == "EXIF disagrees"


def test_a_not_identifiable_verdict_says_what_its_probe_measured():
    # The real capture's defocus: the probe recovers the blur (its interval clear of zero) yet
    # stays far under its allowance; the user reads the radius it fits beside the reason.
    blur = Candidate("defocus_blur")
    blur.add(
        evidence(
            "probe",
            "defocus_blur",
            0.004,
            interval=[0.004, 0.012],
            reduction=0.0077,
            parameters={"sigma_px": 0.9085, "equivalent_disk_radius_px": 1.817},
        )
    )
    blur.add(condition("defocus_blur", "the fit's own misfit hides a blur this size"))
    decide(blur, CONFIG)
    assert blur.status == "not_identifiable"
    assert blur.why.endswith(
        "; its probe fits the held-out views with sigma_px 0.908, equivalent_disk_radius_px "
        "1.82, removing 0.77 % of their error (0.40 to 1.20 %)"
    )
    # A probe whose interval reaches zero measured nothing: it is not passed off as a reading.
    clean = Candidate("defocus_blur")
    clean.add(
        evidence(
            "probe",
            "defocus_blur",
            -0.0003,
            interval=[-0.0003, 0.0003],
            reduction=0.0,
            parameters={"sigma_px": 0.196},
        )
    )
    clean.add(condition("defocus_blur", "the fit's own misfit hides a blur this size"))
    decide(clean, CONFIG)
    assert clean.why.endswith("; its probe removes nothing beyond noise (lower bound -0.03 %)")
    assert "sigma_px" not in clean.why


def test_a_cleared_candidate_confusable_with_a_named_effect_is_significant_but_ambiguous():
    curve = candidate("response_curve", probe=(0.3, 0.4))
    curve.add(
        condition(
            "response_curve",
            "every surface point is seen at one intensity",
            capture="bracketed exposures",
            confused_with=["albedo", "exposure"],
        )
    )
    ranking = decide_all([candidate("vignetting", probe=(0.0, 0.01)), curve], CONFIG)
    assert curve.significant and curve.status == "ambiguous" and curve.decided_by == "probe"
    assert "response_curve or exposure: not separable from this data, because every" in curve.why
    assert curve.why.endswith("bracketed exposures would make it identifiable")
    # Scored as naming the first: the significant set is the candidate alone.
    assert [item.name for item in ranking if item.significant] == ["response_curve"]
    assert verdict_of(ranking) == (
        "significant unmodelled effects: response_curve or exposure; response_curve or "
        "exposure: not separable from this data, because every surface point is seen at one "
        "intensity"
    )
    # The ambiguity is re-derived from the stored evidence.
    again = redecide(Diagnosis(candidates=ranking, verdict="", settings={}))
    assert again.verdict == verdict_of(ranking)
    assert again.candidates[0].status == "ambiguous"


def test_a_cleared_candidate_whose_condition_names_no_effect_stays_significant_and_qualified():
    falloff = candidate("vignetting", probe=(0.3, 0.4))
    falloff.add(condition("vignetting", "the corner falloff is an extrapolation"))
    decide(falloff, CONFIG)
    assert falloff.significant and falloff.status == "significant"
    assert falloff.why.endswith("; but the corner falloff is an extrapolation")
    assert verdict_of([falloff]) == "significant unmodelled effects: vignetting"


def test_a_condition_the_deciding_evidence_measured_does_not_qualify_it():
    # "a second light would settle it" reads wrong when the second light found it.
    def shadows(**intervals):
        found = candidate("shadows", **intervals)
        found.add(
            condition(
                "shadows",
                "placebo lights explain the baked shading as well",
                capture="a relight split",
                settled_by=["relight"],
            )
        )
        return decide(found, CONFIG)

    by_relight = shadows(relight=(0.3, 0.4))
    assert by_relight.status == "significant" and by_relight.decided_by == "relight"
    assert "but" not in by_relight.why and "relight split" not in by_relight.why
    by_probe = shadows(probe=(0.3, 0.4))
    assert by_probe.status == "significant" and by_probe.decided_by == "probe"
    assert by_probe.why.endswith("; a relight split would settle it")


def test_agreeing_metadata_and_unknown_kinds_change_nothing():
    exposure = candidate("exposure", probe=(0.1, 0.2))
    exposure.add(Evidence("metadata", "exposure", 0.9, math.nan, True, "EXIF agrees r = 0.9"))
    exposure.add(Evidence("something_new", "exposure", 1.0, 0.0, False, "a future check"))
    assert decide(exposure, CONFIG).significant and exposure.decided_by == "probe"


def test_metadata_that_disagrees_vetoes_the_candidate():
    # A fixed-exposure capture (EXIF the same in every view) whose fit leaves per-view gains:
    # the camera's own record says it was not the exposure.
    exposure = candidate("exposure", probe=(0.1, 0.2))
    reason = "recovered exposure does not agree: EXIF exposure is the same in all 9 views"
    exposure.add(Evidence("metadata", "exposure", 0.027, 0.0, False, reason))
    decided = decide(exposure, CONFIG)
    assert decided.status == "vetoed" and not decided.significant and "EXIF" in decided.why
    assert verdict_of([decided]) == "no significant unmodelled effect"


def test_every_row_has_a_known_role():
    roles = {rule.role for rule in DECISION_TABLE}
    assert roles <= {"overrule", "clear", "name", "null", "veto", "qualify", "inform"}
    assert [rule.kind for rule in DECISION_TABLE][:5] == [
        "flat_field",
        "line_target",
        "probe",
        "absorption",
        "relight",
    ]


def test_redecide_uses_the_stored_evidence_and_the_given_config():
    ranking = decide_all(
        [candidate("exposure", probe=(0.1, 0.2)), candidate("vignetting", probe=(0.03, 0.1))],
        CONFIG,
    )
    stored = Diagnosis(candidates=ranking, verdict=verdict_of(ranking)).to_json()
    stored = json.loads(json.dumps(stored, allow_nan=False))
    assert redecide(stored).verdict == "significant unmodelled effects: exposure, vignetting"
    strict = DiagnoseConfig(decision=DecisionConfig(minimum_share=0.05))
    decided = redecide(stored, strict)
    assert decided.verdict == "significant unmodelled effects: exposure"
    assert decided.settings["decision"]["minimum_share"] == 0.05
    assert decided.candidate("vignetting").evidence_of("probe").threshold == 0.05
    # The stored record itself is unchanged.
    assert stored["candidates"][1]["significant"]


def test_a_colour_gain_shared_by_separate_halves_is_not_vetoed_in_the_domains_they_split():
    # Own bunny's white balance in the blind check: the halves of each view share a 6 % colour
    # change (p = 0.001), but the F-test against the image position (p = 1, under a misfit of
    # 18-20 dB) vetoed it. The agreement tested the image position, intensity, n.h and n.v
    # itself (halves split by each; per-view highlight composition partialled out); a veto in
    # another domain (the surface region) still stands.
    def white_balance(failing):
        result = Candidate("white_balance")
        result.add(evidence("agreement", "white_balance", 0.06, p_value=0.001, views=8))
        details = {"worst_domain": "image_position", "alternative": "vignetting"}
        if failing is not None:
            details["failing_domains"] = failing
        result.add(Evidence("specificity", "white_balance", 1.0, 0.01, False, "veto", details))
        return decide(result, CONFIG)

    assert white_balance(["image_position"]).status == "significant"
    assert white_balance(["image_position", "n_dot_h", "n_dot_v", "intensity"]).status == (
        "significant"
    )
    assert white_balance(["image_position", "surface"]).status == "vetoed"
    assert white_balance(None).status == "vetoed"  # a record without its failing domains
    # The probe did not test the image position: its veto stands.
    probed = Candidate("white_balance")
    probed.add(evidence("probe", "white_balance", 0.2, interval=[0.2, 0.3], reduction=0.25))
    probed.add(
        Evidence(
            "specificity",
            "white_balance",
            1.0,
            0.01,
            False,
            "veto",
            {"failing_domains": ["image_position"]},
        )
    )
    assert decide(probed, CONFIG).status == "vetoed"
    # Unless the agreement also passed: it tested the image position, whichever row decided.
    probed.add(evidence("agreement", "white_balance", 0.06, p_value=0.001, views=8))
    assert decide(probed, CONFIG).status == "significant"


def test_the_agreement_settles_only_the_domains_whose_splits_agreed_on_their_own():
    # Own bob beside a strong exposure in the blind check: the halves share a 10 % colour
    # change pooled (p = 0.001), but the bright and the dark halves of each view agree only at
    # p = 0.033; the specificity check failed in the intensity (and n.h, image position).
    def white_balance(domain_p_values, failing):
        result = Candidate("white_balance")
        result.add(
            evidence(
                "agreement",
                "white_balance",
                0.1,
                p_value=0.001,
                views=8,
                domain_p_values=domain_p_values,
            )
        )
        details = {"worst_domain": "intensity", "failing_domains": failing}
        result.add(Evidence("specificity", "white_balance", 0.15, 0.01, False, "veto", details))
        return decide(result, CONFIG)

    agreed = {"image_position": 0.002, "intensity": 0.001, "n_dot_h": 0.003, "n_dot_v": 0.001}
    bright_only = {**agreed, "intensity": 0.033}
    assert white_balance(agreed, ["intensity", "n_dot_h"]).status == "significant"
    assert white_balance(bright_only, ["intensity", "n_dot_h"]).status == "vetoed"
    # A veto outside the split that disagreed is still settled.
    assert white_balance(bright_only, ["n_dot_h", "image_position"]).status == "significant"
    # The level is the config's: at a looser agreement_alpha the intensity split agreed.
    loose = replace(CONFIG, agreement_alpha=0.05)
    result = white_balance(bright_only, ["intensity"])
    assert result.status == "vetoed"
    assert decide(result, loose).status == "significant"


def test_a_relight_split_that_shows_no_curve_vetoes_a_response_curve_the_probe_found():
    # Own spot beside a strong exposure in the blind check (a 12 dB fit): the probe on top of
    # the exposure removed 23 % of the held-out error as a response curve, while the relight
    # split's exponent (1.82, expanding) removed nothing beyond the fitted light's balance.
    def curve(specific, probe=(0.15, 0.28), relight=(0.0, 0.0)):
        result = candidate("response_curve", probe=probe, relight=relight)
        item = result.evidence_of("relight")
        item.details.update(specific=specific, parameters={"gamma": 1.82})
        return decide(result, CONFIG)

    vetoed = curve(specific=False)
    assert vetoed.status == "vetoed" and not vetoed.significant
    assert "relight split" in vetoed.why and "1.82" in vetoed.why, vetoed.why
    # A specific exponent the allowance does not reach leaves the probe's verdict alone.
    assert curve(specific=True).status == "significant"
    # The relight split decides on its own, whatever the probe.
    found = curve(specific=True, probe=(-0.01, 0.01), relight=(0.1, 0.2))
    assert found.significant and found.decided_by == "relight"
    # Only for an effect the relight split identifies: an exposure's probe is not vetoed by it.
    gain = candidate("exposure", probe=(0.15, 0.28), relight=(0.0, 0.0))
    gain.evidence_of("relight").details["specific"] = False
    assert decide(gain, CONFIG).significant
    # A voided relight measurement says nothing.
    voided = candidate("response_curve", probe=(0.15, 0.28), relight=(0.0, 0.0))
    relight = voided.evidence_of("relight")
    relight.details["specific"] = False
    voided.evidence = [
        replace(item, void="the relight split's views are too few") if item is relight else item
        for item in voided.evidence
    ]
    assert decide(voided, CONFIG).significant


def lobe_evidence(kind: str, excess: float) -> Evidence:
    """A lobe-like Evidence of specular (kind lobe or relight_lobe) with this excess over its
    placebo lights (p = 0.006)."""
    return Evidence(
        kind=kind,
        candidate="specular",
        statistic=excess,
        threshold=0.0,
        passed=True,
        reason=f"{kind}: excess",
        details={"p_value": 0.006, "correlation": 0.1, "placebo_quantile": 0.1 - excess},
    )


def test_the_relight_lobe_has_the_relight_splits_floor_and_decides_independently():
    config = DecisionConfig()

    def lobe_like(kind: str, excess: float) -> Candidate:
        candidate = Candidate("specular")
        candidate.add(lobe_evidence(kind, excess))
        return decide(candidate, config)

    # An excess of 0.03 clears the lobe's floor (0.02) but not the relight split's (0.05):
    # 8 relight views hold half the lobe's pixels, and no-highlight cases reached +0.031.
    assert config.lobe_minimum < 0.03 < config.relight_lobe_minimum
    assert lobe_like("lobe", 0.03).significant
    assert not lobe_like("relight_lobe", 0.03).significant
    named = lobe_like("relight_lobe", 0.1)
    assert named.significant and named.decided_by == "relight_lobe", named.why


def test_a_specificity_veto_does_not_overturn_a_pass_on_the_relight_split_in_either_order():
    # The lobe under the fitted light comes first in the table; when it passes too, the
    # relight split's pass (other data) still keeps the held-out pattern's veto off.
    veto = Evidence("specificity", "specular", 0.97, 0.01, False, "shadows, not specular", {})
    both = Candidate("specular")
    for item in (lobe_evidence("lobe", 0.03), lobe_evidence("relight_lobe", 0.14), veto):
        both.add(item)
    decide(both, CONFIG)
    assert both.decided_by == "lobe" and both.significant, both.why
    alone = Candidate("specular")
    for item in (lobe_evidence("lobe", 0.03), veto):
        alone.add(item)
    assert decide(alone, CONFIG).status == "vetoed"


def test_a_lens_condition_is_settled_where_the_probe_beat_its_confusers():
    # A reference distortion's condition says a pose correction explains it as well; the lens
    # probe measured otherwise (it keeps 2.6 % on top of every confuser, pose included, beyond
    # the allowance): significant, not "not identifiable" nor "lens or pose".
    def lens(beyond_passes):
        result = candidate("lens_distortion", probe=(0.036, 0.064))
        kept = 0.026 if beyond_passes else 0.005

        def entry(low):
            return {"reduction": low + 0.014, "interval": [low, low + 0.028]}

        record = {
            "candidate": "lens_distortion",
            "confuser": "pose_error",
            "alone": entry(0.036),
            "confuser_alone": entry(0.03),
            "on_top_of_confuser": entry(kept),
            "confuser_on_top": entry(0.0),
            "allowance": 0.087,
            "confuser_allowance": 0.211,
        }
        details = {"pairs": [record], "margin": 0.0, "probe_lower_bound": 0.036}
        result.add(Evidence("specificity", "lens_distortion", kept, 0.087, True, "", details))
        result.add(
            condition(
                "lens_distortion",
                "a radial distortion is a per-view zoom and shift but for 0.10 px",
                capture="views with the object near the image edges",
                confused_with=["pose_error"],
                settled_by=["beyond_confusers"],
            )
        )
        return result

    config = DecisionConfig(probe_allowance={"lens_distortion": 0.087})
    settled = decide(lens(True), config)
    assert settled.status == "significant" and settled.decided_by == "beyond_confusers"
    # Where the probe kept nothing beyond its confusers the condition still answers.
    unsettled = decide(lens(False), config)
    assert unsettled.status == "not_identifiable" and "0.10 px" in unsettled.why


def test_a_distortion_absorbed_alone_does_not_count_beside_a_blur_its_probe_found():
    # A blurred teapot at 48 px: the fit bent the blur's silhouette misfit into the geometry,
    # and the lens refit that moves the vertices takes part of it back (absorption lower bound
    # 0.06 against 0.043), while its probe clears nothing. Beside a defocus blur that its own
    # probe made significant, that absorption measured alone does not count.
    lens_threshold = absorption_threshold("lens_distortion", CONFIG)
    blur_threshold = probe_threshold("defocus_blur", CONFIG)
    lens = candidate("lens_distortion", probe=(0.01, 0.05), absorption=(lens_threshold + 0.02, 0.2))
    blur = candidate("defocus_blur", probe=(blur_threshold + 0.02, 0.4))
    assert lens.significant and blur.significant
    ranking = decide_all([lens, blur], CONFIG)
    assert [item.name for item in ranking if item.significant] == ["defocus_blur"]
    voided = ranking[1].evidence_of("absorption")
    assert not voided.counts and "void beside defocus_blur" in voided.void
    # Recorded, and re-derived under another calibration: where the blur's allowance hides the
    # blur, the absorption counts again and names the distortion.
    stored = json.loads(json.dumps(Diagnosis(candidates=ranking).to_json(), allow_nan=False))
    strict_blur = DecisionConfig(probe_allowance={**CONFIG.probe_allowance, "defocus_blur": 0.5})
    decided = redecide(stored, DiagnoseConfig(decision=strict_blur))
    assert [item.name for item in decided.candidates if item.significant] == ["lens_distortion"]
    assert decided.candidate("lens_distortion").evidence_of("absorption").counts
    # A distortion beside an effect that is not its confuser keeps its absorption.
    exposure = candidate("exposure", probe=(0.2, 0.4))
    kept = decide_all(
        [candidate("lens_distortion", absorption=(lens_threshold + 0.02, 0.2)), exposure], CONFIG
    )
    assert {item.name for item in kept if item.significant} == {"exposure", "lens_distortion"}
