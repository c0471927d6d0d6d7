"""Where the sim-to-real gap lies: the residual binned in seven domains, each with a structure
score (how a score is made: recon.diagnose.residuals):

    {domain: {"score": float, "score_in_sample": float, "summary": {...}}}

with domain in image_position, surface, view, intensity, light_geometry, edges, frequency.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from recon.diagnose.data import DiagnosisData
from recon.diagnose.residuals import (
    BinBaseline,
    BinStage,
    ResidualSamples,
    adaptive_grid,
    bin_counts,
    bin_means,
    bin_ratio,
    constant_features,
    luminance_of,
    quantile_edges,
    scalar_means,
)
from recon.effects.light_transport import dominant_light, view_directions
from recon.errors import ReconError

# Edges: signed distances to the rendered silhouette are clamped to +-this many pixels.
EDGE_DISTANCE_PIXELS = 4
# Light geometry: angle between the normal and the half vector (degrees); the lobe lives low.
HALF_ANGLE_EDGES_DEGREES = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0, 180.0001)
LIGHT_COSINE_BINS = 8
RADIAL_BINS = 16
SPECTRUM_BINS = 12
AUTOCORRELATION_LAGS = (1, 2, 4)


def image_position_domain(
    data: DiagnosisData, samples: ResidualSamples | None = None, grid_size: int = 16
) -> dict:
    """Cells of a grid over the image (x, y), stacked over views, and the radius from the
    principal point: vignetting, distortion, lens blur. The score is the better of the two.

    Summary: the grid's mean residual luminance and counts [G][G] (row 0 at the top), the radial
    profile (radius / the farthest corner, RADIAL_BINS rings): mean residual [K][3], gain
    sum(observed) / sum(rendered) [K][3] (the vignetting curve), counts, and both sub-scores.
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    height, width = data.image_size
    grid = adaptive_grid(grid_size, len(samples))
    cell_row = (samples.row * grid) // height
    cell_column = (samples.column * grid) // width
    cells = cell_row * grid + cell_column
    grid_score, grid_in_sample = samples.binned_score(cells, grid * grid, "views")

    intrinsics = data.cameras.intrinsics.double()
    centre_x = intrinsics[samples.view, 0, 2]
    centre_y = intrinsics[samples.view, 1, 2]
    offset_x = samples.column.double() + 0.5 - centre_x
    offset_y = samples.row.double() + 0.5 - centre_y
    radius = torch.sqrt(offset_x**2 + offset_y**2)
    # Normalised by the farthest image corner of each view's principal point.
    corners_x = torch.stack([centre_x, width - centre_x]).abs().amax(0)
    corners_y = torch.stack([centre_y, height - centre_y]).abs().amax(0)
    normalised = radius / torch.sqrt(corners_x**2 + corners_y**2)
    rings = (normalised * RADIAL_BINS).long().clamp(0, RADIAL_BINS - 1)
    radial_score, radial_in_sample = samples.binned_score(rings, RADIAL_BINS, "views")

    residual_luminance = luminance_of(samples.residual)[:, None]
    score, in_sample = max((grid_score, grid_in_sample), (radial_score, radial_in_sample))
    return {
        "score": score,
        "score_in_sample": in_sample,
        "summary": {
            "samples": len(samples),
            "grid_size": grid,
            "grid_score": grid_score,
            "grid_score_in_sample": grid_in_sample,
            "grid_mean_luminance": _grid(
                scalar_means(residual_luminance, cells, grid * grid), grid
            ),
            "grid_counts": _grid(bin_counts(cells, grid * grid), grid),
            "radial_score": radial_score,
            "radial_score_in_sample": radial_in_sample,
            "radial_edges": [index / RADIAL_BINS for index in range(RADIAL_BINS + 1)],
            "radial_mean_residual": bin_means(samples.residual, rings, RADIAL_BINS),
            "radial_ratio": bin_ratio(samples.observed, samples.rendered, rings, RADIAL_BINS),
            "radial_counts": bin_counts(rings, RADIAL_BINS),
        },
    }


def _grid(values: list, size: int) -> list:
    """A flat row-major list of size * size entries as rows."""
    return [values[row * size : (row + 1) * size] for row in range(size)]


