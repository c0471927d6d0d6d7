"""The warm-started refit: the fitted scene optimised again with effect modules switched on.

Used by the "how far" step (the top or each significant effect, at full resolution) and by the
lens-distortion absorption evidence (a short refit at low resolution: a distortion that the fit
absorbed bent the geometry, and only a refit that moves the vertices can bend it back). It takes
objects (captures, the fitted model, the run config); the stage names the scratch folder its
checkpoint goes to.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch

from recon.config.run_config import RunConfig
from recon.diagnose.data import FittedModel
from recon.io.datasets import CaptureSet
from recon.optimize.checkpoint import History
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.scene_model import FitEffects, LightModel
from recon.optimize.texture_stage import run_texture_stage


@dataclass(frozen=True)
class RefitSettings:
    """One refit's length and steps.

    steps: texture-stage steps. resolution: the longer image side (None: the captures').
    position_learning_rate: the vertices' step size (None: diagnose.refit_position_learning_rate).
    response_exponent: hold a response curve's exponent there (the relight probe's estimate).
        Under the training views' one light the albedo takes up most of a curve, so a refit
        that starts the exponent at 1 ends near 1 and its texture stays curved.
    """

    steps: int
    resolution: int | None = None
    position_learning_rate: float | None = None
    response_exponent: float | None = None


def refit_with(
    names: list[str],
    training: CaptureSet,
    model: FittedModel,
    config: RunConfig,
    device: torch.device,
    scratch: Path,
    settings: RefitSettings,
):
    """Warm start from the fitted mesh + light (+ the fit's own effects, at their fitted
    parameters); optimise texture, light, positions and the named effects on the training
    views. Returns (mesh, lighting, FitEffects of the named effects and the fit's own).

    scratch: a folder for the refit's checkpoint and history (overwritten)."""
    learning_rate = settings.position_learning_rate
    if learning_rate is None:
        learning_rate = config.diagnose.refit_position_learning_rate
    mesh = model.mesh.to(device)
    light = LightModel.from_lighting(model.lighting.to(device))
    fit_config = replace(
        config.fit,
        texture=replace(config.fit.texture, steps=settings.steps, learning_rate=learning_rate),
    )
    own = [name for name in model.effect_names if name not in names]
    effects = FitEffects(own + list(names), len(training.cameras), device)
    for module in effects.modules:
        module.lock_fraction = 0.0
        fitted = next((m for m in model.effects if m.name == module.name), None)
        if fitted is not None:
            module.load_state_dict(fitted.state_dict())
        if module.diagnosis.relight_exponent and settings.response_exponent is not None:
            module.hold_exponent(settings.response_exponent)
    geometry = GeometryResult(mesh.verts, mesh.faces, torch.zeros_like(mesh.verts), light)
    result = run_texture_stage(
        training,
        geometry,
        fit_config,
        device,
        config.seed,
        scratch / f"{'+'.join(names) or 'control'}.pt",
        History(scratch / "refits.jsonl"),  # the refits' own log, not the run's history
        initial=mesh,
        effects=effects,
        resolution=settings.resolution,
    )
    # Detached: the held-out probes run their own optimisations on top of this frozen scene.
    return result.mesh, result.light.lighting().detached(), result.effects
