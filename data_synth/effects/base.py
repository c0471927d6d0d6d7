"""The interface every world-side effect implements, and the catalogue of names.

An effect is applied at one point of the physical capture chain, in this order:

1. light transport (while rendering: specular, shadows, interreflection; the Mitsuba backend),
2. optics (lens_distortion, defocus_blur, motion_blur, vignetting) on linear radiance,
3. sensor (exposure, white_balance, noise) on linear radiance,
4. response (response_curve): the camera's tone curve instead of the standard sRGB encoding,
5. quantisation (8-bit PNG, at write time).

pose_error is a camera effect: the captures are rendered from the true cameras but the dataset
records perturbed ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol

import torch

from recon.camera import Cameras
from recon.config.run_config import EFFECT_NAMES

# The names are part of the interface (config, output and truth files): defined once, in the
# config schema.
CATALOGUE = EFFECT_NAMES
# Effects a forward model can add (noise is a floor the diagnosis estimates, never "added").
ADDABLE = tuple(name for name in CATALOGUE if name != "noise")
LIGHT_TRANSPORT = ("specular", "shadows", "interreflection")

Stage = Literal["light_transport", "camera", "optics", "sensor", "response"]
STAGE_ORDER: tuple[Stage, ...] = ("light_transport", "camera", "optics", "sensor", "response")


@dataclass
class Capture:
    """What the effects act on, for one split.

    images: [B, H, W, 3] linear radiance, premultiplied by coverage (background 0).
    alpha: [B, H, W, 1] coverage.
    cameras: the cameras written to the dataset (pose_error replaces them).
    pixel_scale: samples per output pixel side: a capture rendered above the dataset's
        resolution for the effects that act on the optical image (ImageEffect.supersampled;
        registry.apply_effects averages it down after them). Pixel-sized quantities an effect
        reports are in output pixels.
    """

    images: torch.Tensor
    alpha: torch.Tensor
    cameras: Cameras
    pixel_scale: int = 1


@dataclass
class AppliedEffect:
    """What was injected: the effect name and its realised parameters (JSON-ready)."""

    name: str
    parameters: dict = field(default_factory=dict)


class ImageEffect(Protocol):
    """A world-side effect. Instances are built from (name, strength parameters)."""

    name: str
    stage: Stage
    # Whether it acts on the optical image before the sensor integrates it, so that a capture
    # rendered above the output resolution (Capture.pixel_scale) takes it before being averaged
    # down (registry.apply_effects). Effects without the attribute act on output pixels.
    supersampled: bool

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """Modify capture in place (images, alpha, cameras) and return what was realised
        (e.g. the per-view exposure ratios drawn from the configured spread)."""
        ...
