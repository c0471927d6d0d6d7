"""The geometric checks as producers: a vetoed candidate the others were measured on top of
gives them their probes alone back, and the decision names the effect the capture holds."""

from __future__ import annotations

from diagnose_scenes import camera_effect_torus_views as torus_with

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.decision import decide_all, verdict_of
from recon.diagnose.geometric_checks import GEOMETRIC_PRODUCERS
from recon.diagnose.producers import PRODUCERS, EvidenceInputs, gather
from recon.diagnose.which import EffectProbe, conditional_probes, rank_candidates

SETTINGS = DiagnoseConfig(bootstrap_samples=200)


def probed(data, names):
    probe = EffectProbe(data, SETTINGS)
    return probe, rank_candidates(data, names, probe=probe, settings=SETTINGS)


def test_the_producers_are_registered():
    assert all(producer in PRODUCERS for producer in GEOMETRIC_PRODUCERS)


def test_a_blur_measured_on_top_of_a_vetoed_distortion_is_named():
    data = torus_with("motion_blur", {"length_px": 2.0, "length_spread": 0.3, "curvature_deg": 30})
    probe, ranked = probed(data, ["lens_distortion", "motion_blur", "defocus_blur"])
    # As on the path-traced benchmark: the distortion's probe is what the others are measured
    # on top of (there it topped the ranking through its absorption refit).
    conditional_probes(ranked, probe, "lens_distortion")
    blur = next(item for item in ranked if item.name == "motion_blur")
    assert blur.evidence_of("probe").details["conditional_on"] == "lens_distortion"
    assert "alone" in blur.evidence_of("probe").details
    inputs = EvidenceInputs(data, probe, None, None, None)
    gather(GEOMETRIC_PRODUCERS, inputs, ranked, SETTINGS)
    decide_all(ranked, SETTINGS.decision)
    by_name = {item.name: item for item in ranked}
    lens = by_name["lens_distortion"]
    assert lens.status == "vetoed", lens.why
    assert "not lens_distortion's" in lens.why
    blur = by_name["motion_blur"]
    probe_evidence = blur.evidence_of("probe")
    assert probe_evidence.details["conditional_on"] is None
    assert "restored" in probe_evidence.details
    assert blur.significant, blur.why
    assert blur.evidence_of("null") is not None  # the probe alone faced its placebo null
    verdict = verdict_of(ranked)
    assert "lens_distortion" not in verdict.split(";")[0]
    assert ranked[0].name == "motion_blur", [(item.name, item.status) for item in ranked]


def test_a_distortion_vetoed_where_the_data_cannot_identify_it_counts_as_vetoed():
    """On a centred object a distortion is vetoed by its signature and also not identifiable:
    the decision reads "not identifiable", and the blur measured on top of it must still get
    its probe alone back (the own world's teapot defocus case went unnamed without this)."""
    import math

    from recon.diagnose.geometric_checks import _vetoed
    from recon.diagnose.records import Candidate, Evidence

    def distortion(identifiable: bool) -> Candidate:
        candidate = Candidate("lens_distortion")
        candidate.add(
            Evidence(
                "probe", "lens_distortion", 0.1, math.nan, False, "probe", {"interval": [0.1, 0.2]}
            )
        )
        candidate.add(
            Evidence("specificity", "lens_distortion", -0.01, 0.05, False, "defocus_blur's")
        )
        candidate.add(
            Evidence("identifiability", "lens_distortion", 0.1, 0.5, identifiable, "a zoom")
        )
        return candidate

    assert _vetoed(distortion(identifiable=True), SETTINGS)
    assert _vetoed(distortion(identifiable=False), SETTINGS)
    quiet = Candidate("lens_distortion")
    quiet.add(Evidence("probe", "lens_distortion", 0.0, math.nan, False, "probe", {}))
    quiet.add(Evidence("identifiability", "lens_distortion", 0.1, 0.5, False, "a zoom"))
    assert not _vetoed(quiet, SETTINGS)  # not identifiable, but nothing vetoed it
