"""Which unmodelled effect causes the gap: score test, probe fit, bootstrap, significance.

For every candidate effect module (recon.effects), starting from the fitted scene (frozen):

1. Score test (no fit): the Jacobian J of the image with respect to the effect's parameters at
   zero (the identity) and the loss reduction a full Gauss-Newton step predicts,
   g^T (J^T J)^-1 g with g = J^T r, relative to the loss: a Lagrange-multiplier test for an
   omitted variable.
2. Probe: only the effect's parameters are fitted (damped Gauss-Newton,
   recon.diagnose.gauss_newton), on one half of each held-out view's pixels
   (a checkerboard of blocks), and the loss reduction is measured on the other half. Per-view
   effects (exposure of a view the fit never saw) get their per-view parameters from the same
   view's first half; pixel noise cannot carry over between halves, structure does.
3. Bootstrap over views gives an interval for the held-out reduction; an effect is significant
   when the interval's lower bound clears the probe's null allowance (config diagnose.decision,
   recon.config.run_config.DecisionConfig: what the same probe reaches on clean data).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import torch
from tqdm import tqdm

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.decision import decide, decide_all, rank_key
from recon.diagnose.gauss_newton import GaussNewtonProblem, counted_pixels
from recon.diagnose.records import Candidate, Evidence
from recon.effects.base import ModelEffect
from recon.effects.forward import (
    IMAGE_ORDER,
    EffectContext,
    apply_camera_effects,
    apply_image_effects,
    apply_shading_effects,
)
from recon.effects.registry import MODEL_EFFECTS, diagnosis_facts, make_effect
from recon.render.renderer import Renderer, RenderOutput


def block_halves(
    batch: int, height: int, width: int, device, block_pixels: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Two complementary [B, H, W, 1] masks: a checkerboard of block_pixels blocks
    (config diagnose.block_pixels)."""
    rows = torch.arange(height, device=device) // block_pixels
    columns = torch.arange(width, device=device) // block_pixels
    first = ((rows[:, None] + columns[None, :]) % 2 == 0).float()
    first = first[None, :, :, None].expand(batch, height, width, 1)
    return first, 1 - first


