"""Nulls derived from the run itself: what an effect's held-out reduction must beat on this fit.

A fixed allowance measured on clean 36 dB fits says nothing about a 20 dB fit of a glossy real
object: there, the base model's mismatch leaves a large structured residual, and any flexible
effect removes part of it. The nulls here come from the run:

- placebo effects: random smooth effects with as many parameters as the candidate (per view
  where the candidate is per view), fitted and scored exactly as the probe is (first half of the
  pixel blocks, held-out on the second). A gain-like candidate's placebo multiplies the render
  by random smooth fields; a geometric one's moves it along random smooth displacement fields.
  Their held-out reductions on this fit's residual are the null: a candidate must remove more
  than its placebos do (a quantile of the draws). The null grows with the residual's structure.
- split-half agreement: a per-view gain fitted on the two halves of the held-out blocks
  separately; real per-view parameters agree between halves, noise does not. The null is the
  same agreement with the views of one half permuted.

Producers return recon.diagnose.records.Evidence of kind "null".
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from functools import cached_property

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.records import Evidence
from recon.effects.registry import make_effect

KIND = "null"

# Candidates whose image change is a movement of the render (not a scaling of it): their
# placebo is a displacement along random smooth fields.
GEOMETRIC_EFFECTS = ("lens_distortion", "defocus_blur", "motion_blur", "pose_error")


def permuted_correlations(
    one: torch.Tensor, other: torch.Tensor, count: int, seed: int
) -> torch.Tensor:
    """Correlations [count] of one [B, K] with other [B, K] under random permutations of other's
    views (rows), both centred over views already: the null of a per-view agreement."""
    generator = torch.Generator().manual_seed(seed)
    orders = torch.rand(count, other.shape[0], generator=generator).argsort(dim=1)
    numerator = (one[None] * other[orders]).sum(dim=(1, 2))
    return numerator / ((one * one).sum() * (other * other).sum()).sqrt().clamp_min(1e-30)


def parameter_layout(name: str, view_count: int) -> tuple[int, int]:
    """(parameters per view, global parameters) of the candidate's probe (the pose probe fits
    rotations only, recon.diagnose.which.probe_effect)."""
    effect = make_effect(name, view_count=view_count, pinned_view=None)
    per_view, shared = 0, 0
    for parameter_name, parameter in effect.named_parameters():
        if name == "pose_error" and parameter_name == "translation":
            continue
        if effect.per_view and parameter.ndim >= 1 and parameter.shape[0] == view_count:
            per_view += parameter.numel() // view_count
        else:
            shared += parameter.numel()
    return per_view, shared


def checkerboard(batch: int, height: int, width: int, block_pixels: int) -> torch.Tensor:
    """[B, H, W, 1] float: 1 on the fitting half's blocks, 0 on the held-out half's."""
    rows = torch.arange(height) // block_pixels
    columns = torch.arange(width) // block_pixels
    first = ((rows[:, None] + columns[None, :]) % 2 == 0).float()
    return first[None, :, :, None].expand(batch, height, width, 1)


def smooth_fields(
    count: int, height: int, width: int, cells: int, generator, keep: torch.Tensor | None = None
) -> torch.Tensor:
    """count random smooth fields [count, H, W] (unit variance grid, bilinear upsampled).
    keep: [count] bool, the fields to upsample (the others are drawn, so the random stream
    stays the same, and returned as zeros without the cost of upsampling them)."""
    grid = torch.randn(count, 1, cells, cells, generator=generator)
    if keep is None:
        return torch.nn.functional.interpolate(
            grid, size=(height, width), mode="bilinear", align_corners=True
        )[:, 0]
    fields = torch.zeros(count, height, width, dtype=grid.dtype)
    fields[keep] = torch.nn.functional.interpolate(
        grid[keep], size=(height, width), mode="bilinear", align_corners=True
    )[:, 0]
    return fields


def image_gradients(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-difference gradients (d/dx, d/dy) of [B, H, W, C] images, zero at the border."""
    dx = torch.zeros_like(image)
    dy = torch.zeros_like(image)
    dx[:, :, 1:-1] = (image[:, :, 2:] - image[:, :, :-2]) / 2
    dy[:, 1:-1] = (image[:, 2:] - image[:, :-2]) / 2
    return dx, dy


