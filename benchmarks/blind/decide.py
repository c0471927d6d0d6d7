"""The diagnosis' decision thresholds as one flat dict, and stored evidence re-decided with them.

A threshold set maps names to values:

    probe.<effect>        the held-out reduction a probe's bootstrap lower bound must clear
    absorption.<effect>   the reduction over the control refit an absorption bound must clear
    relight               the relight probe's allowance
    flat_field            the flat-field deviation that makes vignetting significant
    visibility_share      the visibility fingerprint's lower bound that makes it name an effect
    shadow_share          above this share the fingerprint names shadows, below interreflection

``code_thresholds()`` is the set the diagnosis uses today (recon.diagnose.calibration);
``redecide_with(diagnosis, thresholds)`` re-decides a stored diagnosis.json with another set,
keeping its evidence. The diagnosis engine's ``redecide(diagnosis, diagnose_config)`` takes the
same evidence with a ``diagnose:`` config section; until it lands on main this module swaps the
thresholds of recon.diagnose.which for the duration of one call (recon.diagnose is not edited
from the benchmarks).
"""

from __future__ import annotations

import contextlib
import copy
import threading
from collections.abc import Iterator

from recon.effects.registry import MODEL_EFFECTS

_LOCK = threading.Lock()


def code_thresholds() -> dict[str, float]:
    """The thresholds recon.diagnose uses today, resolved per effect."""
    from recon.diagnose import calibration, flat_field

    thresholds: dict[str, float] = {}
    for effect in sorted(MODEL_EFFECTS):
        thresholds[f"probe.{effect}"] = calibration.probe_threshold(effect)
        thresholds[f"absorption.{effect}"] = calibration.absorption_threshold(effect)
    thresholds["relight"] = calibration.RELIGHT_ALLOWANCE
    thresholds["flat_field"] = flat_field.FLAT_FIELD_ALLOWANCE
    thresholds["visibility_share"] = calibration.VISIBILITY_SHARE_MINIMUM
    thresholds["shadow_share"] = calibration.SHADOW_SHARE
    return thresholds


@contextlib.contextmanager
def _thresholds_of_which(thresholds: dict[str, float]) -> Iterator[None]:
    """recon.diagnose.which deciding with thresholds (restored afterwards)."""
    from recon.diagnose import which

    saved = {
        name: getattr(which, name)
        for name in (
            "probe_threshold",
            "absorption_threshold",
            "RELIGHT_ALLOWANCE",
            "FLAT_FIELD_ALLOWANCE",
        )
    }
    with _LOCK:
        which.probe_threshold = lambda effect: thresholds[f"probe.{effect}"]
        which.absorption_threshold = lambda effect: thresholds[f"absorption.{effect}"]
        which.RELIGHT_ALLOWANCE = thresholds["relight"]
        which.FLAT_FIELD_ALLOWANCE = thresholds["flat_field"]
        try:
            yield
        finally:
            for name, value in saved.items():
                setattr(which, name, value)


def _fingerprint_names(fingerprint: dict, thresholds: dict[str, float]) -> str | None:
    """The effect the visibility fingerprint names under thresholds (None: not significant)."""
    from recon.diagnose.fingerprint import MINIMUM_COVERAGE

    testable = fingerprint.get("coverage", 0.0) >= MINIMUM_COVERAGE
    if not (testable and fingerprint["interval"][0] > thresholds["visibility_share"]):
        return None
    return "shadows" if fingerprint["share"] >= thresholds["shadow_share"] else "interreflection"


def redecide_with(diagnosis: dict, thresholds: dict[str, float] | None = None) -> dict:
    """diagnosis (a stored diagnosis.json) re-decided with thresholds (None: the code's);
    returns a new dict with the ranking re-sorted and the verdict rewritten."""
    from recon.diagnose.which import redecide

    thresholds = {**code_thresholds(), **(thresholds or {})}
    diagnosis = copy.deepcopy(diagnosis)
    for item in diagnosis["ranking"]:
        if item.get("fingerprint"):
            item["fingerprint"]["names"] = _fingerprint_names(item["fingerprint"], thresholds)
    with _thresholds_of_which(thresholds):
        return redecide(diagnosis)


def diagnose_section(thresholds: dict[str, float]) -> dict:
    """thresholds in the shape of a run config's ``diagnose:`` section (its ``decision``
    allowances, as the diagnosis engine reads them): every probe and absorption threshold per
    effect, the relight, flat-field, fingerprint and shadow-share values."""

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
            "relight_allowance": thresholds["relight"],
            "flat_field_allowance": thresholds["flat_field"],
            "visibility_share_minimum": thresholds["visibility_share"],
            "shadow_share": thresholds["shadow_share"],
        }
    }


def significant_effects(diagnosis: dict) -> list[str]:
    """The significant effects of a (re-decided) diagnosis, strongest first."""
    return [item["effect"] for item in diagnosis["ranking"] if item["significant"]]