class PixelPacking:
    """Chosen pixels of a [B, H, W, C] batch held per view as a [B, M, 1, C] batch (M: the most
    pixels any view has; the rest zeros), so a pixelwise image effect (ModelEffect.pixelwise),
    applied to the packed batch with its per-view parameters, gives its image at those pixels
    alone.

    index: [N] flat indices over B * H * W, ascending; shape: (B, H, W).
    """

    def __init__(self, index: torch.Tensor, shape: tuple[int, int, int]) -> None:
        batch, height, width = shape
        self.index = index
        self.batch = batch
        self.image_height, self.image_width = height, width
        self.view = torch.div(index, height * width, rounding_mode="floor")
        counts = torch.bincount(self.view, minlength=batch)
        starts = torch.cumsum(counts, 0) - counts
        self.slot = torch.arange(index.numel(), device=index.device) - starts[self.view]
        self.width = int(counts.max()) if index.numel() else 0
        self.packed_index = self.view * self.width + self.slot  # [N] over B * M

    def pack(self, image: torch.Tensor) -> torch.Tensor:
        """[B, M, 1, C] of the chosen pixels of image [B, H, W, C]."""
        channels = image.shape[-1]
        return self.pack_values(image.reshape(-1, channels).index_select(0, self.index))

    def pack_values(self, values: torch.Tensor) -> torch.Tensor:
        """[B, M, 1, C] of values [N, C] at the chosen pixels (index's order)."""
        channels = values.shape[-1]
        packed = values.new_zeros(self.batch * self.width, channels)
        packed[self.packed_index] = values
        return packed.view(self.batch, self.width, 1, channels)

    def rows_and_columns(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(row [N], column [N]) of the chosen pixels."""
        pixel = self.index - self.view * (self.image_height * self.image_width)
        return torch.div(pixel, self.image_width, rounding_mode="floor"), pixel % self.image_width

    def unpack(self, packed: torch.Tensor) -> torch.Tensor:
        """[N, C] the chosen pixels' values of a packed batch [B, M, 1, C] (index's order)."""
        return packed.reshape(-1, packed.shape[-1]).index_select(0, self.packed_index)


class EffectProbe:
    """Renders the frozen fitted scene with effect modules on top, cheaply: image effects reuse
    the cached render, shading effects its buffers, and camera effects (pose corrections) warp
    the cached render along the flow that the correction gives each pixel's surface point."""

    def __init__(
        self,
        data: DiagnosisData,
        settings: DiagnoseConfig | None = None,
        renderer: Renderer | None = None,
        scene_output: RenderOutput | None = None,
    ) -> None:
        """scene_output: data's views rendered already (data.render_views_once), else the
        probe renders them."""
        self.data = data
        self.settings = settings or DiagnoseConfig()
        # The probe's per-view held-out error sums [B] by effect: the baseline when the others
        # are probed on top of that effect.
        self.heldout_errors: dict[str, torch.Tensor] = {}
        self.renderer = renderer or Renderer(
            texture_filter="linear-mipmap-linear", texture_boundary="clamp"
        )
        model = data.model
        with torch.no_grad():
            if scene_output is not None:
                self.scene_output = scene_output
            elif model is not None and model.pbr is not None:
                self.scene_output = model.render(self.renderer, data.cameras)
            else:
                self.scene_output = self.renderer.render(data.mesh, data.cameras, data.lighting)
        self.base_output = self.scene_output
        self.view_indices = torch.arange(len(data.cameras), device=data.observed.device)
        self._surface_points: torch.Tensor | None = None
        self._surface_pixels: torch.Tensor | None = None
        # The fit's own effects are part of the model: global ones keep the fit's parameters,
        # per-view ones are fitted on the first half of each held-out view's blocks, once.
        self.model_effects: list[ModelEffect] = []
        if model is not None and model.effects:
            self.model_effects = heldout_modules(
                model.effect_names, model.effects, data.view_count, data.observed.device
            )
            per_view = [module for module in self.model_effects if module.per_view]
            if per_view:
                batch, height, width, _ = data.observed.shape
                first, _ = block_halves(
                    batch, height, width, data.observed.device, self.settings.block_pixels
                )
                weight = first * data.region
                GaussNewtonProblem(
                    per_view,
                    lambda: self.render([]),
                    data.observed,
                    weight,
                    render_counted=self.counted_render([], weight),
                ).fit(self.settings.gauss_newton_iterations)
            for module in self.model_effects:
                module.requires_grad_(False)
            with torch.no_grad():
                self.base_output = self._render_over_scene([])

    def surface_points(self) -> torch.Tensor:
        """World position of what every pixel shows [B, H * W, 3]; background pixels take the
        view's mean object depth, so the silhouette's neighbourhood moves with the object."""
        if self._surface_points is None:
            cameras = self.data.cameras
            output = self.base_output
            batch, height, width, _ = output.depth.shape
            mask = output.mask[..., 0] > 0.5
            depth = output.depth[..., 0]
            mean_depth = (depth * mask).sum((1, 2)) / mask.sum((1, 2)).clamp_min(1)
            depth = torch.where(mask, depth, mean_depth[:, None, None])
            rows, columns = torch.meshgrid(
                torch.arange(height, device=depth.device) + 0.5,
                torch.arange(width, device=depth.device) + 0.5,
                indexing="ij",
            )
            intrinsics = cameras.intrinsics
            fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
            cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
            camera_points = torch.stack(
                [
                    (columns - cx) / fx * depth,
                    (rows - cy) / fy * depth,
                    depth,
                    torch.ones_like(depth),
                ],
                dim=-1,
            ).view(batch, -1, 4)
            world = camera_points @ torch.linalg.inv(cameras.world_to_cam).transpose(1, 2)
            self._surface_points = world[..., :3]
        return self._surface_points

    def warp_to(self, cameras, color: torch.Tensor, alpha: torch.Tensor):
        """(color, alpha) [B, H, W, C] seen from `cameras` instead of the data's cameras, to first
        order: each pixel samples the cached render where its surface point's flow came from."""
        batch, height, width, _ = color.shape
        points = self.surface_points()
        if self._surface_pixels is None:  # where the data's cameras see them: fixed
            self._surface_pixels = self.data.cameras.project_to_pixels(points)
        before = self._surface_pixels
        after = cameras.project_to_pixels(points)
        source = before - (after - before)  # backward warp, flow evaluated at the target pixel
        scale = torch.tensor([width, height], dtype=source.dtype, device=source.device)
        grid = (source / scale * 2 - 1).view(batch, height, width, 2)
        stacked = torch.cat([color, alpha], dim=-1).permute(0, 3, 1, 2)
        warped = torch.nn.functional.grid_sample(
            stacked, grid, mode="bilinear", padding_mode="zeros", align_corners=False
        ).permute(0, 2, 3, 1)
        return warped[..., : color.shape[-1]], warped[..., color.shape[-1] :]

    def counted_render(
        self, effects: list[ModelEffect], weight: torch.Tensor
    ) -> Callable[[], torch.Tensor] | None:
        """A render of the scene with the model's and the given effects at the pixels with
        weight [B, H, W, 1] > 0 only ([N, C], gauss_newton.counted_pixels' order), for a
        GaussNewtonProblem's render_counted; None where the effects need whole images.

        Each counted pixel's value is the full render's, at a fraction of its cost, where
        every image effect is pixelwise (ModelEffect.pixelwise) but possibly the first step:
        a camera effect (the cached render warped, warp_to, sampled at those pixels alone) or
        a first image effect that samples the image at moved positions (sample_grids: lens
        distortion). grid_sample's value at a position does not depend on the others asked
        for, so the samples are forward's. Shading effects, blurs and anything after a
        non-pixelwise image effect take the whole image (None)."""
        everything = self.model_effects + effects
        if not everything or any(module.stage == "shading" for module in everything):
            return None
        camera = [module for module in everything if module.stage == "camera"]
        image = sorted(
            (module for module in everything if module.stage == "image"),
            key=lambda module: (
                IMAGE_ORDER.index(module.name) if module.name in IMAGE_ORDER else len(IMAGE_ORDER)
            ),
        )
        sampling = bool(image) and not image[0].pixelwise and hasattr(image[0], "sample_grids")
        rest = image[1:] if sampling and not camera else image
        if not all(module.pixelwise for module in rest):
            return None
        observed = self.data.observed
        packing = PixelPacking(counted_pixels(weight, observed.shape), observed.shape[:3])
        if camera:
            sample = self._warped_at(camera, packing)
        elif sampling:
            sample = self._sampled_at(image[0], packing)
        else:
            color = packing.pack(self.scene_output.color)
            alpha = packing.pack(self.scene_output.alpha)

            def sample() -> tuple[torch.Tensor, torch.Tensor]:
                return color, alpha

        def render() -> torch.Tensor:
            color, alpha = sample()
            image, _ = apply_image_effects(rest, color, alpha, self.data.cameras, self.view_indices)
            return packing.unpack(image)

        return render

    def _stacked(self) -> torch.Tensor:
        """The cached render's colour and alpha as grid_sample's input [B, C + 1, H, W]."""
        output = self.scene_output
        return torch.cat([output.color, output.alpha], dim=-1).permute(0, 3, 1, 2)

    def _warped_at(
        self, camera: list[ModelEffect], packing: PixelPacking
    ) -> Callable[[], tuple[torch.Tensor, torch.Tensor]]:
        """warp_to of the cached render to the cameras the camera effects give, at packing's
        pixels ([B, M, 1, C] colour and [B, M, 1, 1] alpha): the same flow, with only those
        pixels' surface points projected, sampled at those pixels only. (The projection is a
        [B, M, 4] x [4, 4] product instead of warp_to's [B, H * W, 4] one: the same sums of
        four products, equal bit for bit on this project's machines, by test.)"""
        stacked = self._stacked()
        channels = self.scene_output.color.shape[-1]
        batch, height, width, _ = self.scene_output.color.shape
        points = self.surface_points()
        if self._surface_pixels is None:  # where the data's cameras see them: fixed
            self._surface_pixels = self.data.cameras.project_to_pixels(points)
        before = self._surface_pixels.reshape(-1, 2).index_select(0, packing.index)
        chosen = packing.pack_values(points.reshape(-1, 3).index_select(0, packing.index))
        chosen = chosen.view(batch, packing.width, 3)  # [B, M, 3]
        scale = torch.tensor([width, height], dtype=before.dtype, device=before.device)

        def sample() -> tuple[torch.Tensor, torch.Tensor]:
            moved = apply_camera_effects(camera, self.data.cameras, self.view_indices)
            after = packing.unpack(moved.project_to_pixels(chosen)[:, :, None])  # [N, 2]
            source = before - (after - before)
            grid = packing.pack_values(source / scale * 2 - 1)  # [B, M, 1, 2]
            warped = torch.nn.functional.grid_sample(
                stacked, grid, mode="bilinear", padding_mode="zeros", align_corners=False
            ).permute(0, 2, 3, 1)
            return warped[..., :channels], warped[..., channels:]

        return sample

    def _sampled_at(
        self, effect: ModelEffect, packing: PixelPacking
    ) -> Callable[[], tuple[torch.Tensor, torch.Tensor]]:
        """An image effect that resamples the image (its sample_grids: lens distortion) on the
        cached render, at packing's pixels: image + sample(grid) - sample(base grid), as its
        forward writes it, the base samples (independent of its parameters) taken once."""
        output = self.scene_output
        stacked = self._stacked()
        channels = output.color.shape[-1]
        _, height, width, _ = output.color.shape
        at_pixels = packing.pack(torch.cat([output.color, output.alpha], dim=-1))
        row, column = packing.rows_and_columns()
        cameras = self.data.cameras
        options = {"mode": "bilinear", "padding_mode": "zeros", "align_corners": False}

        def grids() -> tuple[torch.Tensor, torch.Tensor]:
            grid, base = effect.sample_grids(
                cameras, height, width, packing.view, row, column, output.color
            )
            return packing.pack_values(grid), packing.pack_values(base)

        with torch.no_grad():
            base_grid = grids()[1]
            at_centres = torch.nn.functional.grid_sample(stacked, base_grid, **options)

        def sample() -> tuple[torch.Tensor, torch.Tensor]:
            sampled = torch.nn.functional.grid_sample(stacked, grids()[0], **options)
            result = (at_pixels.permute(0, 3, 1, 2) + (sampled - at_centres)).permute(0, 2, 3, 1)
            return result[..., :channels], result[..., channels:]

        return sample

    def render(self, effect: ModelEffect | list[ModelEffect]) -> torch.Tensor:
        """Premultiplied colour [B, H, W, 3] of the scene (the fitted model, its own effects
        included) with the effect(s)."""
        effects = effect if isinstance(effect, list) else [effect]
        return self._render_over_scene(effects).color

    def _render_over_scene(self, effects: list[ModelEffect]):
        """The cached scene render with the model's and the given effects, as a RenderOutput
        (colour and alpha replaced)."""
        effects = self.model_effects + effects
        output = self.scene_output
        cameras = self.data.cameras
        if any(module.stage == "shading" for module in effects):
            context = EffectContext(
                self.data.mesh, self.data.lighting, cameras, self.view_indices, self.renderer
            )
            output = apply_shading_effects(effects, output, context)
        color, alpha = output.color, output.alpha
        if any(module.stage == "camera" for module in effects):
            moved = apply_camera_effects(effects, cameras, self.view_indices)
            color, alpha = self.warp_to(moved, color, alpha)
        color, alpha = apply_image_effects(
            effects, color, alpha, self.data.cameras, self.view_indices
        )
        return replace(output, color=color, alpha=alpha)


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