@dataclass
class _Pixels:
    """The region's pixels of a DiagnosisData, flattened (N pixels): where they are, their
    render, its gradients, the residual, and which held-out half they belong to."""

    view: torch.Tensor  # [N]
    row: torch.Tensor  # [N]
    column: torch.Tensor  # [N]
    rendered: torch.Tensor  # [N, 3]
    gradient_x: torch.Tensor  # [N, 3]
    gradient_y: torch.Tensor  # [N, 3]
    residual: torch.Tensor  # [N, 3]
    first: torch.Tensor  # [N] bool

    @classmethod
    def of(cls, data: DiagnosisData, block_pixels: int) -> _Pixels:
        batch, height, width, _ = data.observed.shape
        inside = data.region[..., 0] > 0.5
        view, row, column = inside.nonzero(as_tuple=True)
        gradient_x, gradient_y = image_gradients(data.rendered)
        first = checkerboard(batch, height, width, block_pixels)[..., 0] > 0.5
        return cls(
            view=view,
            row=row,
            column=column,
            rendered=data.rendered[inside],
            gradient_x=gradient_x[inside],
            gradient_y=gradient_y[inside],
            residual=data.residual[inside].double(),
            first=first[inside],
        )

    @cached_property
    def energy(self) -> torch.Tensor:
        """[N] the render's squared norm per pixel (the placebo fields' mean weights)."""
        return (self.rendered**2).sum(-1)

    @cached_property
    def halves(self) -> _Halves:
        """What every placebo draw reads of the two halves (computed once per pixels)."""
        fit = self.first.nonzero().squeeze(1)
        test = (~self.first).nonzero().squeeze(1)
        rendered_fit = self.rendered.index_select(0, fit).double()
        rendered_test = self.rendered.index_select(0, test).double()
        residual_fit = self.residual.index_select(0, fit)
        residual_test = self.residual.index_select(0, test)
        return _Halves(
            fit=fit,
            test=test,
            rendered_test=rendered_test,
            residual_test=residual_test,
            energy_fit=(rendered_fit * rendered_fit).sum(-1),
            correlation_fit=(rendered_fit * residual_fit).sum(-1),
            before=(residual_test**2).sum(),
        )


@dataclass
class _Halves:
    """A _Pixels' fitting half (fit [F]) and held-out half (test [T]), as indices, with the
    float64 render and residual there and the per-pixel sums of a gain placebo's normal
    equations: energy_fit [F] sum_c r^2, correlation_fit [F] sum_c r * residual; before: the
    held-out residual's squared sum."""

    fit: torch.Tensor
    test: torch.Tensor
    rendered_test: torch.Tensor
    residual_test: torch.Tensor
    energy_fit: torch.Tensor
    correlation_fit: torch.Tensor
    before: torch.Tensor


def placebo_bases(
    pixels: _Pixels,
    size: tuple[int, int, int],
    count: int,
    geometric: bool,
    settings: DiagnoseConfig,
    generator,
    shared: bool = False,
) -> torch.Tensor:
    """count random basis images [count, N, 3] (at the region's N pixels) of one placebo
    parameter each: a random smooth gain field times the render, or (geometric) the render's
    change along a random smooth displacement field (its first-order image change). size:
    (B, H, W); shared: one field for every view's image frame (a global parameter), else one
    per view."""
    fields = placebo_fields(pixels, size, count, geometric, settings, generator, shared)
    return _bases_at(fields, pixels, geometric)


