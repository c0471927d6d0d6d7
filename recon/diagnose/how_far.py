"""How far the gap shrinks: refit with the top (or each significant) effect switched on and
measure the held-out gap again, against the noise floor (and on the relight split)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from recon.config.run_config import DiagnoseConfig, RunConfig
from recon.diagnose.absorption import heldout_errors
from recon.diagnose.data import DiagnosisData, FittedModel
from recon.diagnose.gap import gauge_gain, noise_floor
from recon.diagnose.records import Candidate
from recon.diagnose.refit import RefitSettings, refit_with
from recon.diagnose.which import heldout_modules
from recon.effects.forward import render_with_effects
from recon.effects.registry import diagnosis_facts
from recon.io.datasets import CaptureSet
from recon.render.renderer import Renderer

# Secant steps that fix the albedo x light gauge under a response curve (converges in 2-3).
GAUGE_ITERATIONS = 3


def heldout_gap(data: DiagnosisData, modules: list, settings: DiagnoseConfig) -> float:
    """Held-out MSE on the second half of the pixel blocks, after fitting the per-view
    parameters of the given effect modules on the first half (scene frozen)."""
    squared, count = heldout_errors(data, modules, settings)
    return float(squared.sum() / count.sum())


def relight_heldout_gap(
    relight: DiagnosisData, mesh, modules: list, settings: DiagnoseConfig
) -> float:
    """The relight split's MSE after a refit, measured like heldout_gap: per-view effect
    parameters fitted on the first half of the pixel blocks, the error on the second half, the
    scene rendered under the split's own light.

    The albedo x light gauge is fixed first, as relight_gap does: the fitted albedo is only
    known up to a per-channel scale that the fitted light carries. A curve after the albedo (a
    response curve, x -> x^gamma) turns a texture gain g into g^gamma, so the texture's gain
    is found by secant steps on log g against the log of the least-squares gain r of the render
    with the global effects on (r = 1 at the answer; the first step takes gamma = 1)."""
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    mesh = mesh.to(relight.observed.device)
    global_effects = [module for module in modules if not module.per_view]
    log_gain = torch.zeros(3, dtype=torch.float64)
    previous: tuple[torch.Tensor, torch.Tensor] | None = None
    gauged = mesh
    for _ in range(GAUGE_ITERATIONS):
        with torch.no_grad():
            color = render_with_effects(
                renderer, gauged, relight.cameras, relight.lighting, global_effects
            ).color
        log_ratio = gauge_gain(relight.observed, color, relight.region).clamp_min(1e-6).log()
        slope = torch.ones(3, dtype=torch.float64)  # d log r / d log g = -slope
        if previous is not None:
            moved = log_gain - previous[0]
            usable = moved.abs() > 1e-9
            secant = (previous[1] - log_ratio) / torch.where(usable, moved, torch.ones_like(moved))
            slope = torch.where(usable, secant.clamp(0.2, 5.0), slope)
        previous = (log_gain, log_ratio)
        log_gain = log_gain + log_ratio / slope
        gauged = replace(mesh, texture=mesh.texture * log_gain.exp().to(mesh.texture.dtype))
    return heldout_gap(replace(relight, mesh=gauged), modules, settings)


@dataclass
class RefitBaseline:
    """What a refit is measured against: the held-out views of the fitted scene and their MSE,
    the noise floor's MSE, and (with a relight split) the same on the relight split."""

    data: DiagnosisData
    before: float
    floor: float
    relight: DiagnosisData | None = None
    relight_before: float | None = None
    relight_floor: float | None = None

    @classmethod
    def measure(
        cls,
        data: DiagnosisData,
        floor: float,
        relight: DiagnosisData | None,
        settings: DiagnoseConfig,
    ) -> RefitBaseline:
        baseline = cls(data, heldout_gap(data, [], settings), floor)
        if relight is not None:
            # Where the fit baked an effect into the albedo under its one light (shadows, a
            # response curve), the held-out views show little of it: the relight split does.
            baseline.relight = relight
            baseline.relight_before = relight_heldout_gap(relight, relight.mesh, [], settings)
            baseline.relight_floor = (noise_floor(relight).get("floor_rmse") or 0.0) ** 2
        return baseline

    def after(self, record: dict) -> RefitBaseline:
        """The baseline for the next effect of a greedy chain: this refit's errors."""
        return replace(self, before=record["after"], relight_before=record.get("relight_after"))


def _closed(before: float, after: float, floor: float) -> float:
    return (before - after) / max(before - floor, 1e-20)


