"""The evaluate stage: the fitted scene against held-out views (and the reference mesh when the
run has one) -> metrics.json and renders/ (target | render | error per view)."""

from __future__ import annotations

import json

import matplotlib
import numpy as np
import torch

from recon.config.run_config import RunConfig
from recon.effects.forward import render_with_effects
from recon.errors import ReconError, warn_user
from recon.io.atomic import atomic_write_json
from recon.io.datasets import held_out_split, read_captures
from recon.io.images import linear_to_srgb, write_png
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.geometry import geometry_metrics, mesh_stats
from recon.metrics.image import image_metrics
from recon.optimize.fit import load_fitted_light
from recon.optimize.material_stage import load_pbr_result
from recon.optimize.scene_model import FitEffects
from recon.render.renderer import Renderer

matplotlib.use("Agg")

VIEWS_PER_BATCH = 4


def render_fitted(paths: RunPaths, cameras, device: torch.device):
    """Premultiplied colour [B, H, W, 3] and alpha [B, H, W, 1] of the fitted scene."""
    mesh = load_mesh(paths.fitted_mesh).to(device)
    lighting = load_fitted_light(paths, device)
    # A run fitted with fit.material: pbr renders with its material maps and environment.
    pbr = load_pbr_result(paths, device)
    effects = load_fitted_effects(paths, device)
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
    return mesh, torch.cat(colors), torch.cat(alphas)


def load_fitted_effects(paths: RunPaths, device: torch.device) -> list:
    """The run's fitted effect modules (RUN/effects.json, written when fit.effects was set), or
    [] when it has none."""
    if not paths.fitted_effects.exists():
        return []
    try:
        data = json.loads(paths.fitted_effects.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ReconError(f"{paths.fitted_effects}: unreadable effects record: {error}") from error
    return FitEffects.modules_from_json(data, device)


# The error panels map |sRGB error| from 0 (black) to this (white) through magma.
ERROR_PANEL_MAXIMUM = 0.25


def error_image(prediction_srgb: torch.Tensor, target_srgb: torch.Tensor) -> torch.Tensor:
    """Absolute sRGB error as a colour-mapped image [H, W, 3] (magma, 0 .. ERROR_PANEL_MAXIMUM)."""
    difference = (prediction_srgb - target_srgb).abs().mean(-1)
    error = difference.clamp(0, ERROR_PANEL_MAXIMUM) / ERROR_PANEL_MAXIMUM
    colored = matplotlib.colormaps["magma"](error.numpy())[..., :3]
    return torch.from_numpy(colored.astype(np.float32))


def evaluate_stage(config: RunConfig, paths: RunPaths, device: torch.device) -> dict:
    """Entry point 'evaluate' of the recon.stages group."""
    if not paths.fitted_mesh.exists():
        raise ReconError(f"evaluate: no fitted mesh at {paths.fitted_mesh} (run the fit stage)")
    split = held_out_split(paths.dataset)
    if split == "val":
        # Legal (a dataset without a test split), but the user must know what was scored.
        warn_user(
            f"{paths.dataset} has no transforms_test.json; evaluating on the 'val' split "
            "instead (metrics.json says split: val)"
        )
    captures = read_captures(paths.dataset, split, config.dataset)
    mesh, colors, alphas = render_fitted(paths, captures.cameras, device)
    background = torch.tensor(config.capture.background)
    prediction = colors + (1 - alphas) * background
    target = captures.images + (1 - captures.masks) * background
    metrics: dict = {"split": split, "views": len(captures.cameras)}
    metrics["image"] = image_metrics(prediction, target, mask=captures.masks)
    metrics["mesh"] = mesh_stats(mesh.to("cpu"))
    if paths.reference_mesh.exists():
        reference = load_mesh(paths.reference_mesh)
        metrics["geometry"] = geometry_metrics(mesh.to("cpu"), reference, exact=True)
    environment = json.loads(paths.environment.read_text()) if paths.environment.exists() else {}
    metrics["stage_seconds"] = environment.get("stage_seconds", {})
    atomic_write_json(paths.metrics, _plain(metrics))

    paths.renders.mkdir(parents=True, exist_ok=True)
    prediction_srgb = linear_to_srgb(prediction.clamp(0, 1))
    target_srgb = linear_to_srgb(target.clamp(0, 1))
    for index, name in enumerate(captures.names):
        panel = torch.cat(
            [
                target[index].clamp(0, 1),
                prediction[index].clamp(0, 1),
                # The error panel is already display-ready: undo the PNG's sRGB encoding.
                _srgb_to_linear_for_png(error_image(prediction_srgb[index], target_srgb[index])),
            ],
            dim=1,
        )
        write_png(paths.renders / f"{split}_{name.replace('/', '_')}.png", panel)
    return {"psnr": metrics["image"]["psnr"]}


def _srgb_to_linear_for_png(image: torch.Tensor) -> torch.Tensor:
    from recon.io.images import srgb_to_linear

    return srgb_to_linear(image)


def _plain(value):
    """JSON-ready: tensors and numpy scalars to Python numbers."""
    if isinstance(value, dict):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, torch.Tensor):
        return value.item() if value.numel() == 1 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
