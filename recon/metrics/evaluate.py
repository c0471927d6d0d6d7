"""The fitted scene against held-out views: renders, metrics and the comparison panels.

The evaluate stage (recon/stages/evaluate.py) reads the run folder, calls these and writes
metrics.json and renders/.
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib
import numpy as np
import torch

from recon.effects.base import ModelEffect
from recon.effects.forward import render_with_effects
from recon.io.images import linear_to_srgb, srgb_to_linear
from recon.mesh.mesh import Mesh
from recon.metrics.geometry import geometry_metrics, mesh_stats
from recon.metrics.image import image_metrics
from recon.optimize.material_stage import PbrTextureResult
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

matplotlib.use("Agg")

VIEWS_PER_BATCH = 4


def render_scene(
    mesh: Mesh,
    lighting: Lighting,
    pbr: PbrTextureResult | None,
    cameras,
    device: torch.device,
    effects: Sequence[ModelEffect] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied colour [B, H, W, 3] and alpha [B, H, W, 1] of a fitted scene (on the CPU).

    A fit with fit.material 'pbr' (pbr given) renders with its material maps and environment;
    otherwise the mesh's texture under lighting, with the fit's effect modules (fit.effects:
    a specular lobe, shadows) when it had any.
    """
    mesh = mesh.to(device)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    colors, alphas = [], []
    with torch.no_grad():
        for start in range(0, len(cameras), VIEWS_PER_BATCH):
            batch = cameras[start : start + VIEWS_PER_BATCH].to(device)
            if pbr is not None:
                output = pbr.render(renderer, batch)
            else:
                # Held-out views have no per-view effect parameters (view_indices None: the
                # training views' typical value).
                output = render_with_effects(renderer, mesh, batch, lighting, effects)
            colors.append(output.color.cpu())
            alphas.append(output.alpha.cpu())
    return torch.cat(colors), torch.cat(alphas)


def heldout_metrics(
    prediction: torch.Tensor,
    target: torch.Tensor,
    masks: torch.Tensor,
    mesh: Mesh,
    reference: Mesh | None = None,
) -> dict:
    """Image metrics of prediction vs target [B, H, W, 3] (both over the background; masks
    [B, H, W, 1]), the mesh's statistics and, with a reference mesh, the geometry metrics."""
    metrics: dict = {"image": image_metrics(prediction, target, mask=masks)}
    metrics["mesh"] = mesh_stats(mesh.to("cpu"))
    if reference is not None:
        metrics["geometry"] = geometry_metrics(mesh.to("cpu"), reference, exact=True)
    return metrics


# The error panels map |sRGB error| from 0 (black) to this (white) through magma.
ERROR_PANEL_MAXIMUM = 0.25


def error_image(prediction_srgb: torch.Tensor, target_srgb: torch.Tensor) -> torch.Tensor:
    """Absolute sRGB error as a colour-mapped image [H, W, 3] (magma, 0 .. ERROR_PANEL_MAXIMUM)."""
    difference = (prediction_srgb - target_srgb).abs().mean(-1)
    error = difference.clamp(0, ERROR_PANEL_MAXIMUM) / ERROR_PANEL_MAXIMUM
    colored = matplotlib.colormaps["magma"](error.numpy())[..., :3]
    return torch.from_numpy(colored.astype(np.float32))


def comparison_panels(prediction: torch.Tensor, target: torch.Tensor) -> list[torch.Tensor]:
    """One linear panel [H, 3 W, 3] per view of prediction and target [B, H, W, 3]: target |
    render | absolute sRGB error (write_png encodes them to sRGB)."""
    prediction_srgb = linear_to_srgb(prediction.clamp(0, 1))
    target_srgb = linear_to_srgb(target.clamp(0, 1))
    panels = []
    for index in range(len(prediction)):
        panel = torch.cat(
            [
                target[index].clamp(0, 1),
                prediction[index].clamp(0, 1),
                # The error panel is already display-ready: undo the PNG's sRGB encoding.
                srgb_to_linear(error_image(prediction_srgb[index], target_srgb[index])),
            ],
            dim=1,
        )
        panels.append(panel)
    return panels


def plain_json(value):
    """JSON-ready: tensors and numpy scalars to Python numbers, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(key): plain_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(item) for item in value]
    if isinstance(value, torch.Tensor):
        return value.item() if value.numel() == 1 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
