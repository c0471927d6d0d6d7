"""Line-target frames: the capture camera imaging a card of straight stripes that fills the frame.

This is the plumb-line calibration of a lens (Brown's method): a pinhole camera images every
straight line as a straight line whatever the card's pose, so whatever bends the stripes' edges is
the lens. It is the one measurement of a distortion that reaches the image corners, where it is
largest; an object in the middle of the frame covers only the part of the field where a radial
distortion is nearly a zoom, which the fit's geometry absorbs.

The card is a plane at unit distance along its normal, tilted from facing the camera by up to
capture.line_target.tilt_deg per axis, its stripes horizontal in even frames and vertical in odd
ones (turned by up to 10 degrees), their period capture.line_target.period_pixels at the image
centre. The frames are box-filtered by rendering the card analytically at
capture.line_target.supersampling times the resolution per side, so that a lens distortion bends
the optical image before the sensor integrates it (as for the views,
data_synth.effects.registry.apply_effects), and go through the same camera chain as the views with
the same effect parameters: exposure, white balance, vignetting, response, blur and noise act as on
any frame. A pose error moves the card, not the lines' straightness, and light transport does not
apply (the card is lit by its own lamp). The frames draw their cameras, cards and per-frame effect
values from their own seeded streams, so adding them moves nothing in the views.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import torch

from data_synth.calibration_splits import write_frames
from data_synth.effects.base import LIGHT_TRANSPORT, Capture
from data_synth.rigs import make_cameras
from recon.camera import Cameras
from recon.config.run_config import CaptureConfig, EffectConfig, LineTargetConfig
from recon.io.datasets import LINE_TARGET_SPLIT

# A pose error moves the card; its lines stay straight.
LINE_INVARIANT = ("pose_error",)
# Offsets from the run seed for the frames' own streams (primes, apart from the stage's and the
# flat field's).
CAMERA_SEED_OFFSET = 49979687
CARD_SEED_OFFSET = 67867967
EFFECT_SEED_OFFSET = 86028121
# How far the stripes turn from horizontal or vertical, in degrees: the two families stay apart.
STRIPE_TURN_DEG = 10.0
# The card's margin beyond the frame, per side, as a share of the larger image side: more than
# the largest displacement the sampler draws at the corners (a fifth of the corner radius).
MARGIN_SHARE = 0.25


def _rotation(about_x: float, about_y: float) -> torch.Tensor:
    """[3, 3] rotation by about_y (radians) about y after about_x about x."""
    cx, sx, cy, sy = math.cos(about_x), math.sin(about_x), math.cos(about_y), math.sin(about_y)
    rotate_x = torch.tensor([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]], dtype=torch.float64)
    rotate_y = torch.tensor([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]], dtype=torch.float64)
    return rotate_y @ rotate_x


def stripe_card(
    cameras: Cameras, settings: LineTargetConfig, period_pixels: float, generator: torch.Generator
) -> tuple[torch.Tensor, list[dict]]:
    """Radiance [N, H, W, 3] of the striped card seen by each camera (pinhole, one sample at each
    pixel centre of cameras' image size), and each card's pose and stripes. period_pixels: the
    stripes' period at the image centre in pixels of these cameras.

    Camera space is OpenCV's (x right, y down, z forward); a pixel (u, v) (centres at i + 0.5)
    looks along ((u - cx) / fx, (v - cy) / fy, 1)."""
    height, width = cameras.image_size
    intrinsics = cameras.intrinsics.double()
    rows = torch.arange(height, dtype=torch.float64) + 0.5
    columns = torch.arange(width, dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(rows, columns, indexing="ij")
    images, cards = [], []
    tilt = math.radians(settings.tilt_deg)
    for index in range(len(cameras)):
        fx, fy = float(intrinsics[index, 0, 0]), float(intrinsics[index, 1, 1])
        cx, cy = float(intrinsics[index, 0, 2]), float(intrinsics[index, 1, 2])
        draws = torch.rand(4, generator=generator, dtype=torch.float64).tolist()
        about_x, about_y = ((2 * draw - 1) * tilt for draw in draws[:2])
        turn = math.radians((2 * draws[2] - 1) * STRIPE_TURN_DEG)
        # Even frames: horizontal stripes (the pattern varies along the card's second axis).
        angle = turn + (math.pi / 2 if index % 2 == 0 else 0.0)
        rotation = _rotation(about_x, about_y)
        normal, first_axis, second_axis = rotation[:, 2], rotation[:, 0], rotation[:, 1]
        rays = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)
        # The card: points p with normal . p = 1 (unit distance along its normal).
        hits = rays / (rays @ normal)[..., None]
        along = math.cos(angle) * (hits @ first_axis) + math.sin(angle) * (hits @ second_axis)
        # One unit on the card at unit distance spans about fx pixels at the image centre.
        period = period_pixels / fx
        phase = draws[3]
        white = torch.remainder(along / period + phase, 1.0) < 0.5
        level = torch.where(white, 1.0, settings.dark_share) * settings.radiance
        images.append(level[..., None].expand(height, width, 3))
        cards.append(
            {
                "tilt_deg": [round(math.degrees(about_x), 4), round(math.degrees(about_y), 4)],
                "stripe_angle_deg": round(math.degrees(angle), 4),
                "phase": round(phase, 6),
            }
        )
    return torch.stack(images).float(), cards


def line_target_capture(
    capture_config: CaptureConfig, effects: list[EffectConfig], seed: int
) -> tuple[Capture, list[dict], list[dict]]:
    """capture_config.line_target.views frames of the striped card through effects.

    Returns the capture (images [N, H, W, 3] linear at the output resolution, alpha [N, H, W, 1]
    all 1), the realised parameters of the effects that touched it ({"name", "parameters"} each)
    and each card's pose and stripes."""
    from data_synth.effects.registry import apply_effects, average_down, make_world_effect

    settings = capture_config.line_target
    count = int(settings.views)
    cameras = make_cameras(
        capture_config.cameras, count, torch.Generator().manual_seed(seed + CAMERA_SEED_OFFSET)
    )
    height, width = cameras.image_size
    scale = int(settings.supersampling)
    # The card is rendered beyond the frame by a margin, so that a lens pulls card, not
    # nothing, into the corners; the margin is cropped once the lens has bent the image.
    margin = math.ceil(MARGIN_SHARE * max(height, width))
    intrinsics = cameras.intrinsics.clone()
    intrinsics[:, 0, 2] += margin
    intrinsics[:, 1, 2] += margin
    padded = replace(
        cameras, intrinsics=intrinsics, image_size=(height + 2 * margin, width + 2 * margin)
    )
    fine = padded.with_image_size(((height + 2 * margin) * scale, (width + 2 * margin) * scale))
    radiance, cards = stripe_card(
        fine,
        settings,
        settings.period_pixels * scale,
        torch.Generator().manual_seed(seed + CARD_SEED_OFFSET),
    )
    chosen = [
        make_world_effect(effect.name, dict(effect.parameters))
        for effect in effects
        if effect.name not in LIGHT_TRANSPORT and effect.name not in LINE_INVARIANT
    ]
    optical = [effect for effect in chosen if getattr(effect, "supersampled", False)]
    generator = torch.Generator().manual_seed(seed + EFFECT_SEED_OFFSET)
    capture = Capture(radiance, torch.ones(*radiance.shape[:3], 1), fine, pixel_scale=scale)
    applied = apply_effects(capture, optical, generator) if optical else []
    average_down(capture)
    capture.images = capture.images[
        :, margin : margin + height, margin : margin + width
    ].contiguous()
    capture.alpha = torch.ones(count, height, width, 1)
    capture.cameras = cameras
    rest = [effect for effect in chosen if not getattr(effect, "supersampled", False)]
    if rest and count:
        applied += apply_effects(capture, rest, generator)
    realised = [{"name": item.name, "parameters": item.parameters} for item in applied]
    return capture, realised, cards


def write_line_target(
    dataset: Path,
    capture_config: CaptureConfig,
    effects: list[EffectConfig],
    seed: int,
    force: bool = False,
) -> list[dict]:
    """Write the line-target split into dataset (NeRF-synthetic layout, linear EXR beside the
    8-bit PNG when the capture writes EXR; an existing split only with force); returns the
    realised effect parameters."""
    capture, realised, _ = line_target_capture(capture_config, effects, seed)
    write_frames(dataset, LINE_TARGET_SPLIT, capture, capture_config.write_exr, force)
    return realised