@dataclass
class RefitInputs:
    """What the how-far refits start from: the training captures, the fitted model, the run
    config, the device and a scratch folder for their checkpoints (named by the stage)."""

    training: CaptureSet
    model: FittedModel
    config: RunConfig
    device: torch.device
    scratch: Path


def measure_refit(
    names: list[str], baseline: RefitBaseline, inputs: RefitInputs, settings: RefitSettings
) -> tuple[dict, object]:
    """Refit with `names` switched on and measure the gap again. Returns (the refit record of
    diagnosis.json without the geometry errors, the refitted mesh)."""
    diagnose = inputs.config.diagnose
    refitted, fitted_effects = refit_with(
        names, inputs.training, inputs.model, inputs.config, inputs.device, inputs.scratch, settings
    )
    mesh = refitted.mesh
    data = baseline.data
    modules = heldout_modules(names, fitted_effects.modules, len(data.cameras), inputs.device)
    refitted = refitted.to("cpu")
    after = heldout_gap(
        replace(data, mesh=refitted.mesh, lighting=refitted.lighting, model=refitted),
        modules,
        diagnose,
    )
    closed = _closed(baseline.before, after, baseline.floor)
    record = {
        "effects": names,
        "before": baseline.before,
        "after": after,
        "before_rmse": math.sqrt(baseline.before),
        "after_rmse": math.sqrt(max(after, 0.0)),
        "floor": baseline.floor,
        "closed_fraction": closed,
        "confirmed": closed >= diagnose.confirming_share,
        "parameters": {m.name: m.parameters_summary() for m in fitted_effects.modules},
    }
    relight = baseline.relight
    if relight is not None:
        relight_modules = heldout_modules(
            names, fitted_effects.modules, len(relight.cameras), relight.observed.device
        )
        relight_after = relight_heldout_gap(relight, mesh, relight_modules, diagnose)
        record.update(
            relight_before=baseline.relight_before,
            relight_after=relight_after,
            relight_floor=baseline.relight_floor,
            relight_closed_fraction=_closed(
                baseline.relight_before, relight_after, baseline.relight_floor
            ),
        )
    return record, mesh


def position_learning_rate(names: list[str], config: RunConfig) -> float:
    """The vertices' step size in a how-far refit: the texture stage's own where an effect
    that bends the geometry is switched on (its facts' absorption mode 'geometry': a lens
    distortion the fit absorbed must be bent back), else diagnose.refit_position_learning_rate
    (a larger step lets the vertices chase the residual). `recon-bench refit-settings`
    measures both."""
    if any(diagnosis_facts(name).absorption == "geometry" for name in names):
        return config.fit.texture.learning_rate
    return config.diagnose.refit_position_learning_rate


def relight_exponent(candidates: list[Candidate]) -> float | None:
    """The relight probe's exponent estimate (None without a relight split)."""
    for candidate in candidates:
        evidence = candidate.evidence_of("relight")
        if evidence is not None and evidence.details.get("parameters"):
            return evidence.details["parameters"]["gamma"]
    return None


def how_far(
    candidates: list[Candidate],
    baseline: RefitBaseline,
    inputs: RefitInputs,
    mode: str,
    geometry_errors=None,
    geometry_before: float | None = None,
) -> list[dict]:
    """The refit ladder: the top significant effect ('top') or each significant one in turn
    ('greedy', at most diagnose.max_greedy_effects, stopping at the first refit that does not
    confirm). geometry_errors: mesh -> Chamfer-L1 against a ground truth (None: none), and
    geometry_before the fitted mesh's."""
    diagnose = inputs.config.diagnose
    refits: list[dict] = []
    chosen: list[str] = []
    exponent = relight_exponent(candidates)
    for candidate in candidates:
        if not candidate.significant or diagnosis_facts(candidate.name) is None:
            continue  # a base-model mismatch has no module to switch on
        if mode == "top" and chosen:
            break
        if len(chosen) >= diagnose.max_greedy_effects:
            break
        names = chosen + [candidate.name]
        holds = any(diagnosis_facts(name).relight_exponent for name in names)
        settings = RefitSettings(
            steps=diagnose.refit_steps,
            position_learning_rate=position_learning_rate(names, inputs.config),
            response_exponent=exponent if holds else None,
        )
        record, mesh = measure_refit(names, baseline, inputs, settings)
        if geometry_errors is not None:
            record["geometry_before"] = geometry_before
            record["geometry_after"] = geometry_errors(mesh)
        refits.append(record)
        if mode == "greedy" and not record["confirmed"]:
            break
        chosen = names
        if mode == "greedy":
            baseline = baseline.after(record)
    return refits
