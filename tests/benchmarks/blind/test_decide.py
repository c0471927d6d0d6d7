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
    stored = _diagnosis()
    fingerprint = {"share": 0.7, "interval": [0.3, 0.9], "coverage": 0.2, "names": "shadows"}
    stored["ranking"].append(
        {
            "effect": "shadows",
            "score": 0.0,
            "heldout_reduction": 0.0,
            "interval": [0.0, 0.0],
            "significant": True,
            "fingerprint": fingerprint,
        }
    )
    assert "shadows" in significant_effects(redecide_with(stored))
    assert "shadows" not in significant_effects(redecide_with(stored, {"visibility_share": 0.5}))
    # Above a share of 0.8 only a shadow is "shadows": 0.7 now names interreflection.
    assert "shadows" not in significant_effects(redecide_with(stored, {"shadow_share": 0.8}))


def test_thresholds_as_a_diagnose_section():
    section = diagnose_section(code_thresholds())["decision"]
    assert section["probe_allowance"]["pose_error"] == 0.108
    assert section["absorption_allowance"]["lens_distortion"] == 0.043
    assert section["relight_allowance"] == 0.03 and section["shadow_share"] == 0.6
    assert set(section["probe_allowance"]) == set(section["absorption_allowance"])