def _per_view_mse(prediction: torch.Tensor, observed: torch.Tensor, weight: torch.Tensor):
    squared = ((prediction - observed) ** 2 * weight).sum(dim=(1, 2, 3))
    count = (weight.sum(dim=(1, 2, 3)) * prediction.shape[-1]).clamp_min(1)
    return squared, count


def probe_evidence(
    name: str,
    reduction: float,
    interval: tuple[float, float],
    parameters: dict,
    score: float | None = None,
    conditional_on: str | None = None,
) -> Evidence:
    """The probe's Evidence (threshold and passed are the decision's,
    recon.diagnose.decision)."""
    on_top = f" on top of {conditional_on}" if conditional_on else ""
    details = {"reduction": reduction, "interval": list(interval), "parameters": parameters}
    details["conditional_on"] = conditional_on
    if score is not None:
        details["score"] = score
    return Evidence(
        kind="probe",
        candidate=name,
        statistic=interval[0],
        threshold=math.nan,
        passed=False,
        reason=f"probe{on_top}: held-out reduction's lower bound",
        details=details,
    )


def probe_candidate(name: str, probe: EffectProbe, seed: int = 0) -> Candidate:
    """A candidate with its probe evidence: score test at the identity, probe fit on the first
    half of each view's blocks, held-out reduction on the second, bootstrapped over views."""
    data = probe.data
    settings = probe.settings
    batch, height, width, _ = data.observed.shape
    _, second = block_halves(batch, height, width, data.observed.device, settings.block_pixels)
    effect = probe_effect(name, batch, data.observed.device)
    with torch.no_grad():
        before, _ = _per_view_mse(probe.base_output.color, data.observed, second * data.region)
    (after, _), score = fit_on_halves([effect], probe, with_score=True)
    reduction, interval = bootstrap_reduction(before, after, settings.bootstrap_samples, seed)
    probe.heldout_errors[name] = after
    candidate = Candidate(name)
    candidate.add(
        probe_evidence(name, reduction, interval, effect.parameters_summary(), float(score))
    )
    return decide(candidate, settings.decision)


