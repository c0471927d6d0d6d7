"""The evaluate stage: the fitted scene against the held-out views (and the reference mesh when
the run has one) -> metrics.json and renders/ (target | render | error per view)."""

from __future__ import annotations

import json

import torch

from recon.config.run_config import RunConfig
from recon.errors import ReconError, warn_user
from recon.io.atomic import atomic_write_json
from recon.io.datasets import read_captures
from recon.io.images import write_png
from recon.io.meshes import load_material_maps, load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import comparison_panels, heldout_metrics, plain_json, render_scene
from recon.metrics.material import material_metrics
from recon.stages.fitted_scene import load_fitted_scene


def evaluate_stage(config: RunConfig, paths: RunPaths, device: torch.device) -> dict:
    """Stage 'evaluate': metrics.json (split, views, image, mesh, geometry, material,
    stage_seconds) and one comparison panel per held-out view. `material` (the fitted
    roughness/metalness against the true maps over the surface) is there only for a `pbr` fit
    whose reference mesh carries its true maps (a synthetic glossy world)."""
    if not paths.fitted_mesh.exists():
        raise ReconError(f"evaluate: no fitted mesh at {paths.fitted_mesh} (run the fit stage)")
    layout = paths.dataset_layout
    split = layout.held_out_split
    if split == "val":
        # Legal (a dataset without a test split), but the user must know what was scored.
        warn_user(
            f"{paths.dataset} has no {layout.split_file('test').name}; evaluating on the 'val' "
            "split instead (metrics.json says split: val)"
        )
    captures = read_captures(paths.dataset, split, config.dataset)
    scene = load_fitted_scene(paths, device)
    colors, alphas = render_scene(
        scene.mesh, scene.lighting, scene.pbr, captures.cameras, device, scene.effects
    )
    background = torch.tensor(config.capture.background)
    prediction = colors + (1 - alphas) * background
    target = captures.images + (1 - captures.masks) * background
    reference = load_mesh(paths.reference_mesh) if paths.reference_mesh.exists() else None
    metrics: dict = {"split": split, "views": len(captures.cameras)}
    metrics.update(heldout_metrics(prediction, target, captures.masks, scene.mesh, reference))
    if scene.pbr is not None and reference is not None:
        true_maps = load_material_maps(paths.reference_mesh)
        if true_maps is not None:
            metrics["material"] = _material_comparison(
                config, paths, scene.pbr, reference, true_maps
            )
    environment = json.loads(paths.environment.read_text()) if paths.environment.exists() else {}
    metrics["stage_seconds"] = environment.get("stage_seconds", {})
    atomic_write_json(paths.metrics, plain_json(metrics))
    paths.renders.mkdir(parents=True, exist_ok=True)
    for name, panel in zip(captures.names, comparison_panels(prediction, target), strict=True):
        write_png(paths.render_panel(split, name), panel)
    return {"psnr": metrics["image"]["psnr"]}


def _material_comparison(config: RunConfig, paths: RunPaths, pbr, reference, true_maps) -> dict:
    """The fitted material against the reference's true maps (recon.metrics.material), where
    the training views saw the surface (evaluate.material_seen_only; everywhere, with
    seen_from null, when the dataset has no training split)."""
    settings = config.evaluate
    seen_from = None
    if settings.material_seen_only and paths.dataset_layout.has_split("train"):
        seen_from = read_captures(paths.dataset, "train", config.dataset).cameras
    metrics = material_metrics(
        pbr.mesh.to("cpu"),
        pbr.material.detach().cpu(),
        reference,
        true_maps,
        samples=settings.material_samples,
        seed=config.seed,
        tolerance=settings.material_tolerance,
        max_distance=settings.material_max_distance,
        seen_from=seen_from,
        depth_tolerance=settings.material_depth_tolerance,
    )
    metrics["seen_from"] = "train" if seen_from is not None else None
    return metrics
