"""Absorption evidence: does an effect pull back out of the texture what the fit put there?

An effect that looks the same in every view (vignetting, lens distortion, a specular lobe) is
partly absorbed by the fitted texture and light: the probe on the frozen scene sees only what
the fit left. Refitting the texture and light together with the effect lets it take back its
share; the held-out error of that refit, against a control refit of the same length without the
effect, is the absorption evidence (bootstrapped over views like the probes).

Specular refits keep the geometry frozen: the training views are rasterised once (in groups
of VIEWS_PER_GROUP) and every step only re-textures, re-shades and applies the effects, without
antialiasing; a step costs a few milliseconds instead of a full render and backward pass. A lens
distortion that the fit absorbed bent the geometry as well, and only moving the vertices bends
it back (with frozen geometry its evidence was a third as large): its refits are the full
warm-started refit (recon.diagnose.refit) at GEOMETRY_RESOLUTION. Vignetting needs no refit at
all: a falloff is a gain per pixel, so texture cell gains and the falloff are fitted in closed
form (recon.diagnose.radial_absorption). The held-out evaluation renders in full (antialiased),
like every other held-out number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from recon.camera.cameras import Cameras
from recon.config.run_config import DiagnoseConfig, RunConfig
from recon.diagnose.data import DiagnosisData, FittedModel, render_diagnosis_data
from recon.diagnose.decision import absorption_threshold, decide
from recon.diagnose.radial_absorption import radial_absorption
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.refit import RefitSettings, refit_with
from recon.diagnose.which import EffectProbe, bootstrap_reduction, fit_on_halves, heldout_modules
from recon.effects.base import ModelEffect
from recon.effects.forward import EffectContext, apply_image_effects, apply_shading_effects
from recon.effects.registry import diagnosis_facts, make_effect
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.optimize.scene_model import LightModel, texture_total_variation
from recon.render.renderer import Renderer, SurfaceBuffers
from recon.render.shading import Lighting
from recon.render.texture import build_mip_pyramid

# Training views rasterised per group of a frozen refit (memory, not a tuned number).
VIEWS_PER_GROUP = 8


@dataclass
class FrozenTrainingViews:
    """The training views rasterised once with the fitted geometry, in groups of views.

    groups: (surface buffers, view indices [b], observed [b, H, W, 3]) per group.
    """

    mesh: Mesh
    lighting: Lighting
    cameras: Cameras
    groups: list[tuple[SurfaceBuffers, torch.Tensor, torch.Tensor]]
    view_count: int

    @classmethod
    def build(
        cls, captures: CaptureSet, mesh: Mesh, lighting: Lighting, renderer: Renderer
    ) -> FrozenTrainingViews:
        """captures: the training split; mesh, lighting: the fitted scene (one device)."""
        device = mesh.verts.device
        cameras = captures.cameras.to(device)
        view_count = len(cameras)
        groups = []
        with torch.no_grad():
            for start in range(0, view_count, VIEWS_PER_GROUP):
                views = torch.arange(start, min(start + VIEWS_PER_GROUP, view_count))
                buffers = renderer.surface_buffers(mesh, cameras[views.to(device)])
                groups.append((buffers, views.to(device), captures.images[views].to(device)))
        return cls(mesh, lighting, cameras, groups, view_count)


def frozen_refit(
    frozen: FrozenTrainingViews,
    names: list[str],
    renderer: Renderer,
    settings: DiagnoseConfig,
) -> tuple[Mesh, Lighting, list[ModelEffect]]:
    """Refit texture, light and the named effects (from the identity) on the training views with
    the geometry frozen, for diagnose.absorption_steps (one group of views per step). Returns
    the re-textured mesh, the light (detached) and the fitted effect modules."""
    steps = settings.absorption_steps
    device = frozen.mesh.verts.device
    modules = [make_effect(name, view_count=frozen.view_count).to(device) for name in names]
    texture = torch.nn.Parameter(frozen.mesh.texture.clone())
    light = LightModel.from_lighting(frozen.lighting)
    groups = [{"params": [texture], "lr": settings.absorption_texture_learning_rate}]
    groups.append(
        {"params": list(light.parameters()), "lr": settings.absorption_light_learning_rate}
    )
    groups += [group for module in modules for group in module.parameter_groups()]
    optimizer = torch.optim.Adam(groups)
    for step in range(steps):
        buffers, views, observed = frozen.groups[step % len(frozen.groups)]
        lighting = light.lighting()
        output = renderer.shade(
            buffers,
            lighting,
            texture=texture,
            mip_pyramid=build_mip_pyramid(texture)
            if renderer.texture_filter == "linear-mipmap-linear"
            else None,
            antialias_edges=False,
        )
        cameras = frozen.cameras[views]
        context = EffectContext(frozen.mesh, lighting, cameras, views, renderer)
        output = apply_shading_effects(modules, output, context)
        color, _ = apply_image_effects(modules, output.color, output.alpha, cameras, views)
        smoothness = texture_total_variation(texture)  # as in the fit
        # Squared error, like the held-out evaluation: an L1 loss keeps Adam's texel steps at
        # full size to the end, and that jitter would swamp a small absorbed effect.
        loss = ((color - observed) ** 2).mean() + settings.absorption_smoothness_weight * smoothness
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    mesh = replace(frozen.mesh, texture=texture.detach())
    return mesh, light.lighting().detached(), modules


def heldout_errors(
    data: DiagnosisData, modules: list[ModelEffect], settings: DiagnoseConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view held-out squared error sums and counts [B] on the second half of the pixel
    blocks; the per-view modules are fitted on the first half, the global ones keep their
    parameters."""
    per_view = [module for module in modules if module.per_view]
    return fit_on_halves(modules, EffectProbe(data, settings), trainable=per_view)