def probe_effect(name: str, view_count: int, device) -> ModelEffect:
    """A fresh module for probing held-out views (no pinned view: every held-out view is new),
    with the parameters its diagnosis facts freeze (probe_frozen) held at zero."""
    effect = make_effect(name, view_count=view_count, pinned_view=None).to(device)
    for parameter in effect.diagnosis.probe_frozen:
        getattr(effect, parameter).requires_grad_(False)
    return effect


def _move_to_start(effect: ModelEffect) -> None:
    """Move an effect to its probe start (DiagnosisFacts.probe_start): for parameters whose
    image changes to second order at zero the first Gauss-Newton step from zero overshoots."""
    name, value = effect.diagnosis.probe_start
    with torch.no_grad():
        getattr(effect, name)[..., 0] = value


def fit_on_halves(
    effects: list[ModelEffect],
    probe: EffectProbe,
    trainable: list[ModelEffect] | None = None,
    with_score: bool = False,
):
    """Fit the parameters of `trainable` (default: all the effects) on the first half of each
    view's pixel blocks, scene frozen (Gauss-Newton, recon.diagnose.gauss_newton, for
    diagnose.gauss_newton_iterations); per-view squared error sums and counts [B] of the scene
    with the effects on the second half.

    with_score: also return the score test at the parameters the effects come with (the
    identity for a probe): the relative loss reduction on the first half that a full
    Gauss-Newton step predicts, ((sums, counts), score).
    """
    data = probe.data
    iterations = probe.settings.gauss_newton_iterations
    batch, height, width, _ = data.observed.shape
    first, second = block_halves(
        batch, height, width, data.observed.device, probe.settings.block_pixels
    )
    trainable = effects if trainable is None else trainable
    score = 0.0
    if effects:
        weight = first * data.region
        problem = GaussNewtonProblem(
            trainable,
            lambda: probe.render(effects),
            data.observed,
            weight,
            render_counted=probe.counted_render(effects, weight),
        )
        at_identity = all(effect.is_identity() for effect in effects)
        start_image = probe.base_output.color if at_identity else None
        starting = [e for e in trainable if e.diagnosis.probe_start and e.is_identity()]
        if starting:
            # The score test belongs to the identity, not to the probe's starting point.
            if with_score:
                score = problem.score(start_image)
            for effect in starting:
                _move_to_start(effect)
            problem.fit(iterations)
        else:
            score = problem.fit(iterations, start_image=start_image)["score"]
    with torch.no_grad():
        color = probe.render(effects) if effects else probe.base_output.color
        errors = _per_view_mse(color, data.observed, second * data.region)
    return (errors, score) if with_score else errors


