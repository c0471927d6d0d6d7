"""The warm-started refit: the fitted scene optimised again with effect modules switched on.

Used by the "how far" step (the top or each significant effect, at full resolution) and by the
lens-distortion absorption evidence (a short refit at low resolution: a distortion that the fit
absorbed bent the geometry, and only a refit that moves the vertices can bend it back).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from recon.config.run_config import RunConfig
from recon.io.datasets import read_captures
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.optimize.checkpoint import History
from recon.optimize.fit import load_fitted_light
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.scene_model import FitEffects, LightModel
from recon.optimize.texture_stage import run_texture_stage

REFIT_STEPS = 80
# Vertex steps of a refit, a fifth of the texture stage's default: the fitted geometry is
# already right unless the missing effect bent it (see _position_learning_rate in
# recon.diagnose.diagnose).
POSITION_LEARNING_RATE = 0.002


def refit_with(
    names: list[str],
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    steps: int = REFIT_STEPS,
    resolution: int | None = None,
    response_exponent: float | None = None,
    position_learning_rate: float = POSITION_LEARNING_RATE,
):
    """Warm start from the fitted mesh + light; optimise texture, light, positions and the
    effects on the training views (at `resolution`, default the captures'). Returns (mesh,
    lighting, FitEffects).

    response_exponent: hold a response_curve's exponent there (the relight probe's estimate).
    Under the training views' one light the albedo takes up most of a curve, so a refit that
    starts the exponent at 1 ends near 1 (0.89-1.00 against truths of 0.80-0.89 on the
    benchmark) and its texture stays curved: the relight split then gains little.
    position_learning_rate: the vertices' step size."""
    captures = read_captures(paths.dataset, "train", config.dataset)
    mesh = load_mesh(paths.fitted_mesh).to(device)
    light = LightModel.from_lighting(load_fitted_light(paths, device))
    fit_config = replace(
        config.fit,
        texture=replace(config.fit.texture, steps=steps, learning_rate=position_learning_rate),
    )
    effects = FitEffects(names, len(captures.cameras), device)
    for module in effects.modules:
        module.lock_fraction = 0.0
        if module.name == "response_curve" and response_exponent is not None:
            module.hold_exponent(response_exponent)
    geometry = GeometryResult(mesh.verts, mesh.faces, torch.zeros_like(mesh.verts), light)
    scratch = paths.root / "diagnosis" / "refit"
    result = run_texture_stage(
        captures,
        geometry,
        fit_config,
        device,
        config.seed,
        scratch / f"{'+'.join(names)}.pt",
        History(scratch / "history.jsonl"),
        initial=mesh,
        effects=effects,
        resolution=resolution,
    )
    # Detached: the held-out probes run their own optimisations on top of this frozen scene.
    return result.mesh, result.light.lighting().detached(), result.effects
