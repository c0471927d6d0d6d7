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

from dataclasses import dataclass, replace

import torch

from recon.camera.cameras import Cameras
from recon.config.run_config import RunConfig
from recon.diagnose.calibration import MINIMUM_SHARE, absorption_threshold
from recon.diagnose.data import DiagnosisData, load_diagnosis_data
from recon.diagnose.radial_absorption import radial_absorption
from recon.diagnose.refit import refit_with
from recon.diagnose.which import (
    CandidateResult,
    EffectProbe,
    bootstrap_reduction,
    fit_on_halves,
)
from recon.effects.base import ModelEffect
from recon.effects.forward import EffectContext, apply_image_effects, apply_shading_effects
from recon.effects.registry import make_effect
from recon.io.datasets import CaptureSet, read_captures
from recon.io.run_folder import RunPaths
from recon.mesh.mesh import Mesh
from recon.optimize.scene_model import LightModel, texture_total_variation
from recon.render.renderer import Renderer, SurfaceBuffers
from recon.render.shading import Lighting
from recon.render.texture import build_mip_pyramid

# Effects that look the same in every view and that a short refit can pull back out of the
# texture and light. (Shadows and interreflection are baked in for good under one light; their
# evidence is the albedo fingerprint, recon.diagnose.fingerprint.)
ABSORBABLE = ("vignetting", "lens_distortion", "specular")
ABSORPTION_STEPS = 24
# Absorbed effects that bent the geometry too: their refits move the vertices, in fewer pixels.
GEOMETRY_ABSORBABLE = ("lens_distortion",)
# A refit step at 64 px costs nearly what a fit step at 128 px does (the rasteriser's work is
# per triangle), so these two refits are the diagnosis' dearest part. At 15 steps the lens
# datasets' lower bounds stayed at 0.15-0.32 (0.15-0.35 at 30 steps); the clean calibration
# fits' largest reduction was 0.022 (the allowance 0.043, recon.diagnose.calibration).
GEOMETRY_STEPS = 15
GEOMETRY_RESOLUTION = 64
VIEWS_PER_GROUP = 8
TEXTURE_LEARNING_RATE = 0.03
LIGHT_LEARNING_RATE = 0.01
SMOOTHNESS_WEIGHT = 0.01


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
    steps: int = ABSORPTION_STEPS,
) -> tuple[Mesh, Lighting, list[ModelEffect]]:
    """Refit texture, light and the named effects (from the identity) on the training views with
    the geometry frozen; one group of views per step. Returns the re-textured mesh, the light
    (detached) and the fitted effect modules."""
    device = frozen.mesh.verts.device
    modules = [make_effect(name, view_count=frozen.view_count).to(device) for name in names]
    texture = torch.nn.Parameter(frozen.mesh.texture.clone())
    light = LightModel.from_lighting(frozen.lighting)
    groups = [{"params": [texture], "lr": TEXTURE_LEARNING_RATE}]
    groups.append({"params": list(light.parameters()), "lr": LIGHT_LEARNING_RATE})
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
        loss = ((color - observed) ** 2).mean() + SMOOTHNESS_WEIGHT * smoothness
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    mesh = replace(frozen.mesh, texture=texture.detach())
    return mesh, light.lighting().detached(), modules


def heldout_modules(names: list[str], fitted: list[ModelEffect], view_count: int, device):
    """Modules for held-out views: per-view effects start at the identity (their views are new;
    fit_on_halves fits them on each view's first half), global effects copy the refit's
    parameters."""
    modules = []
    for name in names:
        module = make_effect(name, view_count=view_count, pinned_view=None).to(device)
        source = next((m for m in fitted if m.name == name), None)
        if source is not None and not module.per_view:
            module.load_state_dict(source.state_dict())
        modules.append(module)
    return modules


