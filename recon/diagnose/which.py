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
   when the interval's lower bound clears the probe's null allowance (recon.diagnose.calibration:
   what the same probe reaches on clean data).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tqdm import tqdm

from recon.diagnose.calibration import (
    RELIGHT_ALLOWANCE,
    absorption_threshold,
    probe_threshold,
)
from recon.diagnose.data import DiagnosisData
from recon.diagnose.flat_field import FLAT_FIELD_ALLOWANCE
from recon.diagnose.gauss_newton import GAUSS_NEWTON_ITERATIONS, GaussNewtonProblem
from recon.effects.base import ModelEffect
from recon.effects.forward import (
    EffectContext,
    apply_camera_effects,
    apply_image_effects,
    apply_shading_effects,
)
from recon.effects.registry import MODEL_EFFECTS, make_effect
from recon.render.renderer import Renderer

BLOCK_PIXELS = 4
BOOTSTRAP_SAMPLES = 400


@dataclass
class CandidateResult:
    effect: str
    score: float
    heldout_reduction: float
    interval: tuple[float, float]
    significant: bool
    parameters: dict = field(default_factory=dict)
    absorption: float | None = None
    absorption_interval: tuple[float, float] | None = None
    absorption_parameters: dict | None = None
    fingerprint: dict | None = None
    # The relight split's evidence (the response curve only, recon.diagnose.relight_probe).
    relight_reduction: float | None = None
    relight_interval: tuple[float, float] | None = None
    relight_parameters: dict | None = None
    # The effect its probe and absorption evidence were measured on top of (None: alone).
    conditional_on: str | None = None
    # The conditioning effect that voids this candidate's absorption evidence, measured alone
    # (recon.diagnose.absorption.absorption_probes: geometry-moving refits are not repeated on
    # top of a given effect); None when the absorption evidence counts.
    absorption_discounted_by: str | None = None
    # The flat-field frames' measurement (vignetting only, recon.diagnose.flat_field): a
    # falloff there is the camera's, whatever the residual shows.
    flat_field: dict | None = None
    # What made it significant: "probe", "absorption", "relight", "flat_field" or
    # "fingerprint" ("" when nothing did).
    evidence: str = ""
    # The probe's per-view held-out error sums [B] (not saved): the baseline when the others
    # are probed on top of this effect.
    heldout_errors: torch.Tensor | None = field(default=None, repr=False, compare=False)

    def decide(self) -> None:
        """Significance from the recorded evidence and the calibrated thresholds
        (recon.diagnose.calibration): the probe's held-out reduction, else the absorption
        refit's, else the relight split's, else the visibility fingerprint naming this effect.
        Flat-field frames (vignetting only) overrule all of them, either way: they measure the
        falloff itself, where the rest infer it from a residual other effects can shape."""
        evidence = ""
        if self.flat_field is not None:
            if self.flat_field["deviation"] > FLAT_FIELD_ALLOWANCE:
                evidence = "flat_field"
        elif self.probe_clears():
            evidence = "probe"
        elif self._absorption_counts() and self.absorption_interval[0] > absorption_threshold(
            self.effect
        ):
            evidence = "absorption"
        elif self.relight_interval is not None and self.relight_interval[0] > RELIGHT_ALLOWANCE:
            evidence = "relight"
        elif self.fingerprint is not None and self.fingerprint.get("names") == self.effect:
            evidence = "fingerprint"
        self.evidence = evidence
        self.significant = bool(evidence)

    def probe_clears(self) -> bool:
        """Whether the probe's held-out reduction clears its null allowance."""
        return self.interval[0] > probe_threshold(self.effect)

    def _absorption_counts(self) -> bool:
        return self.absorption_interval is not None and self.absorption_discounted_by is None

    @classmethod
    def from_json(cls, record: dict) -> CandidateResult:
        """The inverse of to_json (for re-deciding a stored diagnosis)."""
        absorption_interval = record.get("absorption_interval")
        relight_interval = record.get("relight_interval")
        return cls(
            effect=record["effect"],
            score=record["score"],
            heldout_reduction=record["heldout_reduction"],
            interval=tuple(record["interval"]),
            significant=record["significant"],
            parameters=record.get("probe_parameters", record.get("parameters", {})),
            absorption=record.get("absorption"),
            absorption_interval=None if absorption_interval is None else tuple(absorption_interval),
            absorption_parameters=record.get("absorption_parameters"),
            fingerprint=record.get("fingerprint"),
            relight_reduction=record.get("relight_reduction"),
            relight_interval=None if relight_interval is None else tuple(relight_interval),
            relight_parameters=record.get("relight_parameters"),
            conditional_on=record.get("conditional_on"),
            absorption_discounted_by=record.get("absorption_discounted_by"),
            flat_field=record.get("flat_field"),
            evidence=record.get("evidence", ""),
        )

    def excess(self) -> float:
        """How far the residual evidence clears its own null: the larger of the probe's and the
        absorption's interval lower bound minus its allowance (recon.diagnose.calibration).
        Comparing raw reductions would favour the flexible probes (pose, blur), whose null
        allowance is several times another's."""
        excess = self.interval[0] - probe_threshold(self.effect)
        if self._absorption_counts():
            excess = max(excess, self.absorption_interval[0] - absorption_threshold(self.effect))
        if self.relight_interval is not None:
            excess = max(excess, self.relight_interval[0] - RELIGHT_ALLOWANCE)
        return excess

    def rank_key(self) -> tuple:
        """Significant first; then held-out evidence (probe, absorption, relight) or a direct
        measurement (the flat field) before the albedo fingerprint alone, whose effect shows in
        no held-out residual; then by how far the residual evidence clears its null (the
        fingerprint: by its share)."""
        by_residual = self.evidence in ("probe", "absorption", "relight", "flat_field")
        strength = (self.fingerprint or {}).get("share", 0.0)
        return (
            self.significant,
            by_residual,
            strength if self.evidence == "fingerprint" else self.excess(),
        )

    def _deciding_parameters(self) -> dict:
        """The parameters of the evidence that decided (a flat field: the absorption
        regression's, whose corner and half-way falloffs the diagnosis then replaces by the
        frames' measurement); with none deciding, the relight
        split's when it has them (the one estimate of a response curve the albedo cannot
        absorb), else the probe's."""
        measured = self.evidence in ("absorption", "flat_field")
        if measured and self.absorption_parameters is not None:
            return self.absorption_parameters
        relight_decides = self.evidence in ("relight", "")
        if relight_decides and self.relight_parameters is not None:
            return self.relight_parameters
        return self.parameters

    def to_json(self) -> dict:
        return {
            "effect": self.effect,
            "score": self.score,
            "heldout_reduction": self.heldout_reduction,
            "interval": list(self.interval),
            "significant": self.significant,
            # The parameters of the evidence that decided (the absorption refit's when that
            # made it significant), and the probe's own.
            "parameters": self._deciding_parameters(),
            "probe_parameters": self.parameters,
            "absorption_parameters": self.absorption_parameters,
            "absorption": self.absorption,
            "absorption_interval": None
            if self.absorption_interval is None
            else list(self.absorption_interval),
            "fingerprint": self.fingerprint,
            "relight_reduction": self.relight_reduction,
            "relight_interval": None
            if self.relight_interval is None
            else list(self.relight_interval),
            "relight_parameters": self.relight_parameters,
            "conditional_on": self.conditional_on,
            "absorption_discounted_by": self.absorption_discounted_by,
            "flat_field": self.flat_field,
            "evidence": self.evidence,
        }