@dataclass
class AbsorptionCache:
    """What the two absorption passes of a diagnosis (alone, then on top of a given effect)
    and the later producers share: the training views rasterised once with the fitted geometry
    (frozen), and the training views against the fitted model (training; also read by the
    lobe evidence, recon.diagnose.lobe)."""

    frozen: FrozenTrainingViews | None = None
    training: DiagnosisData | None = None


@dataclass
class AbsorptionInputs:
    """What the absorption refits start from (objects, no run-folder paths).

    training: the training split's captures; model: the fitted model; config: the run config
    (fit recipe, seed, diagnose section); device: where the refits run; scratch: a folder the
    geometry-moving refits may write their checkpoints to (the stage's RunPaths names it).
    """

    training: CaptureSet
    model: FittedModel
    config: RunConfig
    device: torch.device
    scratch: Path


def _could_clear_on_top(
    candidate: Candidate, given: Candidate | None, settings: DiagnoseConfig
) -> bool:
    """Whether the candidate's unconditional absorption evidence leaves room for it to become
    significant on top of the given effect, so its refits are worth running again.

    The evidence is a share of the control refit's held-out error. On top of the given effect
    the control's error is smaller, by at most about the given effect's probe reduction (the
    upper end of its interval), so the same absolute gain becomes a larger share: the first
    pass's upper bound, divided by the error the given effect leaves (at least
    diagnose.smallest_remaining_share, against a division by zero), must reach the allowance.
    The first pass must also have seen some sign of the effect (a positive lower bound).
    Candidates below either keep their unconditional evidence; neither their significance nor
    their place among the significant ones could change (an absorption excess below zero
    cannot outrank a significant probe's)."""
    evidence = candidate.evidence_of("absorption")
    interval = None if evidence is None else evidence.interval
    if interval is None or interval[0] <= 0:
        return False
    probe = None if given is None else given.evidence_of("probe")
    given_high = probe.interval[1] if probe is not None else 0.0
    remaining = max(1.0 - max(given_high, 0.0), settings.smallest_remaining_share)
    return interval[1] / remaining > absorption_threshold(candidate.name, settings.decision)


