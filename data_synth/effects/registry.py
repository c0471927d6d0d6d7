"""The world's image effects by name, and applying a set of them in physical order.

Light-transport effects (specular, shadows, interreflection) are not image effects: they happen
while rendering (data_synth.effects.light_transport and the Mitsuba backend), so they are not in
WORLD_EFFECTS; make_world_effect refuses them and apply_effects skips them (the caller renders
them).

Order: STAGE_ORDER (camera < optics < sensor < response), then APPLICATION_ORDER within a stage.
Supersampling: a capture rendered above the output resolution (Capture.pixel_scale > 1) takes
the effects that act on the optical image first (ImageEffect.supersampled: a lens distortion),
is then averaged down to the output pixels, and takes the rest in order. A blur drawn before
a distortion in APPLICATION_ORDER then comes after it: the two commute but for the local
scale the distortion gives the blur's kernel (a few per cent at the corners).

Randomness: apply_effects draws one base seed from the generator, then gives each effect its own
generator seeded from that base and the effect's name, so an effect's realised values (e.g. the
exposure ratios) do not change when another effect is switched on or off, and the same
generator state gives the same result.
"""

from __future__ import annotations

import difflib
import zlib
from collections.abc import Mapping, Sequence

import torch

from data_synth.effects.base import (
    LIGHT_TRANSPORT,
    STAGE_ORDER,
    AppliedEffect,
    Capture,
    ImageEffect,
)
from data_synth.effects.camera import PoseError
from data_synth.effects.optics import DefocusBlur, LensDistortion, MotionBlur, Vignetting
from data_synth.effects.response import ResponseCurve
from data_synth.effects.sensor import Exposure, Noise, WhiteBalance
from data_synth.effects.world_effect import WorldEffect
from recon.errors import ReconError

WORLD_EFFECTS: dict[str, type[WorldEffect]] = {
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
        Noise,
    )
}

# Within a stage: the scene moves during the exposure (motion blur) before the lens blurs and
# bends the image; vignetting dims the sensor-fixed irradiance last; the shutter and the
# illuminant colour set the light before the photosites add shot and read noise.
APPLICATION_ORDER: tuple[str, ...] = (
    "pose_error",
    "motion_blur",
    "defocus_blur",
    "lens_distortion",
    "vignetting",
    "exposure",
    "white_balance",
    "noise",
    "response_curve",
)


def make_world_effect(name: str, parameters: Mapping[str, object] | None = None) -> WorldEffect:
    """The world effect called name built from its strength parameters (defaults fill gaps).

    Raises ReconError for a light-transport name (rendered, not an image effect), an unknown
    name (with the closest known one) or bad parameters.
    """
    if name in LIGHT_TRANSPORT:
        raise ReconError(
            f"effect {name}: a light-transport effect is rendered (data_synth.effects."
            "light_transport / the Mitsuba backend), not applied to images"
        )
    if name not in WORLD_EFFECTS:
        close = difflib.get_close_matches(str(name), [*WORLD_EFFECTS, *LIGHT_TRANSPORT], n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise ReconError(
            f"unknown effect '{name}'{hint} (image effects: {', '.join(sorted(WORLD_EFFECTS))})"
        )
    return WORLD_EFFECTS[name](parameters)


def _order_key(effect: ImageEffect) -> tuple[int, int]:
    stage = STAGE_ORDER.index(effect.stage)
    within = (
        APPLICATION_ORDER.index(effect.name)
        if effect.name in APPLICATION_ORDER
        else len(APPLICATION_ORDER)
    )
    return stage, within


def effect_generator(base_seed: int, name: str, device: torch.device | str) -> torch.Generator:
    """The generator one effect draws from: seeded from the call's base seed and its name."""
    seed = (base_seed + zlib.crc32(name.encode())) % (2**63 - 1)
    return torch.Generator(device=device).manual_seed(seed)


def apply_effects(
    capture: Capture,
    effects: Sequence[ImageEffect | tuple[str, Mapping[str, object]]],
    generator: torch.Generator,
) -> list[AppliedEffect]:
    """Apply image effects to capture in physical order (in place); returns what was realised.

    effects: ImageEffect instances (e.g. from make_world_effect) or (name, parameters) pairs.
        Light-transport entries (a name in LIGHT_TRANSPORT or stage "light_transport") are
        skipped: the caller renders them. A name may appear once.
    generator: consumed for one base seed per call (see the module docstring).
    Returns the AppliedEffect of each applied effect, in application order.
    """
    built: list[ImageEffect] = []
    for effect in effects:
        if isinstance(effect, tuple):
            name, parameters = effect
            if name in LIGHT_TRANSPORT:
                continue
            effect = make_world_effect(name, parameters)
        if effect.name in LIGHT_TRANSPORT or effect.stage == "light_transport":
            continue
        if effect.stage not in STAGE_ORDER:
            raise ReconError(
                f"effect {effect.name}: unknown stage '{effect.stage}' (expected one of {STAGE_ORDER})"
            )
        built.append(effect)
    names = [effect.name for effect in built]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ReconError(f"effects: each effect may be applied once; repeated: {repeated}")
    base_seed = int(torch.randint(0, 2**62, (), generator=generator, device=generator.device))
    ordered = sorted(built, key=_order_key)
    if capture.pixel_scale > 1:
        # The optical image's effects first, on the supersampled capture (a stable sort).
        ordered.sort(key=lambda effect: not getattr(effect, "supersampled", False))
    applied = []
    for effect in ordered:
        if capture.pixel_scale > 1 and not getattr(effect, "supersampled", False):
            average_down(capture)
        own_generator = effect_generator(base_seed, effect.name, generator.device)
        applied.append(effect.apply(capture, own_generator))
    average_down(capture)
    return applied


def average_down(capture: Capture) -> None:
    """A supersampled capture (Capture.pixel_scale s > 1) in place at its output resolution:
    each output pixel averages its s x s samples of the premultiplied colour and the coverage
    (as a sensor integrates the optical image over its photosite), and the cameras take the
    output size. A capture at its output resolution is left as it is."""
    scale = capture.pixel_scale
    if scale <= 1:
        return
    count, height, width = capture.images.shape[:3]
    if height % scale or width % scale:
        raise ReconError(
            f"average_down: capture of {height}x{width} px is not a whole multiple of its "
            f"pixel_scale {scale}"
        )
    stacked = torch.cat([capture.images, capture.alpha], dim=-1).permute(0, 3, 1, 2)
    averaged = torch.nn.functional.avg_pool2d(stacked, scale).permute(0, 2, 3, 1)
    capture.images = averaged[..., :3].contiguous()
    capture.alpha = averaged[..., 3:].clamp(0.0, 1.0).contiguous()
    capture.cameras = capture.cameras.with_image_size((height // scale, width // scale))
    capture.pixel_scale = 1