def block_halves(batch: int, height: int, width: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Two complementary [B, H, W, 1] masks: a checkerboard of BLOCK_PIXELS blocks."""
    rows = torch.arange(height, device=device) // BLOCK_PIXELS
    columns = torch.arange(width, device=device) // BLOCK_PIXELS
    first = ((rows[:, None] + columns[None, :]) % 2 == 0).float()
    first = first[None, :, :, None].expand(batch, height, width, 1)
    return first, 1 - first


class EffectProbe:
    """Renders the frozen fitted scene with effect modules on top, cheaply: image effects reuse
    the cached render, shading effects its buffers, and camera effects (pose corrections) warp
    the cached render along the flow that the correction gives each pixel's surface point."""

    def __init__(self, data: DiagnosisData, renderer: Renderer | None = None) -> None:
        self.data = data
        self.renderer = renderer or Renderer(
            texture_filter="linear-mipmap-linear", texture_boundary="clamp"
        )
        with torch.no_grad():
            self.base_output = self.renderer.render(data.mesh, data.cameras, data.lighting)
        self.view_indices = torch.arange(len(data.cameras), device=data.observed.device)
        self._surface_points: torch.Tensor | None = None

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
        before = self.data.cameras.project_to_pixels(points)
        after = cameras.project_to_pixels(points)
        source = before - (after - before)  # backward warp, flow evaluated at the target pixel
        scale = torch.tensor([width, height], dtype=source.dtype, device=source.device)
        grid = (source / scale * 2 - 1).view(batch, height, width, 2)
        stacked = torch.cat([color, alpha], dim=-1).permute(0, 3, 1, 2)
        warped = torch.nn.functional.grid_sample(
            stacked, grid, mode="bilinear", padding_mode="zeros", align_corners=False
        ).permute(0, 2, 3, 1)
        return warped[..., : color.shape[-1]], warped[..., color.shape[-1] :]

    def render(self, effect: ModelEffect | list[ModelEffect]) -> torch.Tensor:
        """Premultiplied colour [B, H, W, 3] of the scene with the effect(s)."""
        effects = effect if isinstance(effect, list) else [effect]
        output = self.base_output
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
        color, _ = apply_image_effects(effects, color, alpha, self.data.cameras, self.view_indices)
        return color


def _per_view_mse(prediction: torch.Tensor, observed: torch.Tensor, weight: torch.Tensor):
    squared = ((prediction - observed) ** 2 * weight).sum(dim=(1, 2, 3))
    count = (weight.sum(dim=(1, 2, 3)) * prediction.shape[-1]).clamp_min(1)
    return squared, count


def probe_candidate(
    name: str, probe: EffectProbe, iterations: int = GAUSS_NEWTON_ITERATIONS, seed: int = 0
) -> CandidateResult:
    data = probe.data
    batch, height, width, _ = data.observed.shape
    _, second = block_halves(batch, height, width, data.observed.device)
    effect = probe_effect(name, batch, data.observed.device)
    with torch.no_grad():
        before, _ = _per_view_mse(probe.base_output.color, data.observed, second * data.region)
    # 1. Score test at the identity and 2. probe fit on the first half, measured on the second.
    (after, _), score = fit_on_halves([effect], probe, iterations, with_score=True)
    # 3. Bootstrap over views.
    reduction, (low, high) = bootstrap_reduction(before, after, seed)
    result = CandidateResult(
        effect=name,
        score=float(score),
        heldout_reduction=float(reduction),
        interval=(low, high),
        significant=False,
        parameters=effect.parameters_summary(),
        heldout_errors=after,
    )
    result.decide()
    return result


def probe_effect(name: str, view_count: int, device) -> ModelEffect:
    """A fresh module for probing held-out views (no pinned view: every held-out view is new).

    The pose probe fits the rotations only. At the capture distance a small translation moves
    the image as a rotation does, except for a change of scale, and a per-view change of scale
    is also what a lens distortion or a blur leaves in views of a texture that absorbed it:
    with translations free, the pose probe explains those cases better than their own probes.
    """
    effect = make_effect(name, view_count=view_count, pinned_view=None).to(device)
    if name == "pose_error":
        effect.translation.requires_grad_(False)
    return effect


# Where a probe starts instead of the identity, for parameters whose image changes to second
# order at zero: the motion blur's covariance is quadratic in its line vector there, so the
# first Gauss-Newton step from zero overshoots (a half-pixel-squared horizontal line instead).
PROBE_STARTS: dict[str, tuple[str, float]] = {"motion_blur": ("line", 0.5)}


def _move_to_start(effect: ModelEffect) -> None:
    """Move an effect to its PROBE_STARTS point."""
    name, value = PROBE_STARTS[effect.name]
    with torch.no_grad():
        getattr(effect, name)[..., 0] = value


def fit_on_halves(
    effects: list[ModelEffect],
    probe: EffectProbe,
    iterations: int = GAUSS_NEWTON_ITERATIONS,
    trainable: list[ModelEffect] | None = None,
    with_score: bool = False,
):
    """Fit the parameters of `trainable` (default: all the effects) on the first half of each
    view's pixel blocks, scene frozen (Gauss-Newton, recon.diagnose.gauss_newton); per-view
    squared error sums and counts [B] of the scene with the effects on the second half.

    with_score: also return the score test at the parameters the effects come with (the
    identity for a probe): the relative loss reduction on the first half that a full
    Gauss-Newton step predicts, ((sums, counts), score).
    """
    data = probe.data
    batch, height, width, _ = data.observed.shape
    first, second = block_halves(batch, height, width, data.observed.device)
    trainable = effects if trainable is None else trainable
    score = 0.0
    if effects:
        problem = GaussNewtonProblem(
            trainable, lambda: probe.render(effects), data.observed, first * data.region
        )
        at_identity = all(effect.is_identity() for effect in effects)
        start_image = probe.base_output.color if at_identity else None
        starting = [e for e in trainable if e.name in PROBE_STARTS and e.is_identity()]
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


def conditioning_effect(ranking: list[CandidateResult]) -> str | None:
    """The effect the other evidence is conditioned on: the top candidate when its probe made it
    significant. Such an effect leaves a large held-out residual that other flexible probes
    partly explain (a per-view exposure or pose, and a blur too, which motion blur, lens
    distortion and pose refinement all imitate); measured on top of it, the others show only
    what they add."""
    top = max(ranking, key=CandidateResult.rank_key, default=None)
    if top is None or not top.significant:
        return None
    # A flat field overrules the label, not what the probe saw.
    by_probe = top.evidence == "probe" or (top.evidence == "flat_field" and top.probe_clears())
    return top.effect if by_probe else None


def conditional_probes(
    ranking: list[CandidateResult],
    probe: EffectProbe,
    given: str,
    iterations: int = GAUSS_NEWTON_ITERATIONS,
    seed: int = 0,
) -> None:
    """Re-probe every other significant candidate jointly with `given`: its held-out reduction
    becomes the share of the error left by `given` alone that it removes, and its significance
    is decided again on that (recorded in place, with conditional_on)."""
    batch = probe.data.view_count
    device = probe.data.observed.device
    alone = next(candidate for candidate in ranking if candidate.effect == given).heldout_errors
    if alone is None:
        alone = fit_on_halves([probe_effect(given, batch, device)], probe, iterations)[0]
    for candidate in ranking:
        if candidate.effect == given or not candidate.significant:
            continue
        modules = [probe_effect(name, batch, device) for name in (given, candidate.effect)]
        joint = fit_on_halves(modules, probe, iterations)[0]
        reduction, interval = bootstrap_reduction(alone, joint, seed)
        candidate.heldout_reduction = reduction
        candidate.interval = interval
        candidate.conditional_on = given
        candidate.parameters = modules[1].parameters_summary()
        candidate.decide()


def bootstrap_reduction(
    before: torch.Tensor, after: torch.Tensor, seed: int = 0
) -> tuple[float, tuple[float, float]]:
    """Share of the error removed, 1 - sum(after) / sum(before), over per-view error sums [B],
    and its 90 % bootstrap interval over views."""
    before, after = before.detach().cpu().double(), after.detach().cpu().double()
    batch = before.shape[0]
    generator = torch.Generator().manual_seed(seed)
    picks = torch.randint(0, batch, (BOOTSTRAP_SAMPLES, batch), generator=generator)
    sampled = 1 - after[picks].sum(1) / before[picks].sum(1).clamp_min(1e-20)
    reduction = float(1 - after.sum() / before.sum().clamp_min(1e-20))
    return reduction, (float(torch.quantile(sampled, 0.05)), float(torch.quantile(sampled, 0.95)))


def rank_candidates(
    data: DiagnosisData,
    candidates: list[str] | None = None,
    iterations: int = GAUSS_NEWTON_ITERATIONS,
    probe: EffectProbe | None = None,
) -> list[CandidateResult]:
    """Every candidate probed; sorted by CandidateResult.rank_key (best first). probe: an
    EffectProbe of the same data to reuse (its render is cached)."""
    probe = probe or EffectProbe(data)
    names = candidates or sorted(MODEL_EFFECTS)
    results = []
    bar = tqdm(names, desc="diagnose candidates", unit="effect", leave=False)
    for name in bar:
        bar.set_postfix(effect=name)
        results.append(probe_candidate(name, probe, iterations=iterations))
    return sorted(results, key=CandidateResult.rank_key, reverse=True)


def verdict_of(ranking: list[CandidateResult]) -> str:
    significant = [candidate.effect for candidate in ranking if candidate.significant]
    if not significant:
        return "no significant unmodelled effect"
    return "significant unmodelled effects: " + ", ".join(significant)


def redecide(diagnosis: dict) -> dict:
    """A stored diagnosis.json's ranking re-decided with the current thresholds and re-sorted
    (the evidence itself is kept); returns a new dict."""
    ranking = [CandidateResult.from_json(record) for record in diagnosis["ranking"]]
    for candidate in ranking:
        candidate.decide()
    ranking.sort(key=CandidateResult.rank_key, reverse=True)
    return {
        **diagnosis,
        "ranking": [candidate.to_json() for candidate in ranking],
        "verdict": verdict_of(ranking),
    }