def surface_domain(
    data: DiagnosisData, samples: ResidualSamples | None = None, grid_size: int = 32
) -> dict:
    """Cells of the fitted UV atlas, stacked over views: shadows and interreflection (fixed on
    the surface); with a second model, per (texel cell, view) means beyond the texel cells
    ("view_dependent_score"): a residual that changes from view to view at one texel is
    view-dependent, e.g. specular.

    Only pixels a fitted triangle covers count. Summary: the atlas grid's mean residual
    luminance, across-view standard deviation of the per-view cell means (None where fewer
    than two views see the cell) and counts [G][G] (row 0 = v 0, the texture's top).
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    uv = data.texel_uv[samples.view, samples.row, samples.column].double()  # [N, 2]
    textured = (uv >= 0).all(-1)
    summary: dict = {"samples": int(textured.sum()), "grid_size": 0}
    if int(textured.sum()) < 2:
        summary.update({"view_dependent_score": 0.0, "view_dependent_score_in_sample": 0.0})
        return {"score": 0.0, "score_in_sample": 0.0, "summary": summary}
    surface = samples.subset(textured)
    uv = uv[textured]
    grid = adaptive_grid(grid_size, len(surface), per_cell=4)
    cell_column = (uv[:, 0] * grid).long().clamp(0, grid - 1)
    cell_row = (uv[:, 1] * grid).long().clamp(0, grid - 1)
    cells = cell_row * grid + cell_column
    texel_stage = surface.response().rebinned(cells, grid * grid)
    score, in_sample = surface.baseline("views").score(texel_stage)

    views = data.view_count
    cell_views = cells * views + surface.view
    # Beyond the response and the texel cells, fitted on random pixel halves of every view.
    texel_baseline = BinBaseline(
        surface.residual, [surface.response(), texel_stage], surface.pixel_half()
    )
    view_stage = BinStage(constant_features(len(surface), 3), cell_views, grid * grid * views)
    view_score, view_in_sample = texel_baseline.score(view_stage)

    residual_luminance = luminance_of(surface.residual)[:, None]
    # Across-view spread at each texel cell: the std over views of the cell's per-view mean.
    per_view = torch.zeros(grid * grid * views, dtype=torch.float64)
    per_view.index_add_(0, cell_views, residual_luminance[:, 0])
    per_view_counts = torch.bincount(cell_views, minlength=grid * grid * views).double()
    seen = per_view_counts > 0
    per_view_means = (per_view / per_view_counts.clamp_min(1)).view(grid * grid, views)
    seen = seen.view(grid * grid, views)
    seen_count = seen.sum(1).double()
    mean_over_views = (per_view_means * seen).sum(1) / seen_count.clamp_min(1)
    spread = (((per_view_means - mean_over_views[:, None]) ** 2) * seen).sum(1)
    spread = (spread / (seen_count - 1).clamp_min(1)).sqrt()
    across_view_std = [
        float(spread[index]) if seen_count[index] >= 2 else None for index in range(grid * grid)
    ]
    summary.update(
        {
            "grid_size": grid,
            "view_dependent_score": view_score,
            "view_dependent_score_in_sample": view_in_sample,
            "mean_luminance": _grid(scalar_means(residual_luminance, cells, grid * grid), grid),
            "across_view_std": _grid(across_view_std, grid),
            "counts": _grid(bin_counts(cells, grid * grid), grid),
        }
    )
    return {"score": score, "score_in_sample": in_sample, "summary": summary}


def view_domain(data: DiagnosisData, samples: ResidualSamples | None = None) -> dict:
    """Per view and channel: exposure, white balance (an affine response per view beyond the
    shared one); pose error and motion blur show here only as far as they change a view's level.
    Summary per view: names, mean residual [B][3], gain sum(observed) / sum(rendered) [B][3],
    RMSE [B], counts [B]."""
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    views = data.view_count
    score, in_sample = samples.binned_score(samples.view, views, "pixels")
    squares = torch.zeros(views, dtype=torch.float64)
    squares.index_add_(0, samples.view, (samples.residual**2).mean(-1))
    counts = torch.bincount(samples.view, minlength=views).double()
    return {
        "score": score,
        "score_in_sample": in_sample,
        "summary": {
            "samples": len(samples),
            "names": list(data.names),
            "mean_residual": bin_means(samples.residual, samples.view, views),
            "gain": bin_ratio(samples.observed, samples.rendered, samples.view, views),
            "rmse": [
                math.sqrt(float(squares[view] / counts[view])) if counts[view] > 0 else None
                for view in range(views)
            ],
            "counts": bin_counts(samples.view, views),
        },
    }


def intensity_domain(data: DiagnosisData, samples: ResidualSamples | None = None) -> dict:
    """Bins of the rendered value, per channel: response curve, gamma, tone mapping, and (its
    linear part) a gain common to all views. Scored about the residual's mean per channel (not
    beyond a response, which is what this domain measures). Summary: "linear_score" (a line per
    channel instead of the bins), "nonlinear_score" (what the bins add to the line, as a share
    of what the line leaves), and per channel and bin the mean rendered, observed, residual,
    ratio sum(observed) / sum(rendered), counts; "gamma": slope of log observed on log rendered.
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    channels = 3
    count = len(samples)
    edges, levels = samples.intensity_bins()
    level_count = len(edges) - 1
    half = samples.view_half()
    no_bins = torch.zeros(count, dtype=torch.int64)
    channel_means = BinStage(constant_features(count, channels), no_bins, 1)
    line = samples.response().rebinned(no_bins, 1)
    binned = BinStage(constant_features(count, channels), levels, level_count)
    about_mean = BinBaseline(samples.residual, [channel_means], half)
    score, in_sample = about_mean.score(binned)
    linear, linear_in_sample = about_mean.score(line)
    nonlinear, nonlinear_in_sample = BinBaseline(samples.residual, [line], half).score(binned)

    def per_channel(values: torch.Tensor) -> list:
        """[N, C] values -> [C][K] bin means (None where empty)."""
        curves = []
        for channel in range(channels):
            means = bin_means(values[:, channel : channel + 1], levels[:, channel], level_count)
            curves.append([None if mean is None else mean[0] for mean in means])
        return curves

    mean_rendered = per_channel(samples.rendered)
    mean_observed = per_channel(samples.observed)
    ratio = [
        [
            row[0]
            for row in bin_ratio(
                samples.observed[:, channel : channel + 1],
                samples.rendered[:, channel : channel + 1],
                levels[:, channel],
                level_count,
            )
        ]
        for channel in range(channels)
    ]
    return {
        "score": score,
        "score_in_sample": in_sample,
        "summary": {
            "samples": count,
            "linear_score": linear,
            "linear_score_in_sample": linear_in_sample,
            "nonlinear_score": nonlinear,
            "nonlinear_score_in_sample": nonlinear_in_sample,
            # The outer edges are +-inf inside; report the data's range instead (JSON-safe).
            "edges": [float(samples.rendered.min())]
            + [float(value) for value in edges[1:-1]]
            + [float(samples.rendered.max())],
            "mean_rendered": mean_rendered,
            "mean_observed": mean_observed,
            "mean_residual": per_channel(samples.residual),
            "ratio": ratio,
            "counts": [bin_counts(levels[:, channel], level_count) for channel in range(channels)],
            "gamma": [_log_slope(mean_rendered[c], mean_observed[c]) for c in range(channels)],
        },
    }