def _bases_at(
    fields: torch.Tensor, pixels: _Pixels, geometric: bool, rows: torch.Tensor | None = None
) -> torch.Tensor:
    """placebo_bases from placebo_fields' values [count, components, N], at the pixels rows
    [N] bool only ([count, M, 3]; default all): each element the same product as at all."""
    rendered, gradient_x, gradient_y = pixels.rendered, pixels.gradient_x, pixels.gradient_y
    if rows is not None:
        fields = fields[:, :, rows]
        rendered, gradient_x, gradient_y = rendered[rows], gradient_x[rows], gradient_y[rows]
    if not geometric:
        return fields[:, 0, :, None] * rendered[None]
    return fields[:, 0, :, None] * gradient_x[None] + fields[:, 1, :, None] * gradient_y[None]


def placebo_fields(
    pixels: _Pixels,
    size: tuple[int, int, int],
    count: int,
    geometric: bool,
    settings: DiagnoseConfig,
    generator,
    shared: bool = False,
) -> torch.Tensor:
    """The random smooth fields of placebo_bases read at the region's pixels, each view's
    weighted mean removed: [count, components, N] (components 2 for a displacement, else 1)."""
    batch, height, width = size
    views = 1 if shared else batch
    cells = settings.nulls.field_cells
    # Two fields per parameter are drawn (a displacement's x and y); a gain uses the first only,
    # so the second is drawn (the same random stream either way) but not upsampled.
    components = 2 if geometric else 1
    grid = torch.randn(count * views * 2, 1, cells, cells, generator=generator)
    kept = grid.view(count, views, 2, cells, cells)[:, :, :components]
    fields = torch.nn.functional.interpolate(
        kept.reshape(-1, 1, cells, cells), size=(height, width), mode="bilinear", align_corners=True
    )  # [count * views * components, 1, H, W]
    # Read at the region's pixels only: one flat gather per parameter (field index, then pixel).
    view = torch.zeros_like(pixels.view) if shared else pixels.view
    pixel = pixels.row * width + pixels.column
    offsets = torch.arange(components)[:, None] * (height * width)
    index = (view * components * height * width)[None] + offsets + pixel[None]  # [components, N]
    values = fields.view(count, -1).index_select(1, index.reshape(-1))
    values = values.view(count, components, -1)  # [count, components, N]
    # A placebo must mean nothing: without its mean over the view's object (weighted by the
    # render's energy), a random gain field is partly a uniform gain (an exposure), and a
    # random displacement field partly a shift (a pose change).
    weight = pixels.energy
    total = torch.zeros(batch).index_add_(0, pixels.view, weight).clamp_min(1e-30)
    for component in range(components):
        # (summed along dim 0 of a transposed view: the same additions in the same order,
        # twice as fast as along dim 1)
        weighted = (values[:, component] * weight).T
        sums = torch.zeros(batch, count).index_add_(0, pixels.view, weighted).T
        values[:, component] -= (sums / total).index_select(1, pixels.view)
    return values


