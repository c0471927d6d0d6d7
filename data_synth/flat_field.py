"""Flat-field frames: the capture camera imaging a uniformly lit card that fills the frame.

This is how a vignetting falloff is calibrated in practice, and the one measurement of it that
reaches the image corners: an object in the middle of the frame covers only part of the way out
(on the benchmark 0.57-0.61 of the half diagonal), and a falloff beyond that is invisible on it.

The frames go through the same camera chain as the views with the same effect parameters: the
card's radiance is uniform, so of the camera and optics effects only vignetting changes it (an
infinite uniform field shifted by a pose error, bent by a lens or blurred is the same field), and
the sensor and response effects act as on any pixel. Light transport does not apply (the card is
lit by its own lamp). The frames draw their cameras and their per-frame effect values (exposure,
white balance, noise) from their own seeded streams, so adding them moves nothing in the views.
"""

from __future__ import annotations

from pathlib import Path

import torch

from data_synth.calibration_splits import write_frames
from data_synth.effects.base import LIGHT_TRANSPORT, Capture
from data_synth.rigs import make_cameras
from recon.config.run_config import CaptureConfig, EffectConfig
from recon.io.datasets import FLAT_FIELD_SPLIT

# A uniform radiance field is unchanged by these.
UNIFORM_INVARIANT = ("pose_error", "lens_distortion", "defocus_blur", "motion_blur")
# Offsets from the run seed for the frames' own streams (primes, apart from the stage's).
CAMERA_SEED_OFFSET = 15485863
EFFECT_SEED_OFFSET = 32452843


def flat_field_capture(
    capture_config: CaptureConfig, effects: list[EffectConfig], seed: int
) -> tuple[Capture, list[dict]]:
    """capture_config.flat_field.views frames of the uniform card through effects.

    Returns the capture (images [N, H, W, 3] linear, alpha [N, H, W, 1] all 1) and the realised
    parameters of the effects that touched it ({"name", "parameters"} each)."""
    from data_synth.effects.registry import apply_effects, make_world_effect

    settings = capture_config.flat_field
    count = int(settings.views)
    cameras = make_cameras(
        capture_config.cameras, count, torch.Generator().manual_seed(seed + CAMERA_SEED_OFFSET)
    )
    height, width = cameras.image_size
    images = torch.full((count, height, width, 3), float(settings.radiance))
    capture = Capture(images, torch.ones(count, height, width, 1), cameras)
    chosen = [
        make_world_effect(effect.name, dict(effect.parameters))
        for effect in effects
        if effect.name not in LIGHT_TRANSPORT and effect.name not in UNIFORM_INVARIANT
    ]
    if not chosen or count == 0:
        return capture, []
    generator = torch.Generator().manual_seed(seed + EFFECT_SEED_OFFSET)
    applied = apply_effects(capture, chosen, generator)
    return capture, [{"name": item.name, "parameters": item.parameters} for item in applied]


def write_flat_field(
    dataset: Path,
    capture_config: CaptureConfig,
    effects: list[EffectConfig],
    seed: int,
    force: bool = False,
) -> list[dict]:
    """Write the flat-field split into dataset (NeRF-synthetic layout, linear EXR beside the
    8-bit PNG when the capture writes EXR; an existing split only with force); returns the
    realised effect parameters."""
    capture, realised = flat_field_capture(capture_config, effects, seed)
    write_frames(dataset, FLAT_FIELD_SPLIT, capture, capture_config.write_exr, force)
    return realised