def conditioning_effect(candidates: list[Candidate]) -> str | None:
    """The effect the other evidence is conditioned on: the top candidate when its probe made it
    significant. Such an effect leaves a large held-out residual that other flexible probes
    partly explain (a per-view exposure or pose, and a blur too, which motion blur, lens
    distortion and pose refinement all imitate); measured on top of it, the others show only
    what they add."""
    effects = [item for item in candidates if diagnosis_facts(item.name) is not None]
    top = max(effects, key=rank_key, default=None)
    if top is None or not top.significant:
        return None
    # A flat field overrules the label, not what the probe saw.
    probe = top.evidence_of("probe")
    by_probe = top.decided_by == "probe" or (
        top.decided_by == "flat_field" and probe is not None and probe.passed
    )
    return top.name if by_probe else None


def conditional_probes(candidates: list[Candidate], probe: EffectProbe, given: str) -> None:
    """Re-probe every other significant candidate jointly with `given`: its probe evidence
    becomes the share of the error left by `given` alone that it removes, decided again
    (recorded in place, with conditional_on)."""
    batch = probe.data.view_count
    device = probe.data.observed.device
    settings = probe.settings
    alone = probe.heldout_errors.get(given)
    if alone is None:
        alone = fit_on_halves([probe_effect(given, batch, device)], probe)[0]
    for candidate in candidates:
        if candidate.name == given or not candidate.significant:
            continue
        if diagnosis_facts(candidate.name) is None:
            continue
        modules = [probe_effect(name, batch, device) for name in (given, candidate.name)]
        joint = fit_on_halves(modules, probe)[0]
        reduction, interval = bootstrap_reduction(alone, joint, settings.bootstrap_samples)
        earlier = candidate.evidence_of("probe")
        score = None if earlier is None else earlier.details.get("score")
        conditional = probe_evidence(
            candidate.name,
            reduction,
            interval,
            modules[1].parameters_summary(),
            score,
            conditional_on=given,
        )
        if earlier is not None and not earlier.details.get("conditional_on"):
            # Kept so the probe alone can be restored if `given` is vetoed later.
            conditional.details["alone"] = earlier.to_json()
        candidate.add(conditional)
        decide(candidate, settings.decision)