def _least_squares_at(chosen: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Coefficients [P] of bases [P, M, 3] that fit target [M, 3] (float64, the fitting pixels
    alone)."""
    chosen = chosen.flatten(1)
    gram = chosen @ chosen.T
    gram = gram + 1e-9 * gram.diagonal().mean().clamp_min(1e-30) * torch.eye(len(chosen))
    return torch.linalg.solve(gram, chosen @ target.flatten())


def _gain_least_squares(
    fields: torch.Tensor, rendered: torch.Tensor, target: torch.Tensor
) -> torch.Tensor:
    """_least_squares_at of gain bases fields[p, m] * rendered[m, c] (fields [P, M], rendered
    [M, 3], target [M, 3]) from the factored normal equations, in float64 throughout:
    sum_mc f_p r f_q r = sum_m f_p f_q |r|^2 and sum_mc f_p r t = sum_m f_p (r . t)."""
    rendered = rendered.double()
    return _gain_solve(fields, (rendered * rendered).sum(-1), (rendered * target).sum(-1))


def _gain_solve(
    fields: torch.Tensor, energy: torch.Tensor, correlation: torch.Tensor
) -> torch.Tensor:
    """_gain_least_squares from the per-pixel sums energy [M] (sum_c r^2) and correlation [M]
    (sum_c r t)."""
    fields = fields.double()
    gram = (fields * energy) @ fields.T
    gram = gram + 1e-9 * gram.diagonal().mean().clamp_min(1e-30) * torch.eye(len(fields))
    return torch.linalg.solve(gram, fields @ correlation)


def _per_view_least_squares(
    bases: torch.Tensor, target: torch.Tensor, fit: torch.Tensor, view: torch.Tensor, views: int
) -> torch.Tensor:
    """Coefficients [B, P] of bases [P, N, 3] that fit target [N, 3] on the pixels fit [N],
    each view on its own pixels (view [N], in view order as nonzero lists them): _least_squares
    of every view, with the normal equations of each view's block of pixels and one batched
    solve (zero for a view without fitting pixels)."""
    parameters = bases.shape[0]
    counts = torch.bincount(view, minlength=views)
    if bool((view[1:] < view[:-1]).any()):
        raise ValueError("_per_view_least_squares: pixels must be in view order")
    chosen = bases.double() * fit[None, :, None]  # zero outside the fitting half
    gram = torch.zeros(views, parameters, parameters, dtype=torch.float64)
    moment = torch.zeros(views, parameters, dtype=torch.float64)
    blocks = zip(chosen.split(counts.tolist(), 1), target.split(counts.tolist(), 0), strict=True)
    for index, (block, block_target) in enumerate(blocks):
        flat = block.reshape(parameters, -1)
        gram[index] = flat @ flat.T
        moment[index] = flat @ block_target.reshape(-1)
    ridge = 1e-9 * gram.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(1e-30)
    gram = gram + ridge[:, None, None] * torch.eye(parameters, dtype=torch.float64)
    fitted = torch.bincount(view[fit], minlength=views) > 0
    theta = torch.zeros(views, parameters, dtype=torch.float64)
    if bool(fitted.any()):
        theta[fitted] = torch.linalg.solve(gram[fitted], moment[fitted][..., None])[..., 0]
    return theta


def _placebo_reduction(
    pixels: _Pixels,
    data: DiagnosisData,
    per_view: int,
    shared: int,
    geometric: bool,
    settings: DiagnoseConfig,
    seed: int,
) -> float:
    generator = torch.Generator().manual_seed(seed)
    size = (data.view_count, *data.image_size)
    residual = pixels.residual
    explained = torch.zeros_like(residual)
    if per_view:
        # In float64 once (the fits and the prediction below read it; .double() is then free).
        bases = placebo_bases(pixels, size, per_view, geometric, settings, generator).double()
        # Every view's own fit at once (the views' normal equations are independent).
        theta = _per_view_least_squares(bases, residual, pixels.first, pixels.view, data.view_count)
        explained += torch.einsum("np,pnc->nc", theta.index_select(0, pixels.view), bases)
    fit, test = pixels.first, ~pixels.first
    halves = pixels.halves
    heldout_explained = explained.index_select(0, halves.test)
    if shared and not geometric:
        # A gain basis is a field times the render: its normal equations need the fields and
        # two per-pixel sums only (no [P, N, 3] bases; the response curve has 17 of them).
        fields = placebo_fields(pixels, size, shared, geometric, settings, generator, True)
        if per_view:
            theta = _gain_least_squares(
                fields[:, 0, fit], pixels.rendered[fit], (residual - explained)[fit]
            )
        else:  # nothing explained yet: the target is the residual
            fitting = fields[:, 0].index_select(1, halves.fit)
            theta = _gain_solve(fitting, halves.energy_fit, halves.correlation_fit)
        gains = theta @ fields[:, 0].index_select(1, halves.test).double()  # [M]
        heldout_explained += gains[:, None] * halves.rendered_test
    elif shared:
        # The bases at the fitting half for the fit, at the held-out half for the score: the
        # same numbers as the whole bases' rows there, without [P, N, 3] float64 copies.
        fields = placebo_fields(pixels, size, shared, geometric, settings, generator, True)
        chosen = _bases_at(fields, pixels, geometric, fit).double()
        theta = _least_squares_at(chosen, (residual - explained)[fit])
        heldout = _bases_at(fields, pixels, geometric, test).double()
        heldout_explained += torch.einsum("p,pnc->nc", theta, heldout)
    after = ((halves.residual_test - heldout_explained) ** 2).sum()
    return float(1 - after / halves.before.clamp_min(1e-30))


# The last views' placebo draws by parameter layout (per view, shared, geometric), with the
# views and settings they were drawn for: the draws depend on nothing else, so candidates of
# one layout (shadows and vignetting: 2 shared gains) share them, and a candidate measured
# again (recon.diagnose.geometric_checks restores probes alone) does not draw them twice.
_LAST_DRAWS: list = []  # [(data, settings, {layout: draws})], at most one entry


def placebo_draws(
    data: DiagnosisData, per_view: int, shared: int, geometric: bool, settings: DiagnoseConfig
) -> list[float]:
    """The held-out reductions of settings.nulls.placebo_draws placebos of one parameter
    layout on data (seeds nulls.seed, nulls.seed + 1, ...), cached for the last data asked
    about (by identity) under equal settings."""
    if not (_LAST_DRAWS and _LAST_DRAWS[0][0] is data and _LAST_DRAWS[0][1] == settings):
        _LAST_DRAWS[:] = [(data, copy.deepcopy(settings), {})]
    cache = _LAST_DRAWS[0][2]
    layout = (per_view, shared, geometric)
    if layout not in cache:
        if "pixels" not in cache:  # (the same for every layout)
            cache["pixels"] = _Pixels.of(data, settings.block_pixels)
        pixels = cache["pixels"]
        cache[layout] = [
            _placebo_reduction(
                pixels, data, per_view, shared, geometric, settings, settings.nulls.seed + d
            )
            for d in range(settings.nulls.placebo_draws)
        ]
    return list(cache[layout])


def placebo_null(
    data: DiagnosisData, name: str, settings: DiagnoseConfig | None = None
) -> tuple[float, list[float]]:
    """The candidate's null: the settings.nulls.quantile of its placebos' held-out reductions on this
    run, and the draws."""
    settings = settings or DiagnoseConfig()
    per_view, shared = parameter_layout(name, data.view_count)
    draws = placebo_draws(data, per_view, shared, name in GEOMETRIC_EFFECTS, settings)
    threshold = float(
        torch.quantile(torch.tensor(draws, dtype=torch.float64), settings.nulls.quantile)
    )
    return threshold, draws


def fit_psnr(data: DiagnosisData) -> float:
    """The fit's held-out PSNR over the region (peak 1, linear): how much mismatch there is."""
    weight = data.region
    mse = float((data.residual**2 * weight).sum() / (weight.sum() * 3).clamp_min(1))
    return 10 * math.log10(1 / max(mse, 1e-20))


def null_evidence(
    data: DiagnosisData,
    name: str,
    reduction: float,
    interval: tuple[float, float],
    settings: DiagnoseConfig | None = None,
) -> Evidence:
    """Whether a candidate's held-out reduction (the probe's, with its bootstrap interval over
    views) clears its placebo null on this run, with the reason in one line."""
    settings = settings or DiagnoseConfig()
    threshold, draws = placebo_null(data, name, settings)
    per_view, shared = parameter_layout(name, data.view_count)
    size = f"{per_view} per view" if per_view else f"{shared}"
    if per_view and shared:
        size = f"{per_view} per view and {shared} shared"
    psnr = fit_psnr(data)
    low = interval[0]
    passed = low > threshold
    verdict = "significant" if passed else "not significant"
    reason = (
        f"{name} removes {100 * reduction:.1f} % of the held-out error (lower bound "
        f"{100 * low:.1f} %); {len(draws)} placebo effects with the same parameters "
        f"({size}) remove up to {100 * threshold:.1f} % ({100 * settings.nulls.quantile:.0f}th "
        f"percentile) on this {psnr:.1f} dB fit: {verdict}"
    )
    return Evidence(
        kind=KIND,
        candidate=name,
        statistic=float(low),
        threshold=threshold,
        passed=passed,
        reason=reason,
        details={
            "test": "placebo",
            "reduction": float(reduction),
            "interval": [float(interval[0]), float(interval[1])],
            "placebo_reductions": draws,
            "parameters_per_view": per_view,
            "shared_parameters": shared,
            "fit_psnr": psnr,
        },
    )


def per_view_log_gains(data: DiagnosisData, weight: torch.Tensor) -> torch.Tensor:
    """Least-squares log gain per view and channel [B, 3] of observed against rendered over
    weight [B, H, W, 1] (the exposure and white balance probes' parameters, in closed form)."""
    observed, rendered = data.observed.double(), data.rendered.double()
    weight = weight.double()
    cross = (observed * rendered * weight).sum(dim=(1, 2))
    energy = (rendered**2 * weight).sum(dim=(1, 2))
    return torch.log(cross.clamp_min(1e-20) / energy.clamp_min(1e-20))


def split_half_evidence(
    data: DiagnosisData, name: str, settings: DiagnoseConfig | None = None
) -> Evidence | None:
    """Split-half agreement of a per-view gain's parameters (exposure: the luminance log gain
    per view; white balance: red and blue over green): fitted on each half of the held-out
    blocks, correlated over views, against the same correlation with one half's views
    permuted. None for other candidates (their parameters need the probe's fit)."""
    if name not in ("exposure", "white_balance"):
        return None
    settings = settings or DiagnoseConfig()
    batch, height, width, _ = data.observed.shape
    first = checkerboard(batch, height, width, settings.block_pixels) * data.region
    second = (1 - checkerboard(batch, height, width, settings.block_pixels)) * data.region
    halves = []
    for weight in (first, second):
        gains = per_view_log_gains(data, weight)
        if name == "exposure":
            values = gains.mean(dim=1, keepdim=True)
        else:
            values = torch.stack([gains[:, 0] - gains[:, 1], gains[:, 2] - gains[:, 1]], -1)
        halves.append(values - values.mean(dim=0, keepdim=True))
    one, other = (half.flatten() for half in halves)

    def correlation(a: torch.Tensor, b: torch.Tensor) -> float:
        return float((a * b).sum() / ((a * a).sum() * (b * b).sum()).sqrt().clamp_min(1e-30))

    observed = correlation(one, other)
    null = permuted_correlations(
        halves[0].reshape(batch, -1).double(),
        halves[1].reshape(batch, -1).double(),
        settings.nulls.permutations,
        settings.nulls.seed,
    )
    threshold = float(torch.quantile(null, settings.nulls.quantile))
    p_value = float((1 + (null >= observed).sum()) / (1 + null.numel()))
    passed = observed > threshold
    reason = (
        f"{name}'s per-view parameters from the two halves of the held-out blocks agree "
        f"(r = {observed:.2f} over {batch} views; permuted views reach {threshold:.2f}, "
        f"p = {p_value:.2g}): " + ("not noise" if passed else "indistinguishable from noise")
    )
    return Evidence(
        kind=KIND,
        candidate=name,
        statistic=observed,
        threshold=threshold,
        passed=passed,
        reason=reason,
        details={"test": "split_half", "p_value": p_value, "views": batch},
    )