def _log_slope(rendered: list, observed: list) -> float | None:
    """Slope of log observed on log rendered over bins where both are above 1e-3."""
    pairs = [
        (math.log(x), math.log(y))
        for x, y in zip(rendered, observed, strict=True)
        if x is not None and y is not None and x > 1e-3 and y > 1e-3
    ]
    if len(pairs) < 3:
        return None
    x = np.array([pair[0] for pair in pairs])
    y = np.array([pair[1] for pair in pairs])
    if np.ptp(x) < 1e-6:
        return None
    return float(np.polyfit(x, y, 1)[0])


def light_geometry_domain(data: DiagnosisData, samples: ResidualSamples | None = None) -> dict:
    """Joint bins of n.l and of the angle between n and the half vector h = (l + v) / |l + v|,
    for the fitted light's dominant direction l: specular (low angles), shadows (n.l > 0 but
    dark). No visibility term: a shadow map needs a further render (recon.effects.Shadows).

    Only pixels a fitted triangle covers count. Summary: the light direction used and its
    source, sub-scores of n.l alone and of the half-vector angle alone, and per bin of each the
    mean residual [K][3], the mean of what the shared response curve leaves of it [K][3] (what
    the score sees), gain [K][3] and counts.
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    covered = data.rendered_mask[samples.view, samples.row, samples.column]
    summary: dict = {"samples": int(covered.sum())}
    direction, irradiance = dominant_light(data.lighting.to("cpu"))
    summary.update(
        {
            "light_direction": [float(value) for value in direction],
            "light_source": "directional" if data.lighting.directional else "sh_linear_band",
        }
    )
    if int(covered.sum()) < 2:
        return {"score": 0.0, "score_in_sample": 0.0, "summary": summary}
    lit = samples.subset(covered)
    height, width = data.image_size
    normals = data.normals[lit.view, lit.row, lit.column].double()
    normals = torch.nn.functional.normalize(normals, dim=-1)
    views = view_directions(data.cameras, height, width, data.normals)
    to_camera = views[lit.view, lit.row, lit.column].double()
    light = direction.double()
    half_vector = torch.nn.functional.normalize(light[None] + to_camera, dim=-1)
    cosine = (normals @ light).clamp(-1, 1)
    half_cosine = (normals * half_vector).sum(-1).clamp(-1, 1)
    half_angle = torch.rad2deg(torch.arccos(half_cosine))
    cosine_bin = ((cosine + 1) / 2 * LIGHT_COSINE_BINS).long().clamp(0, LIGHT_COSINE_BINS - 1)
    angle_edges = torch.tensor(HALF_ANGLE_EDGES_DEGREES, dtype=torch.float64)
    angle_bins = len(angle_edges) - 1
    angle_bin = torch.bucketize(half_angle, angle_edges[1:-1], right=True)
    joint = cosine_bin * angle_bins + angle_bin
    score, in_sample = lit.binned_score(joint, LIGHT_COSINE_BINS * angle_bins, "views")
    cosine_score, _ = lit.binned_score(cosine_bin, LIGHT_COSINE_BINS, "views")
    angle_score, _ = lit.binned_score(angle_bin, angle_bins, "views")
    summary.update(
        {
            "light_irradiance": [float(value) for value in irradiance],
            "cosine_score": cosine_score,
            "half_angle_score": angle_score,
            "cosine_edges": [
                -1 + 2 * index / LIGHT_COSINE_BINS for index in range(LIGHT_COSINE_BINS + 1)
            ],
            "cosine_mean_residual": bin_means(lit.residual, cosine_bin, LIGHT_COSINE_BINS),
            "cosine_mean_beyond_response": bin_means(
                lit.baseline("views").left, cosine_bin, LIGHT_COSINE_BINS
            ),
            "cosine_ratio": bin_ratio(lit.observed, lit.rendered, cosine_bin, LIGHT_COSINE_BINS),
            "cosine_counts": bin_counts(cosine_bin, LIGHT_COSINE_BINS),
            "half_angle_edges": list(HALF_ANGLE_EDGES_DEGREES),
            "half_angle_mean_residual": bin_means(lit.residual, angle_bin, angle_bins),
            "half_angle_mean_beyond_response": bin_means(
                lit.baseline("views").left, angle_bin, angle_bins
            ),
            "half_angle_ratio": bin_ratio(lit.observed, lit.rendered, angle_bin, angle_bins),
            "half_angle_counts": bin_counts(angle_bin, angle_bins),
        }
    )
    return {"score": score, "score_in_sample": in_sample, "summary": summary}


def signed_silhouette_distance(mask: torch.Tensor) -> torch.Tensor:
    """Signed distance in pixels to the silhouette of mask [B, H, W] bool: [B, H, W] float,
    negative inside (-1 next to the edge), positive outside (+1 next to it)."""
    distances = []
    for view_mask in mask.cpu().numpy():
        if not view_mask.any():
            distances.append(np.full(view_mask.shape, np.inf))
            continue
        if view_mask.all():
            distances.append(np.full(view_mask.shape, -np.inf))
            continue
        outside = distance_transform_edt(~view_mask)
        inside = distance_transform_edt(view_mask)
        distances.append(np.where(view_mask, -inside, outside))
    return torch.from_numpy(np.stack(distances)).float()


def _image_derivatives(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(d/dx, d/dy, Laplacian) of image [B, H, W, C], central differences, edges replicated."""
    planes = image.permute(0, 3, 1, 2)
    padded = torch.nn.functional.pad(planes, (1, 1, 1, 1), mode="replicate")
    centre = padded[..., 1:-1, 1:-1]
    left, right = padded[..., 1:-1, :-2], padded[..., 1:-1, 2:]
    up, down = padded[..., :-2, 1:-1], padded[..., 2:, 1:-1]
    gradient_x = (right - left) / 2
    gradient_y = (down - up) / 2
    laplacian = left + right + up + down - 4 * centre

    def back(values: torch.Tensor) -> torch.Tensor:
        return values.permute(0, 2, 3, 1)

    return back(gradient_x), back(gradient_y), back(laplacian)


