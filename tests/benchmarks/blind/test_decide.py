"""benchmarks/blind/decide.py: stored evidence re-decided with another threshold set."""

from __future__ import annotations

from benchmarks.blind.decide import (
    code_thresholds,
    diagnose_section,
    redecide_with,
    significant_effects,
)
from recon.config.run_config import DecisionConfig


def _diagnosis() -> dict:
    def item(effect: str, low: float) -> dict:
        return {
            "effect": effect,
            "score": low,
            "heldout_reduction": low * 1.2,
            "interval": [low, low * 1.4],
            "significant": False,
        }

    return {"ranking": [item("pose_error", 0.08), item("exposure", 0.05)], "refits": []}


def test_thresholds_change_the_decision_and_are_restored():
    stored = _diagnosis()
    code = code_thresholds()
    # The code's pose allowance (0.108) keeps pose silent; exposure (0.02) is named.
    assert significant_effects(redecide_with(stored)) == ["exposure"]
    lowered = redecide_with(stored, {"probe.pose_error": 0.03, "probe.exposure": 0.06})
    assert significant_effects(lowered) == ["pose_error"]
    assert lowered["verdict"] == "significant unmodelled effects: pose_error"
    # The stored evidence is untouched; the defaults are the diagnosis' own.
    assert stored == _diagnosis()
    assert code["probe.pose_error"] == DecisionConfig().probe_allowance["pose_error"]


def test_the_fingerprint_is_re_decided_with_its_threshold():
    import math

    from recon.diagnose.records import Candidate, Diagnosis, Evidence

    shadows = Candidate("shadows")
    details = {"slope": 0.7, "share": 0.7, "coverage": 0.2, "p_value": 0.005}
    shadows.add(Evidence("fingerprint", "shadows", 0.06, math.nan, False, "fp", details))
    stored = Diagnosis(candidates=[shadows]).to_json()
    assert "shadows" in significant_effects(redecide_with(stored))
    assert "shadows" not in significant_effects(redecide_with(stored, {"fingerprint": 0.1}))
    # Above a slope of 0.8 only a shadow is "shadows": 0.7 now names interreflection.
    assert "shadows" not in significant_effects(redecide_with(stored, {"shadow_share": 0.8}))


def test_thresholds_as_a_diagnose_section():
    section = diagnose_section(code_thresholds())["decision"]
    assert section["probe_allowance"]["pose_error"] == 0.108
    assert section["absorption_allowance"]["lens_distortion"] == 0.043
    assert section["relight_allowance"] == 0.03 and section["shadow_share"] == 0.6
    assert set(section["probe_allowance"]) == set(section["absorption_allowance"])
    assert section["bounce_minimum"] == DecisionConfig().bounce_minimum


def test_an_ambiguous_candidate_is_scored_as_naming_the_first():
    """A significant candidate the data cannot tell from a named effect stays one name in the
    significant set (exact-set scoring), and the verdict says "A or B"."""
    import math

    from recon.diagnose.records import Candidate, Diagnosis, Evidence

    curve = Candidate("response_curve")
    interval = {"reduction": 0.35, "interval": [0.3, 0.4]}
    curve.add(Evidence("probe", "response_curve", 0.3, math.nan, False, "probe", interval))
    condition = {"confused_with": ["albedo", "exposure"]}
    curve.add(
        Evidence("identifiability", "response_curve", math.nan, math.nan, False, "one", condition)
    )
    stored = Diagnosis(candidates=[curve]).to_json()
    decided = redecide_with(stored)
    assert significant_effects(decided) == ["response_curve"]
    assert decided["candidates"][0]["status"] == "ambiguous"
    assert decided["verdict"].startswith(
        "significant unmodelled effects: response_curve or exposure"
    )