def absorption_probes(
    candidates: list[Candidate],
    data: DiagnosisData,
    inputs: AbsorptionInputs,
    given: str | None = None,
    cache: AbsorptionCache | None = None,
) -> None:
    """For each candidate whose diagnosis facts give an absorption mode: a short refit of
    texture, light and the effect (and the vertex positions for mode 'geometry'), against a
    control refit of the same kind without it; the held-out reduction relative to the control
    (bootstrapped over views) is the absorption evidence, recorded in place (and it can make
    the candidate significant). Mode 'closed_form' (vignetting) is a regression instead
    (recon.diagnose.radial_absorption).

    given: an effect switched on in the control and in every candidate refit alike (see
    which.conditioning_effect), so the evidence is what each candidate adds on top of it. With
    a given effect, the refits run only for candidates whose earlier (unconditional)
    absorption evidence could make them significant on top of it (_could_clear_on_top); and
    the geometry-moving refits do not run again at all: their evidence measured alone is
    voided, and the candidate's conditional probe decides. A blur or pose error that the fit
    absorbed is partly taken back by a distortion in a refit that moves the vertices (lower
    bounds 0.2-0.33 on the benchmark's blur datasets), so that evidence does not count beside
    one; measuring it again on top of the given effect cost two more refits, as much as the
    rest of the diagnosis together.

    cache: shared between the two passes of one diagnosis (the rasterised training views).
    """
    settings = inputs.config.diagnose
    # Bilinear without mipmaps: the training views sample the texture near 1:1, and the
    # refits only compare with each other (the held-out evaluation renders in full).
    renderer = Renderer(texture_filter="linear", texture_boundary="clamp")
    cache = cache if cache is not None else AbsorptionCache()
    base = [given] if given else []
    given_candidate = next((c for c in candidates if c.name == given), None) if given else None
    device = inputs.device

    def evaluate(names: list[str], moving: bool) -> tuple[torch.Tensor, list[ModelEffect]]:
        if moving:
            refit = RefitSettings(
                steps=settings.geometry_steps, resolution=settings.geometry_resolution
            )
            refitted, fitted_effects = refit_with(
                names, inputs.training, inputs.model, inputs.config, device, inputs.scratch, refit
            )
            fitted = fitted_effects.modules
            refitted = refitted.to("cpu")
            modules = heldout_modules(names, fitted, data.view_count, data.observed.device)
            moved = replace(data, mesh=refitted.mesh, lighting=refitted.lighting, model=refitted)
            return heldout_errors(moved, modules, settings)[0], fitted
        if cache.frozen is None:
            cache.frozen = FrozenTrainingViews.build(
                inputs.training,
                data.mesh.to(device),
                data.lighting.to(device),
                renderer,
            )
        mesh, lighting, fitted = frozen_refit(cache.frozen, names, renderer, settings)
        modules = heldout_modules(names, fitted, data.view_count, data.observed.device)
        refitted = replace(data, mesh=mesh.to("cpu"), lighting=lighting.to("cpu"))
        return heldout_errors(refitted, modules, settings)[0], fitted

    controls: dict[bool, torch.Tensor] = {}
    for candidate in candidates:
        facts = diagnosis_facts(candidate.name)
        if facts is None or facts.absorption == "none" or candidate.name == given:
            continue
        if inputs.model.pbr is not None and facts.absorption == "frozen":
            continue  # the frozen refits re-texture the Lambertian model only
        if facts.absorption == "closed_form":
            flat_field = candidate.evidence_of("flat_field")
            if flat_field is not None and not candidate.significant:
                # Flat-field frames measured no falloff, and they overrule the residual
                # evidence (recon.diagnose.decision): the regression could not change the
                # verdict, and loading the training views for it is most of its cost.
                continue
            if not given:
                # Its regression holds a gain per view already (a per-view photometric effect
                # on top changes nothing): computed once, unconditionally.
                if cache.training is None:
                    cache.training = render_diagnosis_data(
                        inputs.training, inputs.model, device, settings.band_pixels
                    )
                control, squared, module = radial_absorption(cache.training, data, settings)
                _record(candidate, control, squared, module, given, settings)
            continue
        moving = facts.absorption == "geometry"
        if moving and given:
            evidence = candidate.evidence_of("absorption")
            if evidence is not None:
                candidate.add(
                    replace(
                        evidence,
                        void=f"absorption measured alone: void beside {given}",
                        details={**evidence.details, "discounted_by": given},
                    )
                )
                decide(candidate, settings.decision)
            continue
        probe = candidate.evidence_of("probe")
        reduction = probe.details["reduction"] if probe is not None else 0.0
        if not given and reduction < settings.decision.minimum_share:
            # The refits are the diagnosis' dearest step (the two that move the geometry
            # most of all): they run only where the frozen-scene probe sees a residual of the
            # effect's shape worth naming. An effect the fit absorbed so wholly that its probe
            # removes less than this is not looked for.
            continue
        if given and not _could_clear_on_top(candidate, given_candidate, settings):
            # The refits again on top of the given effect only where the first pass leaves
            # room for a significant effect: otherwise its unconditional evidence stands.
            continue
        if moving not in controls:
            controls[moving] = evaluate(base, moving)[0]
        squared, fitted = evaluate(base + [candidate.name], moving)
        module = next(module for module in fitted if module.name == candidate.name)
        _record(candidate, controls[moving], squared, module, given, settings)


def _record(
    candidate: Candidate,
    control: torch.Tensor,
    squared: torch.Tensor,
    module: ModelEffect,
    given: str | None,
    settings: DiagnoseConfig,
) -> None:
    """Absorption evidence from per-view held-out error sums [B] without and with the effect:
    the reduction with its bootstrap interval, the effect's parameters, and the decision."""
    reduction, (low, high) = bootstrap_reduction(control, squared, settings.bootstrap_samples)
    on_top = f" on top of {given}" if given else ""
    candidate.add(
        Evidence(
            kind="absorption",
            candidate=candidate.name,
            statistic=low,
            threshold=math.nan,
            passed=False,
            reason=f"absorption refit{on_top}: held-out reduction over the control's lower bound",
            details={
                "reduction": reduction,
                "interval": [low, high],
                "parameters": module.parameters_summary(),
                "conditional_on": given,
            },
        )
    )
    decide(candidate, settings.decision)
