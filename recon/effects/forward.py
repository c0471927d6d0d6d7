"""Putting effect modules into a forward model: cameras -> render -> shading -> image.

A fit's forward model takes an optional list of effect modules (none by default) and calls the
three functions below around its render; each picks the effects of its own stage from the list
and ignores the rest, so the whole list can be passed to all three:

    cameras = apply_camera_effects(effects, cameras, view_indices)
    output = renderer.render(mesh, cameras, lighting)
    context = EffectContext(mesh, lighting, cameras, view_indices, renderer)
    output = apply_shading_effects(effects, output, context)
    color, alpha = apply_image_effects(effects, output.color, output.alpha, cameras, view_indices)

The image effects run in physical order whatever the list's order: the scene moves during the
exposure (motion blur), the lens blurs and bends the image (defocus, distortion), the sensor's
irradiance falls off (vignetting), the shutter and the illuminant scale it (exposure, white
balance), and the camera's tone curve encodes it (response curve), as in data_synth's world.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from recon.camera import Cameras
from recon.effects.base import STAGES, ModelEffect
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import Lighting

IMAGE_ORDER: tuple[str, ...] = (
    "motion_blur",
    "defocus_blur",
    "lens_distortion",
    "vignetting",
    "exposure",
    "white_balance",
    "response_curve",
)
# Shadows remove direct light first; the bounce and the highlight add on top.
SHADING_ORDER: tuple[str, ...] = ("shadows", "interreflection", "specular")


@dataclass
class EffectContext:
    """What shading effects need besides the render's buffers.

    mesh: the rendered mesh (its verts and faces are the ones rasterised).
    lighting: the fitted light the render was shaded with.
    cameras: the cameras the batch was rendered from (after camera effects).
    view_indices: [B] training view of each batch entry, or None for held-out views.
    renderer: the Renderer used (for effects that render further passes).
    """

    mesh: Mesh
    lighting: Lighting
    cameras: Cameras
    view_indices: torch.Tensor | None = None
    renderer: Renderer | None = None


def _of_stage(
    effects: Sequence[ModelEffect] | None, stage: str, order: tuple[str, ...] | None = None
) -> list[ModelEffect]:
    """The effects of one stage, checked (ModelEffect, each name once), in order."""
    if not effects:
        return []
    names = []
    for effect in effects:
        if not isinstance(effect, ModelEffect):
            raise ReconError(
                f"effects: expected ModelEffect modules (recon.effects.make_effect), got {effect!r}"
            )
        if effect.stage not in STAGES:
            raise ReconError(f"effect {effect.name}: unknown stage '{effect.stage}'")
        names.append(effect.name)
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ReconError(f"effects: each effect may be used once; repeated: {repeated}")
    chosen = [effect for effect in effects if effect.stage == stage]
    if order is not None:
        chosen.sort(
            key=lambda effect: order.index(effect.name) if effect.name in order else len(order)
        )
    return chosen


def apply_camera_effects(
    effects: Sequence[ModelEffect] | None,
    cameras: Cameras,
    view_indices: torch.Tensor | None,
) -> Cameras:
    """The cameras after every 'camera' effect (pose corrections), before rendering."""
    for effect in _of_stage(effects, "camera"):
        cameras = effect.apply_to_cameras(cameras, view_indices)
    return cameras


def apply_shading_effects(
    effects: Sequence[ModelEffect] | None,
    render_output: RenderOutput,
    context: EffectContext,
) -> RenderOutput:
    """The render with every 'shading' effect's change to its colour (other buffers kept)."""
    for effect in _of_stage(effects, "shading", SHADING_ORDER):
        render_output = effect(render_output, context)
    return render_output


def apply_image_effects(
    effects: Sequence[ModelEffect] | None,
    color: torch.Tensor,
    alpha: torch.Tensor,
    cameras: Cameras | None,
    view_indices: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(color [B, H, W, C], alpha [B, H, W, 1]) after every 'image' effect, in IMAGE_ORDER.

    color: linear, premultiplied against black (blur and distortion pad with black and move
    alpha alike). cameras: the batch's cameras (vignetting and distortion need the principal
    point and focal length).
    """
    for effect in _of_stage(effects, "image", IMAGE_ORDER):
        color, alpha = effect(color, alpha, cameras, view_indices)
    return color, alpha


def render_with_effects(
    renderer: Renderer,
    mesh: Mesh,
    cameras: Cameras,
    lighting: Lighting,
    effects: Sequence[ModelEffect] | None = None,
    view_indices: torch.Tensor | None = None,
    **render_options,
) -> RenderOutput:
    """Renderer.render with the effects around it: a RenderOutput whose color and alpha are the
    final image (cameras corrected, shading changed, image effects applied)."""
    cameras = apply_camera_effects(effects, cameras, view_indices)
    output = renderer.render(mesh, cameras, lighting, **render_options)
    context = EffectContext(mesh, lighting, cameras, view_indices, renderer)
    output = apply_shading_effects(effects, output, context)
    color, alpha = apply_image_effects(effects, output.color, output.alpha, cameras, view_indices)
    return replace(output, color=color, alpha=alpha)