def bootstrap_reduction(
    before: torch.Tensor, after: torch.Tensor, samples: int, seed: int = 0
) -> tuple[float, tuple[float, float]]:
    """Share of the error removed, 1 - sum(after) / sum(before), over per-view error sums [B],
    and its 90 % bootstrap interval over views (samples resamples, diagnose.bootstrap_samples)."""
    before, after = before.detach().cpu().double(), after.detach().cpu().double()
    batch = before.shape[0]
    generator = torch.Generator().manual_seed(seed)
    picks = torch.randint(0, batch, (samples, batch), generator=generator)
    sampled = 1 - after[picks].sum(1) / before[picks].sum(1).clamp_min(1e-20)
    reduction = float(1 - after.sum() / before.sum().clamp_min(1e-20))
    return reduction, (float(torch.quantile(sampled, 0.05)), float(torch.quantile(sampled, 0.95)))


def rank_candidates(
    data: DiagnosisData,
    candidates: list[str] | None = None,
    probe: EffectProbe | None = None,
    settings: DiagnoseConfig | None = None,
) -> list[Candidate]:
    """Every candidate probed; sorted by recon.diagnose.decision.rank_key (best first).
    probe: an EffectProbe of the same data to reuse (its render is cached)."""
    probe = probe or EffectProbe(data, settings)
    names = candidates or sorted(MODEL_EFFECTS)
    results = []
    bar = tqdm(names, desc="diagnose candidates", unit="effect", leave=False)
    for name in bar:
        bar.set_postfix(effect=name)
        results.append(probe_candidate(name, probe))
    return decide_all(results, probe.settings.decision)
