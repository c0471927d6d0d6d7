"""Model-side effect modules (identity at zero parameters) and their place in the forward model.

See recon.effects.base for the interface, recon.effects.forward for how a fit uses them and
recon.effects.registry for building one by its catalogue name.
"""

from recon.effects.base import STAGES, ModelEffect
from recon.effects.forward import (
    EffectContext,
    apply_camera_effects,
    apply_image_effects,
    apply_shading_effects,
    render_with_effects,
)
from recon.effects.light_transport import Interreflection, Shadows, Specular, dominant_light
from recon.effects.optics import DefocusBlur, LensDistortion, MotionBlur
from recon.effects.photometric import Exposure, ResponseCurve, Vignetting, WhiteBalance
from recon.effects.pose import PoseError
from recon.effects.registry import MODEL_EFFECTS, make_effect

__all__ = [
    "MODEL_EFFECTS",
    "STAGES",
    "DefocusBlur",
    "EffectContext",
    "Exposure",
    "Interreflection",
    "LensDistortion",
    "ModelEffect",
    "MotionBlur",
    "PoseError",
    "ResponseCurve",
    "Shadows",
    "Specular",
    "Vignetting",
    "WhiteBalance",
    "apply_camera_effects",
    "apply_image_effects",
    "apply_shading_effects",
    "dominant_light",
    "make_effect",
    "render_with_effects",
]
