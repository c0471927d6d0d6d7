"""Lobe evidence: does the residual follow a highlight under the fitted light, view by view?

A specular highlight moves over the surface as the camera moves: at a surface point it is
bright in the views whose half-vector (light + view direction) lines up with the normal and
dark in the others. A fitted albedo is one colour per surface point: it absorbs the highlight's
mean over the training views, never its change from view to view. What is left at a surface
point, from view to view, is the lobe's departure from its mean there; on held-out views alone
a highlight shows in two or three views, too few for a bootstrap over views
(docs/decisions/0191-blind-misses.md), but every training view and every held-out view carries
it, at every pixel the object covers.

The check, on the training views and the held-out views together (N object pixels, interior
only: silhouette pixels carry the misalignment):

1. the luminance residual r [N], each view's observed pixels first divided by that view's
   gain against the render (divide_view_gains: an exposure times the albedo's own misfit is
   a product no additive nuisance takes out), and, for each exponent e of
   diagnose.lobe.exponents, the normalised Blinn-Phong lobe of the Specular effect under the fitted light,
   f_e = max(0, n.l) (e + 8) / (8 pi) max(0, n.h)^e [N];
2. both with the nuisances the fit could have absorbed or a camera could have made projected
   out: one offset per surface cell (a voxel grid over the object's surface points,
   diagnose.lobe.cells_per_axis per axis: the albedo), one gain per view on the render
   (an exposure) and one coefficient per view on the render's image Laplacian (a blur's
   first-order change, diagnose.lobe.blur_nuisance: a blur changes the shading where it
   curves, under the fitted light only, so placebo lights would not reproduce it); an exact
   least-squares projection;
3. the largest partial correlation of r with f_e over the exponents (a highlight adds light:
   only a positive one counts);
4. its null: the same statistic with the light replaced by placebo lights
   (diagnose.lobe.placebo_lights directions at least diagnose.lobe.placebo_separation_degrees
   from the fitted light, a Fibonacci sphere), each maximised over the same exponents. A
   residual that changes with the view for another reason (a misalignment, a shadow's edge,
   interreflection, a camera effect) correlates with lobes under any light; a highlight only
   with the lobe under its own light. The p-value is the share of placebo lights that reach
   the fitted light's correlation. The statistic is the correlation's excess over the placebo
   lights' 95th percentile: a null derived from the run itself, so a poor fit's larger misfit
   raises its own bar.

The decision (recon.diagnose.decision, row 'lobe') names the candidate when the statistic clears
diagnose.decision.lobe_allowance and the p-value is below diagnose.decision.lobe_alpha.

The same test runs on the relight split under its known light (evidence 'relight_lobe',
diagnose.lobe.relight): there the fitted light's own error is absent, which on a poor fit (the
Mitsuba bunny at 48 px) hides the highlight under the fitted light. There its pixels are
weighted (diagnose.lobe.relight_spread_bins): a fit's residual is several times larger where
the relight sun lights the surface than in the dim part (normal, texture and pose errors
scale with the light they shade), so unweighted the sun's lobe, lying where the residual is
large, out-correlates placebo lights' lobes lying where it is small, highlight or not (the
Mitsuba spot's relight split, docs/decisions/0211-shadows-specular-mitsuba.md). Each pixel is
weighted by 1 / the residual's robust spread among the pixels of its bin of the sun's cosine,
for the sun and every placebo light alike (docs/decisions/0216-relight-specular.md).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData, box_erode
from recon.diagnose.decision import lobe_threshold
from recon.diagnose.pixel_table import view_directions
from recon.diagnose.records import Candidate, Evidence
from recon.effects.light_transport import dominant_light, fibonacci_directions

if TYPE_CHECKING:  # producers imports this module to register the producer
    from recon.diagnose.producers import EvidenceInputs

KIND = "lobe"
# The same test on the relight split under its known light (diagnose.lobe.relight): no fitted
# light's error there, and the relight sun's highlights sit elsewhere on the surface.
RELIGHT_KIND = "relight_lobe"
# Lights whose lobes are projected together (memory, not a tuned number).
LIGHTS_PER_CHUNK = 32
# Channel weights of the luminance the residual is measured in (Rec. 709).
LUMINANCE = (0.2126, 0.7152, 0.0722)


def interior_pixels(data: DiagnosisData) -> torch.Tensor:
    """[B, H, W] bool: pixels well inside both silhouettes (a one-pixel erosion of the
    observed and rendered coverage), where a triangle covers the pixel centre."""
    covered = (data.observed_alpha > 0.5) & (data.rendered_alpha > 0.5)
    covered = covered.float().permute(0, 3, 1, 2)
    inner = box_erode(covered, 1).permute(0, 2, 3, 1)[..., 0] > 0.5
    return inner & data.rendered_mask


def surface_cells(points: torch.Tensor, cells_per_axis: int) -> torch.Tensor:
    """Voxel labels [N] int64 of surface points [N, 3] on a cells_per_axis^3 grid over their
    bounding box (renumbered 0..M-1)."""
    low = points.min(dim=0).values
    span = (points.max(dim=0).values - low).clamp_min(1e-9)
    index = ((points - low) / span * cells_per_axis).long().clamp(0, cells_per_axis - 1)
    flat = (index[:, 0] * cells_per_axis + index[:, 1]) * cells_per_axis + index[:, 2]
    return torch.unique(flat, return_inverse=True)[1]


def divide_view_gains(
    residual: torch.Tensor, rendered: torch.Tensor, view: torch.Tensor
) -> torch.Tensor:
    """The residual [N] again once each view's observed pixels (residual + rendered [N]) are
    divided by that view's least-squares gain against the render (view [N]: view indices).

    Why before the nuisance projection, which has a per-view gain too: under a per-view
    exposure g_v the fitted albedo has averaged differently exposed training views, so it is
    off by a factor e(point) that differs over the surface, and the residual holds
    g_v x e(point) x render, a product of the view and the surface point. An additive gain per
    view and an offset per surface cell cannot take a product out; what is left is brightest
    where the light under test shines, so it follows that light's lobe or shadow more than a
    placebo light's. Dividing the view's gain out first leaves e(point) x render, which under
    the relight split's fixed sun the offsets per surface cell take. On data without an
    exposure every view's gain is about 1 and nothing changes."""
    observed = residual + rendered
    views = int(view.max()) + 1 if view.numel() else 0
    cross = torch.zeros(views, dtype=residual.dtype).index_add_(0, view, observed * rendered)
    power = torch.zeros(views, dtype=residual.dtype).index_add_(0, view, rendered * rendered)
    usable = (power > 0) & (cross > 0)
    gain = torch.where(usable, cross / power.clamp_min(1e-30), torch.ones_like(power))
    return observed / gain[view] - rendered


