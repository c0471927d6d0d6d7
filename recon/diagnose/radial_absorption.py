"""Absorption evidence for vignetting without a refit: a fixed-effects regression.

A falloff shared by every view is mostly baked into the fitted texture: each texel's albedo took
the falloff averaged over the image radii it was seen at. What the texture cannot hold is the
change of that falloff between views, because one surface cell is seen near the centre of one
view and near the edge of another. On the training views' interior pixels, per channel,

    log(observed / rendered) = g[cell] + e[view] + alpha r^2 + beta r^4 + noise

with a gain g per texture cell (the albedo correction the fit would make), a gain e per view
(exposure and white balance, so a per-view effect does not masquerade as a radial one) and the
log falloff alpha r^2 + beta r^4 (r: radius over the half image diagonal, as the Vignetting
module): one sparse weighted least-squares problem, solved exactly by eliminating the cell
gains. Weights are the rendered value squared, so the log fit approximates squared error in
linear radiance.

The evidence is held out like the rest: the cell gains (and the falloff) carry to the held-out
views; each held-out view's own gain is fitted on one half of its pixel blocks and the error is
measured on the other half, with and without the falloff. A few scatter operations replace the
two refits (texture, light and effect, against a control) this used to take.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData, box_dilate
from recon.diagnose.which import block_halves
from recon.effects.photometric import Vignetting, normalised_radius

# Coverage that counts as inside (a blurred observed mask is 1 only up to rounding).
FULL_COVERAGE = 0.999
# Radii (over the half diagonal) on which the log falloff is projected onto the module's
# polynomial 1 + a r^2 + b r^4 for the reported parameters.
PROJECTION_RADII = 101


@dataclass
class InteriorPixels:
    """Pixels well inside both the observed and the rendered object, one row per (pixel,
    channel): N rows.

    log_ratio, weight, rendered, observed: [N]; radius: [N] over the half diagonal;
    cell: [N] texture cell index x channel (cells_per_side^2 * 3 groups); view: [N] view index
    x channel (B * 3 groups); first_half: [N] bool, the pixel's block is in the first half of
    block_halves; view_count: B.
    """

    log_ratio: torch.Tensor
    weight: torch.Tensor
    rendered: torch.Tensor
    observed: torch.Tensor
    radius: torch.Tensor
    cell: torch.Tensor
    view: torch.Tensor
    first_half: torch.Tensor
    view_count: int
    cells_per_side: int

    @classmethod
    def from_data(cls, data: DiagnosisData, settings: DiagnoseConfig) -> InteriorPixels:
        """The interior pixels of data (config diagnose.regression_*: cells per side, interior
        margin, least rendered value; block_pixels for the halves)."""
        margin = settings.regression_interior_margin
        cells_per_side = settings.regression_cells_per_side
        batch, height, width, channels = data.observed.shape
        covered = (data.rendered_alpha >= FULL_COVERAGE) & (data.observed_alpha >= FULL_COVERAGE)
        covered = covered & (data.texel_uv[..., :1] >= 0)
        # margin pixels in from either silhouette: antialiasing, a sub-pixel edge
        # offset and grazing-angle shading are not a falloff.
        outside = (~covered).float().permute(0, 3, 1, 2)
        interior = box_dilate(outside, margin) == 0
        interior = interior.permute(0, 2, 3, 1).expand(batch, height, width, channels)
        bright = (data.rendered > settings.regression_minimum_rendered) & (data.observed > 0)
        keep = interior & bright
        radius = normalised_radius(data.cameras, height, width, data.rendered)
        uv = (data.texel_uv * cells_per_side).long().clamp(0, cells_per_side - 1)
        cell = uv[..., 1] * cells_per_side + uv[..., 0]
        view = torch.arange(batch, device=keep.device)[:, None, None].expand(batch, height, width)
        first, _ = block_halves(batch, height, width, keep.device, settings.block_pixels)
        # The kept (pixel, channel) rows as flat indices, found once: every column below is a
        # gather of them (the same values, in the same order, as indexing with the mask,
        # which would search the [B, H, W, 3] mask again for each of the seven columns).
        kept = torch.nonzero(keep.reshape(-1)).squeeze(1)  # [N] over B * H * W * 3
        pixel = torch.div(kept, channels, rounding_mode="floor")  # [N] over B * H * W
        channel = kept - pixel * channels

        def per_channel(values: torch.Tensor) -> torch.Tensor:
            return values.reshape(-1).index_select(0, pixel)

        rendered = data.rendered.reshape(-1).index_select(0, kept).double()
        observed = data.observed.reshape(-1).index_select(0, kept).double()
        return cls(
            log_ratio=(observed / rendered).log(),
            weight=rendered * rendered,
            rendered=rendered,
            observed=observed,
            radius=per_channel(radius).double(),
            cell=per_channel(cell) * channels + channel,
            view=per_channel(view) * channels + channel,
            first_half=per_channel(first[..., 0] > 0),
            view_count=batch,
            cells_per_side=cells_per_side,
        )

    def regressors(self) -> torch.Tensor:
        """[N, 2]: r^2 and r^4 - 0.75 r^2 (the module's decorrelated pair)."""
        squared = self.radius * self.radius
        return torch.stack([squared, squared * (squared - 0.75)], dim=1)


def _group_sum(values: torch.Tensor, groups: torch.Tensor, count: int) -> torch.Tensor:
    """Sum of values [N, ...] per group [N] -> [count, ...]."""
    total = torch.zeros(count, *values.shape[1:], dtype=values.dtype, device=values.device)
    return total.index_add_(0, groups, values)


def _group_mean(
    values: torch.Tensor, groups: torch.Tensor, weight: torch.Tensor, count: int
) -> torch.Tensor:
    """Weighted mean of values [N] per group [N] -> [count] (0 for empty groups)."""
    mass = _group_sum(weight, groups, count)
    return _group_sum(values * weight, groups, count) / mass.clamp_min(1e-30)


@dataclass
class GainFit:
    """cell_gain: [CELLS^2 * 3] log gains; coefficients: [2] (alpha, beta) of the log falloff
    in the regressors' basis (zeros for the control); cell_seen: [CELLS^2 * 3] bool."""

    cell_gain: torch.Tensor
    coefficients: torch.Tensor
    cell_seen: torch.Tensor


def fit_gains(pixels: InteriorPixels, with_falloff: bool) -> GainFit:
    """Weighted least squares for the cell gains, the view gains (and the falloff when
    with_falloff) on the training pixels, solved exactly: the cell block of the normal
    equations is diagonal, so it is eliminated (a Schur complement over the few view gains
    and falloff coefficients; alternating demeaning converges far too slowly when each cell is
    seen in a few views only). The cell and view gains share one constant per channel; the
    pseudo-inverse picks one split of it, which no prediction depends on."""
    cell_count = pixels.cells_per_side * pixels.cells_per_side * 3
    view_count = pixels.view_count * 3
    weight, target = pixels.weight, pixels.log_ratio
    regressors = pixels.regressors() if with_falloff else target.new_zeros(target.shape[0], 0)
    weighted = regressors * weight[:, None]
    cell_mass = _group_sum(weight, pixels.cell, cell_count)
    cell_view = _group_sum(weight, pixels.cell * view_count + pixels.view, cell_count * view_count)
    # The coupling of each cell to the view gains and the regressors: [cells, views + K].
    coupling = torch.cat(
        [cell_view.view(cell_count, view_count), _group_sum(weighted, pixels.cell, cell_count)],
        dim=1,
    )
    view_regressors = _group_sum(weighted, pixels.view, view_count)
    lower = torch.cat(
        [
            torch.cat(
                [torch.diag(_group_sum(weight, pixels.view, view_count)), view_regressors], 1
            ),
            torch.cat([view_regressors.T, regressors.T @ weighted], 1),
        ]
    )
    inverse_mass = torch.where(cell_mass > 0, 1 / cell_mass.clamp_min(1e-30), 0.0)
    cell_rhs = _group_sum(weight * target, pixels.cell, cell_count)
    other_rhs = torch.cat(
        [_group_sum(weight * target, pixels.view, view_count), weighted.T @ target]
    )
    schur = lower - coupling.T @ (coupling * inverse_mass[:, None])
    reduced_rhs = other_rhs - coupling.T @ (cell_rhs * inverse_mass)
    solution = torch.linalg.pinv(schur, hermitian=True) @ reduced_rhs
    cell_gain = inverse_mass * (cell_rhs - coupling @ solution)
    coefficients = torch.zeros(2, dtype=target.dtype, device=target.device)
    if with_falloff:
        coefficients = solution[view_count:]
    return GainFit(cell_gain, coefficients, cell_mass > 0)


def heldout_errors(pixels: InteriorPixels, fit: GainFit) -> torch.Tensor:
    """Per-view squared error sums [B] on the second half of the held-out pixels (in cells the
    training views saw), each view's gain fitted on its first half."""
    seen = fit.cell_seen[pixels.cell]
    prediction = fit.cell_gain[pixels.cell] + pixels.regressors() @ fit.coefficients
    view_count = pixels.view_count * 3
    fitting = seen & pixels.first_half
    view_gain = _group_mean(
        (pixels.log_ratio - prediction)[fitting],
        pixels.view[fitting],
        pixels.weight[fitting],
        view_count,
    )
    scored = seen & ~pixels.first_half
    predicted = pixels.rendered * (prediction + view_gain[pixels.view]).exp()
    squared = (pixels.observed - predicted) ** 2
    views = pixels.view[scored] // 3
    errors = torch.zeros(pixels.view_count, dtype=squared.dtype, device=squared.device)
    return errors.index_add_(0, views, squared[scored])


def falloff_module(coefficients: torch.Tensor) -> Vignetting:
    """A Vignetting module whose polynomial 1 + a r^2 + b r^4 is the least-squares match (over
    r in [0, 1], area-weighted) of the fitted exp(alpha r^2 + beta (r^4 - 0.75 r^2))."""
    radius = torch.linspace(0.0, 1.0, PROJECTION_RADII, dtype=torch.float64)
    squared = radius * radius
    basis = torch.stack([squared, squared * (squared - 0.75)], dim=1)
    falloff = (basis @ coefficients.cpu()).exp()
    design = torch.stack([squared, squared * squared], dim=1) * radius.sqrt()[:, None]
    target = (falloff - 1) * radius.sqrt()
    a, b = torch.linalg.lstsq(design, target[:, None]).solution[:, 0].tolist()
    module = Vignetting()
    module.set_polynomial(a, b)
    return module


def radial_absorption(
    training: DiagnosisData, heldout: DiagnosisData, settings: DiagnoseConfig
) -> tuple[torch.Tensor, torch.Tensor, Vignetting]:
    """Held-out per-view error sums [B] without and with the falloff (cell and view gains in
    both), and the fitted falloff as a Vignetting module. A fitted falloff that brightens
    half-way out is no vignetting (a lens only loses light off axis; a specular or
    interreflection misfit can put brighter pixels near the rim): its errors are the control's,
    no evidence."""
    train_pixels = InteriorPixels.from_data(training, settings)
    test_pixels = InteriorPixels.from_data(heldout, settings)
    control = heldout_errors(test_pixels, fit_gains(train_pixels, with_falloff=False))
    with_falloff = fit_gains(train_pixels, with_falloff=True)
    module = falloff_module(with_falloff.coefficients)
    if module.parameters_summary()["half_radius_falloff"] >= 1.0:
        return control, control.clone(), module
    return control, heldout_errors(test_pixels, with_falloff), module