def edges_domain(
    data: DiagnosisData,
    samples: ResidualSamples | None = None,
    distance_pixels: int = EDGE_DISTANCE_PIXELS,
) -> dict:
    """Edges: bins of the signed distance to the rendered silhouette (clamped to +-distance
    pixels), each fitting the residual on (1, rendered, Laplacian of the rendered) per channel,
    pooled over views; and a per-view shift model, residual ~ t . gradient of the rendered.

    A blur leaves residual ~ (sigma^2 / 2) Laplacian at texture edges and silhouettes alike (the
    bright side darker, the dark side brighter), which bin means over the unsigned gradient
    magnitude would cancel; a sub-pixel pose error or misregistration leaves t . gradient. The
    score is the better of the two models. Summary: profiles against the signed distance and
    against the rendered luminance's gradient magnitude (mean and RMS residual), the blur sigma
    implied by the Laplacian coefficient, and the shift (pixels, x right, y down) per view.
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    distance = signed_silhouette_distance(data.rendered_mask)
    signed = distance[samples.view, samples.row, samples.column]
    clamped = signed.clamp(-distance_pixels, distance_pixels).round().long()
    # Inside -D..-1 -> 0..D-1, outside 1..D -> D..2D-1 (0 never occurs: centres are >= 1 away).
    bins = torch.where(clamped < 0, clamped + distance_pixels, clamped + distance_pixels - 1)
    bins = bins.clamp(0, 2 * distance_pixels - 1)
    bin_count = 2 * distance_pixels
    gradient_x, gradient_y, laplacian = _image_derivatives(data.rendered)
    pick = (samples.view, samples.row, samples.column)
    lap = laplacian[pick].double()  # [N, 3]
    features = torch.stack([torch.ones_like(lap), samples.rendered, lap], dim=-1)
    edge_stage = BinStage(features, bins, bin_count)
    edge_score, edge_in_sample = samples.baseline("views").score(edge_stage)

    shift_features = torch.stack([gradient_x[pick].double(), gradient_y[pick].double()], dim=-1)
    shift_stage = BinStage(shift_features, samples.view, data.view_count)
    pixel_baseline = samples.baseline("pixels")
    shift_score, shift_in_sample = pixel_baseline.score(shift_stage)
    shifts = pixel_baseline.coefficients(shift_stage).view(data.view_count, 3, 2)
    # One Laplacian coefficient per channel for all pixels (beyond the response): the blur.
    blur_stage = BinStage(lap[..., None], torch.zeros(len(samples), dtype=torch.int64), 1)
    blur_coefficient = pixel_baseline.coefficients(blur_stage)[:, 0]  # [3]

    magnitude = luminance_of(torch.sqrt(gradient_x**2 + gradient_y**2)[pick].double())
    magnitude_edges = quantile_edges(magnitude, 8)
    magnitude_bins = len(magnitude_edges) - 1
    magnitude_bin = torch.bucketize(magnitude, magnitude_edges[1:-1], right=True)
    residual_luminance = luminance_of(samples.residual)[:, None]

    score, in_sample = max((edge_score, edge_in_sample), (shift_score, shift_in_sample))
    return {
        "score": score,
        "score_in_sample": in_sample,
        "summary": {
            "samples": len(samples),
            "distance_score": edge_score,
            "distance_score_in_sample": edge_in_sample,
            "shift_score": shift_score,
            "shift_score_in_sample": shift_in_sample,
            "distance_bins": [-distance_pixels + index for index in range(distance_pixels)]
            + [index + 1 for index in range(distance_pixels)],
            "distance_mean_residual": bin_means(samples.residual, bins, bin_count),
            "distance_mean_beyond_response": bin_means(
                samples.baseline("views").left, bins, bin_count
            ),
            "distance_rms_residual": _rms(residual_luminance, bins, bin_count),
            "distance_counts": bin_counts(bins, bin_count),
            "gradient_magnitude": scalar_means(magnitude, magnitude_bin, magnitude_bins),
            "gradient_mean_residual": scalar_means(
                residual_luminance, magnitude_bin, magnitude_bins
            ),
            "gradient_rms_residual": _rms(residual_luminance, magnitude_bin, magnitude_bins),
            "gradient_counts": bin_counts(magnitude_bin, magnitude_bins),
            "laplacian_coefficient": [float(value) for value in blur_coefficient],
            "blur_sigma_pixels": [
                math.sqrt(2 * max(0.0, float(value))) for value in blur_coefficient
            ],
            "shift_pixels": [
                [float(value) for value in shifts[view].mean(0)] for view in range(data.view_count)
            ],
        },
    }


def _rms(values: torch.Tensor, bins: torch.Tensor, count: int) -> list:
    squares = [None if row is None else row[0] for row in bin_means(values**2, bins, count)]
    return [None if value is None else math.sqrt(value) for value in squares]


def frequency_domain(data: DiagnosisData, samples: ResidualSamples | None = None) -> dict:
    """White noise or structure: the residual predicted by its four neighbours' mean (score),
    the radial power spectrum of the residual luminance inside the region's bounding box per
    view (normalised so that white noise is flat at 1, averaged over views) and its spatial
    autocorrelation at lags 1, 2, 4 pixels (horizontal and vertical pairs inside the region).

    The score's split is by view (a random pixel half with one view); the predictor never uses
    the pixel itself, so white noise scores about 0 in sample as well.
    """
    samples = samples if samples is not None else ResidualSamples.from_data(data)
    residual = data.residual.double()
    region = samples.selection
    # Centre per channel over the region: a constant offset is not spatial structure here.
    mean = samples.residual.mean(0) if len(samples) else torch.zeros(3, dtype=torch.float64)
    centred = (residual - mean) * region[..., None]
    planes = centred.permute(0, 3, 1, 2)
    inside = region[:, None].double()
    neighbour_sum = torch.nn.functional.conv2d(
        planes.reshape(-1, 1, *planes.shape[-2:]),
        torch.tensor([[[[0.0, 1, 0], [1, 0, 1], [0, 1, 0]]]], dtype=torch.float64),
        padding=1,
    ).reshape(planes.shape)
    neighbour_count = torch.nn.functional.conv2d(
        inside,
        torch.tensor([[[[0.0, 1, 0], [1, 0, 1], [0, 1, 0]]]], dtype=torch.float64),
        padding=1,
    )
    # Only pixels whose four neighbours all lie in the region.
    complete = (neighbour_count[:, 0] > 3.5) & region
    view, row, column = torch.nonzero(complete, as_tuple=True)
    target = centred[view, row, column]  # [M, 3]
    predictor = (neighbour_sum / 4).permute(0, 2, 3, 1)[view, row, column]
    if data.view_count >= 2:
        half = view % 2 == 0
    else:
        generator = torch.Generator().manual_seed(samples.seed)
        half = torch.rand(len(view), generator=generator) < 0.5
    # No baseline stage: the target is centred already, so this is R^2 about the mean.
    stage = BinStage(predictor[..., None], torch.zeros(len(view), dtype=torch.int64), 1)
    score, in_sample = BinBaseline(target, [], half).score(stage)

    luminance = luminance_of(centred)  # [B, H, W]
    frequencies, power = _radial_spectrum(luminance, region)
    autocorrelation = {
        str(lag): _autocorrelation(luminance, region, lag) for lag in AUTOCORRELATION_LAGS
    }
    low = [p for f, p in zip(frequencies, power, strict=True) if f < 0.125 and p is not None]
    return {
        "score": score,
        "score_in_sample": in_sample,
        "summary": {
            "samples": len(view),
            "frequencies": frequencies,
            "power": power,
            "low_frequency_power": float(np.mean(low)) if low else None,
            "autocorrelation": autocorrelation,
        },
    }


def _radial_spectrum(luminance: torch.Tensor, region: torch.Tensor) -> tuple[list, list]:
    """Radially binned power spectrum (cycles per pixel, [0, 0.5]) averaged over views,
    each view's spectrum divided by its mean power (white noise -> 1 at every frequency)."""
    totals = torch.zeros(SPECTRUM_BINS, dtype=torch.float64)
    weights = torch.zeros(SPECTRUM_BINS, dtype=torch.float64)
    for view in range(luminance.shape[0]):
        rows, columns = torch.nonzero(region[view], as_tuple=True)
        if len(rows) < 16:
            continue
        crop = luminance[view, rows.min() : rows.max() + 1, columns.min() : columns.max() + 1]
        if crop.shape[0] < 4 or crop.shape[1] < 4:
            continue
        power = torch.fft.fft2(crop).abs() ** 2
        mean_power = power.mean()
        if mean_power <= 0:
            continue
        frequency_y = torch.fft.fftfreq(crop.shape[0], dtype=torch.float64)
        frequency_x = torch.fft.fftfreq(crop.shape[1], dtype=torch.float64)
        radius = torch.sqrt(frequency_y[:, None] ** 2 + frequency_x[None, :] ** 2)
        # Skip the zero frequency (the mean, removed) and the corners beyond Nyquist.
        keep = (radius > 0) & (radius <= 0.5)
        index = (radius[keep] / 0.5 * SPECTRUM_BINS).long().clamp(0, SPECTRUM_BINS - 1)
        bin_power = torch.zeros(SPECTRUM_BINS, dtype=torch.float64)
        bin_count = torch.zeros(SPECTRUM_BINS, dtype=torch.float64)
        bin_power.index_add_(0, index, (power[keep] / mean_power))
        bin_count.index_add_(0, index, torch.ones_like(index, dtype=torch.float64))
        present = bin_count > 0
        totals[present] += bin_power[present] / bin_count[present] * len(rows)
        weights[present] += len(rows)
    frequencies = [(index + 0.5) * 0.5 / SPECTRUM_BINS for index in range(SPECTRUM_BINS)]
    power = [
        float(totals[index] / weights[index]) if weights[index] > 0 else None
        for index in range(SPECTRUM_BINS)
    ]
    return frequencies, power


