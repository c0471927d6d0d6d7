"""The model-side effect modules by catalogue name, and building one by name.

Names are the catalogue's (recon.config.run_config.EFFECT_NAMES, which data_synth's world
uses too), shared by configs, outputs and truth files. ``noise`` is in the catalogue but has no module: it is a floor the diagnosis
estimates, never an effect a forward model adds.
"""

from __future__ import annotations

import difflib

from recon.config.run_config import EFFECT_NAMES
from recon.effects.base import ModelEffect
from recon.effects.facts import DiagnosisFacts
from recon.effects.light_transport import Interreflection, Shadows, Specular
from recon.effects.optics import DefocusBlur, LensDistortion, MotionBlur
from recon.effects.photometric import Exposure, ResponseCurve, Vignetting, WhiteBalance
from recon.effects.pose import PoseError
from recon.errors import ReconError

MODEL_EFFECTS: dict[str, type[ModelEffect]] = {
    effect.name: effect
    for effect in (
        Exposure,
        WhiteBalance,
        Vignetting,
        ResponseCurve,
        LensDistortion,
        DefocusBlur,
        MotionBlur,
        PoseError,
        Specular,
        Shadows,
        Interreflection,
    )
}
# Catalogue names with no module (noise: estimated as a floor, never added).
NOT_ADDABLE = tuple(name for name in EFFECT_NAMES if name not in MODEL_EFFECTS)
if set(MODEL_EFFECTS) - set(EFFECT_NAMES) or NOT_ADDABLE != ("noise",):
    raise ImportError(
        "recon.effects: the model effects must be the catalogue's names except noise; got "
        f"{sorted(MODEL_EFFECTS)} against {EFFECT_NAMES}"
    )


def make_effect(name: str, view_count: int | None = None, **options) -> ModelEffect:
    """The effect module called name, at the identity.

    view_count: the number of training views (required by per-view effects: exposure,
        white_balance, motion_blur, pose_error).
    options: learning_rate, lock_fraction, pinned_view (per-view effects) and the effect's own
        (e.g. map_resolution for shadows, iterations for lens_distortion).
    Raises ReconError for noise, an unknown name (suggesting the closest) or bad options.
    """
    if name in NOT_ADDABLE:
        raise ReconError(
            f"effect '{name}' has no model module: it is a floor the diagnosis estimates, "
            "never added to the forward model"
        )
    if name not in MODEL_EFFECTS:
        close = difflib.get_close_matches(str(name), [*MODEL_EFFECTS, *NOT_ADDABLE], n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise ReconError(
            f"unknown effect '{name}'{hint} (model effects: {', '.join(sorted(MODEL_EFFECTS))})"
        )
    effect_class = MODEL_EFFECTS[name]
    try:
        return effect_class(view_count, **options)
    except TypeError as error:
        raise ReconError(f"effect {name}: bad options {sorted(options)}: {error}") from error


def diagnosis_facts(name: str) -> DiagnosisFacts | None:
    """The diagnosis facts of a model effect (recon.effects.facts), or None for a name that is
    no model effect (a base-model mismatch such as view_dependent_reflectance, or noise)."""
    effect = MODEL_EFFECTS.get(name)
    return None if effect is None else effect.diagnosis


def effects_with_evidence(kind: str) -> tuple[str, ...]:
    """The model effects a kind of evidence applies to (their facts list it), in name order."""
    return tuple(
        name for name in sorted(MODEL_EFFECTS) if kind in MODEL_EFFECTS[name].diagnosis.evidence
    )