def project_out(
    values: torch.Tensor,
    cell: torch.Tensor,
    view: torch.Tensor,
    rendered: torch.Tensor,
    extra: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """values [N, K] with the nuisance space (an offset per cell, a gain on rendered [N] per
    view, and the columns of extra [N, E] if given) projected out exactly (Frisch-Waugh: cell
    means out, then the other columns with their cell means out by least squares); returns
    [N, K]. weights [N] (optional): weighted least squares, every row (values and nuisances)
    scaled by its weight first; the result is the weighted residual (rows scaled)."""
    cells = int(cell.max()) + 1 if cell.numel() else 0
    views = int(view.max()) + 1 if view.numel() else 0
    if weights is None:
        weights = torch.ones_like(rendered, dtype=values.dtype)
    weights = weights.to(values.dtype)
    # The weighted cell indicators' squared norms: a cell's offset column is its rows' weights.
    count = torch.zeros(cells, dtype=values.dtype).index_add_(0, cell, weights * weights)

    def without_cell_means(columns: torch.Tensor) -> torch.Tensor:
        columns = columns * weights[:, None]
        sums = torch.zeros(cells, columns.shape[1], dtype=columns.dtype).index_add_(
            0, cell, columns * weights[:, None]
        )
        return columns - weights[:, None] * (sums / count.clamp_min(1e-30)[:, None])[cell]

    gains = torch.zeros(values.shape[0], views, dtype=values.dtype)
    gains[torch.arange(values.shape[0]), view] = rendered.to(values.dtype)
    if extra is not None:
        gains = torch.cat([gains, extra.to(values.dtype)], dim=1)
    gains = without_cell_means(gains)
    out = without_cell_means(values)
    gram = gains.T @ gains
    size = gram.shape[0]
    ridge = 1e-9 * gram.diagonal().mean().clamp_min(1e-30) * torch.eye(size, dtype=gram.dtype)
    return out - gains @ torch.linalg.solve(gram + ridge, gains.T @ out)


def spread_weights(residual: torch.Tensor, sun_cosine: torch.Tensor, bins: int) -> torch.Tensor:
    """[N] weights 1 / s of the pixels: s is the robust spread (1.4826 x the median absolute
    value) of residual [N] (the nuisances projected out) among the pixels of the same bin of
    sun_cosine [N], bins of equal pixel count. A residual of a fit under a sun is larger where
    the sun lights the surface (normal, texture and pose errors scale with the light they
    shade): unweighted, a lobe under that sun lies where the residual is large and reads a
    larger correlation than placebo lights' lobes in the dim part, highlight or not. The
    median, not the RMS: a highlight is sparse and must not set its own weight. bins 1: one
    spread, every weight equal (the unweighted statistic)."""
    if bins <= 1 or residual.numel() < bins:
        return torch.ones_like(residual)
    edges = torch.quantile(sun_cosine, torch.linspace(0, 1, bins + 1, dtype=sun_cosine.dtype))
    index = torch.bucketize(sun_cosine, edges[1:-1].contiguous())
    spread = torch.ones(bins, dtype=residual.dtype)
    for item in range(bins):
        members = residual[index == item]
        if members.numel():
            spread[item] = 1.4826 * members.abs().median()
    floor = 1e-3 * float(1.4826 * residual.abs().median()) + 1e-30
    return 1.0 / spread.clamp_min(floor)[index]


def lobe_features(
    normals: torch.Tensor,
    to_camera: torch.Tensor,
    to_light: torch.Tensor,
    exponents: list[float],
) -> torch.Tensor:
    """Normalised Blinn-Phong lobes [N, K] (as recon.effects.light_transport.Specular shapes
    them, unit strength and irradiance) for unit normals, directions to the camera and to the
    light [N, 3]."""
    halfway = torch.nn.functional.normalize(to_camera + to_light, dim=-1)
    cosine = (normals * to_light).sum(-1).clamp_min(0.0)
    alignment = (normals * halfway).sum(-1).clamp_min(0.0)
    columns = [
        cosine * (exponent + 8) / (8 * math.pi) * alignment.pow(exponent) for exponent in exponents
    ]
    return torch.stack(columns, dim=-1)


def _pixels(data: DiagnosisData) -> dict[str, torch.Tensor]:
    """The interior pixels of data, flattened: residual and rendered luminance, view index,
    surface point, unit normal and direction to the camera; light directions per view [B, 3]."""
    keep = interior_pixels(data)
    weights = torch.tensor(LUMINANCE, dtype=torch.float64)
    residual = (data.residual.double() * weights).sum(-1)
    rendered = (data.rendered.double() * weights).sum(-1)
    points, to_camera = view_directions(data)
    normals = torch.nn.functional.normalize(data.normals.double(), dim=-1)
    view = torch.arange(data.view_count)[:, None, None].expand_as(keep)
    laplacian = image_laplacian(rendered)
    return {
        "residual": residual[keep],
        "rendered": rendered[keep],
        "laplacian": laplacian[keep],
        "view": view[keep],
        "points": points.double()[keep],
        "normals": normals[keep],
        "to_camera": to_camera.double()[keep],
    }


def image_laplacian(luminance: torch.Tensor) -> torch.Tensor:
    """[B, H, W] the 5-point Laplacian of [B, H, W] images (borders replicated): to first
    order, what a small blur of the render changes (a blur by a kernel of variance s^2 adds
    s^2 / 2 times it)."""
    padded = torch.nn.functional.pad(luminance[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    centre = padded[:, 1:-1, 1:-1]
    neighbours = padded[:, 1:-1, :-2] + padded[:, 1:-1, 2:] + padded[:, :-2, 1:-1]
    return neighbours + padded[:, 2:, 1:-1] - 4 * centre


def blur_columns(view: torch.Tensor, laplacian: torch.Tensor) -> torch.Tensor:
    """[N, B] the render's Laplacian [N] of each view, one column per view (zero on the other
    views' pixels): a blur's first-order change, with its own strength in every view."""
    views = int(view.max()) + 1 if view.numel() else 0
    columns = torch.zeros(view.shape[0], views, dtype=laplacian.dtype)
    columns[torch.arange(view.shape[0]), view] = laplacian
    return columns


def _light_per_pixel(data: DiagnosisData, direction: torch.Tensor, view: torch.Tensor):
    """Unit world directions [N, 3] toward a light of direction [3] in data's lighting frame,
    per pixel of views [N] (a camera-frame light turns with each view)."""
    if data.lighting.frame != "camera":
        return direction.double().expand(view.shape[0], 3)
    rotation = data.cameras.world_to_cam[:, :3, :3].double()
    per_view = direction.double() @ rotation  # [B, 3]: R_b^T d
    return per_view[view]


def _best_correlation(residual: torch.Tensor, features: torch.Tensor) -> tuple[float, int, float]:
    """(largest partial correlation, its column, its coefficient) of projected residual [N]
    and projected features [N, K]."""
    norms = features.norm(dim=0).clamp_min(1e-30)
    dots = (features * residual[:, None]).sum(0)
    correlations = dots / (norms * residual.norm().clamp_min(1e-30))
    best = int(correlations.argmax())
    return float(correlations[best]), best, float(dots[best] / norms[best] ** 2)


def lobe_statistic(
    parts: list[DiagnosisData], settings: DiagnoseConfig, spread_bins: int = 1
) -> dict[str, float | int | list[float]] | None:
    """The lobe statistic of views (parts: e.g. the training and the held-out views, each with
    the fitted light), its placebo-light null and the recovered lobe, or None when there is no
    light direction or too few pixels. Keys: correlation, p_value, exponent, strength
    (coefficient of the unit lobe in luminance over the light's irradiance), placebo_quantile
    (the placebo lights' 95th percentile), pixels, views, cells, spread_bins.

    spread_bins > 1: weighted least squares, each pixel weighted by 1 / the residual's robust
    spread among the pixels of its bin of the light's cosine (spread_weights), for the light and
    every placebo light alike; 1: unweighted."""
    lobe = settings.lobe
    direction, irradiance = dominant_light(parts[0].lighting)
    direction = direction.detach().double().cpu()
    scale = float((irradiance.detach().double().cpu() * torch.tensor(LUMINANCE).double()).sum())
    if float(direction.norm()) < 1e-9 or scale <= 0:
        return None
    direction = direction / direction.norm()
    tables = [_pixels(part) for part in parts]
    offsets = [0]
    for part in parts[:-1]:
        offsets.append(offsets[-1] + part.view_count)
    view = torch.cat(
        [table["view"] + offset for table, offset in zip(tables, offsets, strict=True)]
    )
    if view.numel() < lobe.minimum_pixels:
        return None

    def joined(key: str) -> torch.Tensor:
        return torch.cat([table[key] for table in tables])

    # At most diagnose.lobe.maximum_pixels, an even stride through the views' pixels: the cost
    # is pixels x placebo lights x exponents.
    keep = torch.arange(0, view.numel(), max(1, math.ceil(view.numel() / lobe.maximum_pixels)))
    view = view[keep]
    residual, rendered = joined("residual")[keep], joined("rendered")[keep]
    residual = divide_view_gains(residual, rendered, view)
    normals, to_camera = joined("normals")[keep], joined("to_camera")[keep]
    cell = surface_cells(joined("points")[keep], lobe.cells_per_axis)
    # A blur changes the shading where it curves, under the fitted light only (placebo lights
    # do not reproduce it): its first-order change is projected out with the nuisances.
    extra = blur_columns(view, joined("laplacian")[keep]) if lobe.blur_nuisance else None
    exponents = list(lobe.exponents)

    def light_rows(candidate: torch.Tensor) -> torch.Tensor:
        rows = []
        for part, table in zip(parts, tables, strict=True):
            rows.append(_light_per_pixel(part, candidate, table["view"]))
        return torch.cat(rows)[keep]

    placebos = fibonacci_directions(lobe.placebo_lights).double()
    separation = math.cos(math.radians(lobe.placebo_separation_degrees))
    placebos = placebos[(placebos @ direction) < separation]
    directions = torch.cat([direction[None], placebos])
    weights = None
    if spread_bins > 1:
        unweighted = project_out(residual[:, None], cell, view, rendered, extra)[:, 0]
        sun_cosine = (normals * light_rows(direction)).sum(-1)
        weights = spread_weights(unweighted, sun_cosine, spread_bins)
    residual_p = project_out(residual[:, None], cell, view, rendered, extra, weights)[:, 0]
    scores = []
    # Projection is linear: the lights' lobes are projected in chunks (memory).
    for chunk in directions.split(LIGHTS_PER_CHUNK):
        features = torch.cat(
            [lobe_features(normals, to_camera, light_rows(item), exponents) for item in chunk],
            dim=1,
        )
        projected = project_out(features, cell, view, rendered, extra, weights)
        for index in range(chunk.shape[0]):
            block = projected[:, index * len(exponents) : (index + 1) * len(exponents)]
            scores.append(_best_correlation(residual_p, block))
    correlation, best, coefficient = scores[0]
    null = torch.tensor([score[0] for score in scores[1:]], dtype=torch.float64)
    p_value = float((1 + (null >= correlation).sum()) / (1 + null.numel()))
    quantile = float(torch.quantile(null, 0.95)) if null.numel() else float("nan")
    return {
        "correlation": correlation,
        "p_value": p_value,
        "exponent": exponents[best],
        "strength": coefficient / scale,
        "placebo_quantile": quantile,
        "placebo_lights": int(null.numel()),
        "pixels": int(view.numel()),
        "views": int(sum(part.view_count for part in parts)),
        "cells": int(cell.max()) + 1,
        "spread_bins": spread_bins,
    }


def lobe_evidence(
    parts: list[DiagnosisData], name: str, settings: DiagnoseConfig, kind: str = KIND
) -> Evidence | None:
    """Whether the residual of the views follows a highlight's lobe under their light beyond
    placebo lights (threshold and passed are the decision config's; the decision re-derives
    them); None when it cannot be measured (no light direction, too few pixels). kind: 'lobe'
    (the training and held-out views under the fitted light) or 'relight_lobe' (the relight
    split under its own, known light)."""
    bins = settings.lobe.relight_spread_bins if kind == RELIGHT_KIND else 1
    measured = lobe_statistic(parts, settings, bins)
    if measured is None:
        return None
    decision = settings.decision
    threshold = lobe_threshold(name, decision)
    if kind == RELIGHT_KIND:
        threshold = max(threshold, decision.relight_lobe_minimum)
    light = "the relight split's known light" if kind == RELIGHT_KIND else "the fitted light"
    reason = (
        f"{name}: the residual follows a highlight's lobe under {light} from view to "
        f"view (exponent {measured['exponent']:g}, r = {measured['correlation']:.3f} over "
        f"{measured['views']} views, p = {measured['p_value']:.2g} against "
        f"{measured['placebo_lights']} placebo lights"
        + (
            f", pixels weighted by the residual's spread in {bins} bins of the sun's cosine"
            if bins > 1
            else ""
        )
        + "); its excess over the placebo lights' 95th percentile"
    )
    parameters = {"strength": measured["strength"], "exponent": measured["exponent"]}
    return placebo_excess_evidence(
        kind, name, measured, threshold, decision.lobe_alpha, reason, parameters
    )


def placebo_excess_evidence(
    kind: str,
    name: str,
    measured: dict,
    threshold: float,
    alpha: float,
    reason: str,
    parameters: dict,
) -> Evidence:
    """Evidence whose statistic is a correlation's excess over its placebo directions' 95th
    percentile (measured: correlation, placebo_quantile, p_value): what the predicted pattern
    explains beyond what any placebo explains of this fit's residual, so that a 20 dB fit's
    misfit, which correlates with every pattern more than a 36 dB fit's does, sets its own bar.
    It passes above threshold with p below alpha."""
    statistic = float(measured["correlation"]) - float(measured["placebo_quantile"])
    return Evidence(
        kind=kind,
        candidate=name,
        statistic=statistic,
        threshold=threshold,
        passed=statistic > threshold and measured["p_value"] < alpha,
        reason=reason,
        details={**measured, "parameters": parameters},
    )


def lobe_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Lobe evidence for the candidates with a lobe allowance (specular), on the training views
    (rendered here with the fitted model) and the held-out views together."""
    names = {candidate.name for candidate in candidates}
    wanted = [name for name in settings.decision.lobe_allowance if name in names]
    if not settings.lobe.enabled or not wanted or len(inputs.training.cameras) == 0:
        return []
    parts = [inputs.training_views(settings.band_pixels), inputs.data]
    evidence = [lobe_evidence(parts, name, settings) for name in wanted]
    if inputs.relight is not None and settings.lobe.relight:
        evidence += [
            lobe_evidence([inputs.relight], name, settings, RELIGHT_KIND) for name in wanted
        ]
    return [item for item in evidence if item is not None]