def _autocorrelation(luminance: torch.Tensor, region: torch.Tensor, lag: int) -> float | None:
    """Correlation of the residual with itself lag pixels right and down, pooled over views."""
    products, first_squares, second_squares = 0.0, 0.0, 0.0
    for first, second, both in (
        (luminance[:, :, :-lag], luminance[:, :, lag:], region[:, :, :-lag] & region[:, :, lag:]),
        (luminance[:, :-lag], luminance[:, lag:], region[:, :-lag] & region[:, lag:]),
    ):
        products += float((first * second)[both].sum())
        first_squares += float((first**2)[both].sum())
        second_squares += float((second**2)[both].sum())
    if first_squares <= 0 or second_squares <= 0:
        return None
    return products / math.sqrt(first_squares * second_squares)


DOMAINS = (
    "image_position",
    "surface",
    "view",
    "intensity",
    "light_geometry",
    "edges",
    "frequency",
)


def where_analysis(
    data: DiagnosisData,
    grid_size: int = 16,
    texel_grid_size: int = 32,
    seed: int = 0,
) -> dict:
    """The residual binned in every domain (see the module docstring for the scores).

    Returns {domain: {"score": float (split-half, clamped at 0), "score_in_sample": float,
    "summary": {...}}} for domain in DOMAINS; summaries hold plain floats, ints, strings, lists
    and None (empty bins), ready for JSON. grid_size and texel_grid_size are coarsened when
    there are too few pixels for them; seed drives the random pixel halves.
    """
    samples = ResidualSamples.from_data(data, seed)
    if len(samples) < 2:
        raise ReconError(
            "where_analysis: the region holds no pixels (neither the observed nor the rendered "
            "object is in any view)"
        )
    return {
        "image_position": image_position_domain(data, samples, grid_size),
        "surface": surface_domain(data, samples, texel_grid_size),
        "view": view_domain(data, samples),
        "intensity": intensity_domain(data, samples),
        "light_geometry": light_geometry_domain(data, samples),
        "edges": edges_domain(data, samples),
        "frequency": frequency_domain(data, samples),
    }
