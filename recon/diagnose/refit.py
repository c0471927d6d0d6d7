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
from recon.errors import ReconError
from recon.io.datasets import CaptureSet
from recon.optimize.checkpoint import History
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.material_stage import run_pbr_texture_stage
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
) -> tuple[FittedModel, FitEffects]:
    """Warm start from the fitted model (+ the fit's own effects, at their fitted parameters);
    optimise its material, light, positions and the named effects on the training views with
    the stage the fit used: the Lambertian texture stage (texture and SH light), or for a
    fit.material pbr model the pbr material stage (base colour, roughness/metalness maps and
    environment, recon.optimize.material_stage.run_pbr_texture_stage with warm_start).

    Returns (the refitted model: mesh, light, pbr material where the fit had one, and the fit's
    own effects at their refitted parameters; FitEffects of the fit's own and the named effects).
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
    checkpoint = scratch / f"{'+'.join(names) or 'control'}.pt"
    history = History(scratch / "refits.jsonl")  # the refits' own log, not the run's history
    own_modules = [module for module in effects.modules if module.name in own]
    if model.pbr is not None:
        shading = [module.name for module in effects.modules if module.stage == "shading"]
        if shading:
            raise ReconError(
                f"diagnose: cannot refit {shading} on a fit.material pbr model: they are shading "
                "effects of the Lambertian model (the pbr material models specular reflection)"
            )
        pbr = run_pbr_texture_stage(
            training,
            geometry,
            fit_config,
            device,
            config.seed,
            checkpoint,
            history,
            effects=effects,
            resolution=settings.resolution,
            warm_start=model.pbr,
        )
        refitted = FittedModel(pbr.mesh, pbr.light.lighting().detached(), own_modules, pbr)
        return refitted, effects
    result = run_texture_stage(
        training,
        geometry,
        fit_config,
        device,
        config.seed,
        checkpoint,
        history,
        initial=mesh,
        effects=effects,
        resolution=settings.resolution,
    )
    # Detached: the held-out probes run their own optimisations on top of this frozen scene.
    lighting = result.light.lighting().detached()
    return FittedModel(result.mesh, lighting, own_modules), result.effects