def heldout_errors(
    data: DiagnosisData, modules: list[ModelEffect]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view held-out squared error sums and counts [B] on the second half of the pixel
    blocks; the per-view modules are fitted on the first half, the global ones keep their
    parameters."""
    per_view = [module for module in modules if module.per_view]
    return fit_on_halves(modules, EffectProbe(data), trainable=per_view)


@dataclass
class AbsorptionCache:
    """What the two absorption passes of a diagnosis (alone, then on top of a given effect)
    share: the training views rasterised once with the fitted geometry."""

    frozen: FrozenTrainingViews | None = None


# The least share of the control's error a given effect is taken to leave (a given effect whose
# probe interval reached 1 would otherwise make every candidate worth refitting on top of it
# through a division by zero; every candidate is then, which is the safe side).
SMALLEST_REMAINING_SHARE = 0.05


def _could_clear_on_top(candidate: CandidateResult, given: CandidateResult | None) -> bool:
    """Whether the candidate's unconditional absorption evidence leaves room for it to become
    significant on top of the given effect, so its refits are worth running again.

    The evidence is a share of the control refit's held-out error. On top of the given effect
    the control's error is smaller, by at most about the given effect's probe reduction (the
    upper end of its interval), so the same absolute gain becomes a larger share: the first
    pass's upper bound, divided by the error the given effect leaves, must reach the allowance.
    The first pass must also have seen some sign of the effect (a positive lower bound).
    Candidates below either keep their unconditional evidence; neither their significance nor
    their place among the significant ones could change (an absorption excess below zero
    cannot outrank a significant probe's)."""
    interval = candidate.absorption_interval
    if interval is None or interval[0] <= 0:
        return False
    given_high = given.interval[1] if given is not None else 0.0
    remaining = max(1.0 - max(given_high, 0.0), SMALLEST_REMAINING_SHARE)
    return interval[1] / remaining > absorption_threshold(candidate.effect)


def absorption_probes(
    ranking: list[CandidateResult],
    data: DiagnosisData,
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    given: str | None = None,
    cache: AbsorptionCache | None = None,
) -> None:
    """For each candidate in ABSORBABLE: a short refit of texture, light and the effect (and the
    vertex positions for GEOMETRY_ABSORBABLE), against a control refit of the same kind without
    it; the held-out reduction relative to the control (bootstrapped over views) is the
    absorption evidence, recorded in place (and it can make the candidate significant).

    given: an effect switched on in the control and in every candidate refit alike (see
    which.conditioning_effect), so the evidence is what each candidate adds on top of it. With
    a given effect, the refits run only for candidates whose earlier (unconditional)
    absorption evidence could make them significant on top of it (_could_clear_on_top); and
    the geometry-moving refits do not run
    again at all: their evidence measured alone is voided (absorption_discounted_by), and the
    candidate's conditional probe decides. A blur or pose error that the fit absorbed is
    partly taken back by a distortion in a refit that moves the vertices (lower bounds
    0.2-0.33 on the benchmark's blur datasets), so that evidence does not count beside one;
    measuring it again on top of the given effect cost two more refits, as much as the rest
    of the diagnosis together.

    cache: shared between the two passes of one diagnosis (the rasterised training views).
    """
    # Bilinear without mipmaps: the training views sample the texture near 1:1, and the
    # refits only compare with each other (the held-out evaluation renders in full).
    renderer = Renderer(texture_filter="linear", texture_boundary="clamp")
    cache = cache if cache is not None else AbsorptionCache()
    base = [given] if given else []
    given_candidate = next((c for c in ranking if c.effect == given), None) if given else None

    def evaluate(names: list[str], moving: bool) -> tuple[torch.Tensor, list[ModelEffect]]:
        if moving:
            mesh, lighting, fitted_effects = refit_with(
                names, paths, config, device, GEOMETRY_STEPS, resolution=GEOMETRY_RESOLUTION
            )
            fitted = fitted_effects.modules
        else:
            if cache.frozen is None:
                cache.frozen = FrozenTrainingViews.build(
                    read_captures(paths.dataset, "train", getattr(config, "dataset", None)),
                    data.mesh.to(device),
                    data.lighting.to(device),
                    renderer,
                )
            mesh, lighting, fitted = frozen_refit(cache.frozen, names, renderer, ABSORPTION_STEPS)
        modules = heldout_modules(names, fitted, data.view_count, data.observed.device)
        refitted = replace(data, mesh=mesh.to("cpu"), lighting=lighting.to("cpu"))
        return heldout_errors(refitted, modules)[0], fitted

    controls: dict[bool, torch.Tensor] = {}
    for candidate in ranking:
        if candidate.effect not in ABSORBABLE or candidate.effect == given:
            continue
        if candidate.effect == "vignetting":
            if candidate.flat_field is not None and not candidate.significant:
                # Flat-field frames measured no falloff, and they overrule the residual
                # evidence (CandidateResult.decide): the regression could not change the verdict,
                # and loading the training views for it is most of its cost.
                continue
            if not given:
                # Its regression holds a gain per view already (a per-view photometric effect
                # on top changes nothing): computed once, unconditionally.
                training = load_diagnosis_data(
                    paths, "train", device, dataset_options=getattr(config, "dataset", None)
                )
                control, squared, module = radial_absorption(training, data)
                _record(candidate, control, squared, module, given)
            continue
        moving = candidate.effect in GEOMETRY_ABSORBABLE
        if moving and given:
            if candidate.absorption_interval is not None:
                candidate.absorption_discounted_by = given
                candidate.decide()
            continue
        if not given and candidate.heldout_reduction < MINIMUM_SHARE:
            # The refits are the diagnosis' dearest step (the two that move the geometry
            # most of all): they run only where the frozen-scene probe sees a residual of the
            # effect's shape worth naming. An effect the fit absorbed so wholly that its probe
            # removes less than this is not looked for. (On the benchmark's datasets the lens
            # refits' lower bound stayed at or below 0.04 wherever the probe's reduction was
            # under this, against an allowance of 0.118 then; the specular probe removed
            # 0.048-0.12 on every dataset with a specular lobe, at most 0.005 on clean fits.)
            continue
        if given and not _could_clear_on_top(candidate, given_candidate):
            # The refits again on top of the given effect only where the first pass leaves
            # room for a significant effect: otherwise its unconditional evidence stands.
            continue
        if moving not in controls:
            controls[moving] = evaluate(base, moving)[0]
        squared, fitted = evaluate(base + [candidate.effect], moving)
        module = next(module for module in fitted if module.name == candidate.effect)
        _record(candidate, controls[moving], squared, module, given)


def _record(
    candidate: CandidateResult,
    control: torch.Tensor,
    squared: torch.Tensor,
    module: ModelEffect,
    given: str | None,
) -> None:
    """Absorption evidence from per-view held-out error sums [B] without and with the effect:
    the reduction with its bootstrap interval, the effect's parameters, and the decision."""
    reduction, (low, high) = bootstrap_reduction(control, squared)
    candidate.absorption = reduction
    candidate.absorption_interval = (low, high)
    candidate.absorption_parameters = module.parameters_summary()
    if given:
        candidate.conditional_on = given
    candidate.decide()
