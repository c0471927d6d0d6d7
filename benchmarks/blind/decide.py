"""The diagnosis' decision thresholds as one flat dict, and stored evidence re-decided with them.

A threshold set maps names to values:

    probe.<effect>        the held-out reduction a probe's bootstrap lower bound must clear
    absorption.<effect>   the reduction over the control refit an absorption bound must clear
    agreement.<effect>    the per-view colour spread separate halves of each view must share
    lobe.<effect>         the partial correlation of the view-to-view residual with a lobe
    beyond.<effect>       the reduction a geometric probe must keep on top of every confuser's
    relight               the relight probe's allowance
    flat_field            the flat-field deviation that makes vignetting significant
    fingerprint           the visibility fingerprint's excess over its placebo lights that makes it
                          name an effect
    shadow_share          above this share the fingerprint names shadows, below interreflection
    bounce                the bounce evidence's excess over its placebo suns that names
                          interreflection

``code_thresholds()`` is the set the diagnosis uses by default (the ``diagnose.decision``
section's defaults, resolved per effect); ``diagnose_section(thresholds)`` is the same set as a
``diagnose:`` config section, and ``redecide_with(diagnosis, thresholds)`` re-decides a stored
diagnosis.json with it through the diagnosis' own ``redecide`` (the evidence is kept).
"""

from __future__ import annotations

from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.effects.registry import MODEL_EFFECTS


def code_thresholds(config: DecisionConfig | None = None) -> dict[str, float]:
    """The thresholds of a decision config (default: the diagnosis' defaults), per effect."""
    from recon.diagnose.decision import (
        absorption_threshold,
        agreement_threshold,
        beyond_threshold,
        lobe_threshold,
        probe_threshold,
    )

    config = config or DecisionConfig()
    thresholds: dict[str, float] = {}
    for effect in sorted(MODEL_EFFECTS):
        thresholds[f"probe.{effect}"] = probe_threshold(effect, config)
        thresholds[f"absorption.{effect}"] = absorption_threshold(effect, config)
    # The effects with agreement evidence are the default config's (white_balance).
    for effect in sorted(DecisionConfig().agreement_allowance):
        thresholds[f"agreement.{effect}"] = agreement_threshold(effect, config)
    # The effects with lobe evidence are the default config's (specular).
    for effect in sorted(DecisionConfig().lobe_allowance):
        thresholds[f"lobe.{effect}"] = lobe_threshold(effect, config)
    # The effects with geometric pair records are the default config's (the four geometric ones).
    for effect in sorted(DecisionConfig().beyond_confusers_allowance):
        thresholds[f"beyond.{effect}"] = beyond_threshold(effect, config)
    thresholds["relight"] = config.relight_allowance
    thresholds["flat_field"] = config.flat_field_allowance
    thresholds["fingerprint"] = config.fingerprint_minimum
    thresholds["shadow_share"] = config.shadow_share
    thresholds["bounce"] = config.bounce_minimum
    return thresholds


def diagnose_section(thresholds: dict[str, float]) -> dict:
    """thresholds as a run config's ``diagnose:`` section (its ``decision`` allowances, as the
    diagnosis reads them): every probe and absorption threshold per effect, the relight,
    flat-field, fingerprint, shadow-share and bounce values."""

    def per_effect(prefix: str) -> dict[str, float]:
        return {
            name.split(".", 1)[1]: value
            for name, value in sorted(thresholds.items())
            if name.startswith(prefix + ".")
        }

    return {
        "decision": {
            "probe_allowance": per_effect("probe"),
            "absorption_allowance": per_effect("absorption"),
            "agreement_allowance": per_effect("agreement"),
            "lobe_allowance": per_effect("lobe"),
            "beyond_confusers_allowance": per_effect("beyond"),
            "relight_allowance": thresholds["relight"],
            "flat_field_allowance": thresholds["flat_field"],
            "fingerprint_minimum": thresholds["fingerprint"],
            "shadow_share": thresholds["shadow_share"],
            "bounce_minimum": thresholds["bounce"],
        }
    }


def diagnose_config(thresholds: dict[str, float]) -> DiagnoseConfig:
    """A DiagnoseConfig deciding with thresholds (every other setting at its default)."""
    # Per-effect allowances are resolved values: their floors must not raise them again.
    decision = DecisionConfig(
        **diagnose_section(thresholds)["decision"],
        minimum_share=0.0,
        absorption_minimum_share=0.0,
        regression_minimum_share=0.0,
        agreement_minimum=0.0,
        lobe_minimum=0.0,
    )
    return DiagnoseConfig(decision=decision)


def redecide_with(diagnosis: dict, thresholds: dict[str, float] | None = None) -> dict:
    """diagnosis (a stored diagnosis.json, either schema) re-decided with thresholds (None: the
    defaults); returns the re-decided diagnosis as JSON."""
    from recon.diagnose.decision import redecide

    thresholds = {**code_thresholds(), **(thresholds or {})}
    return redecide(diagnosis, diagnose_config(thresholds)).to_json()


def significant_effects(diagnosis: dict) -> list[str]:
    """The significant candidates of a (re-decided) diagnosis, strongest first."""
    return [item["name"] for item in diagnosis["candidates"] if item["significant"]]
