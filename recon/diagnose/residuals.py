"""Where the sim-to-real gap lies: the residual observed - rendered, measured and binned.

gap_summary: RMSE and PSNR of the residual in linear radiance over the region (object plus a
band around its silhouette), per view and overall.

noise_floor: the part of the residual no forward model removes (sensor noise, quantisation),
from the high-frequency part of the residual against the predicted intensity.

where_analysis: the residual binned in seven domains, each with a structure score:

    {domain: {"score": float, "score_in_sample": float, "summary": {...}}}

with domain in image_position, surface, view, intensity, light_geometry, edges, frequency.

How a score is made. Each domain has a bin model: per bin (and channel) a small least-squares
fit of the residual on features of the rendered image, fitted with a light ridge (one pseudo
sample pulling every coefficient to zero, so a bin with two pixels cannot fit them exactly):

- the intensity domain (bins of the rendered value, one mean per bin) is scored as the fraction
  of the residual variance about its mean that the bins explain: a response curve, gamma or a
  global gain all make the residual a function of the rendered value;
- every other domain is scored beyond a response curve shared by all pixels and views (per
  channel, piecewise affine over 16 bins of the rendered value), as the fraction of what that
  curve leaves that the domain's bins explain, each bin fitting its own affine response
  (camera effects such as vignetting and exposure are multiplicative: a gain per bin).
  Removing the shared curve first keeps an effect that depends only on the rendered value (a
  gamma) from reappearing in every domain whose bins sort pixels by brightness: the object's
  footprint against the dark band around it, texels of one albedo, n.l, silhouette distance;
- frequency: the fraction of the residual variance predicted by the mean of each pixel's four
  neighbours (zero for white noise, near one for smooth structure).

score_in_sample fits and evaluates on all pixels and is inflated by the number of bins (the
expected value for pure noise is about bins x parameters / samples). score is the honest one: a
two-fold split-half check, fitting on one half and measuring the explained variance on the
other, both ways, clamped at 0. Domains pooled over views (image position, surface, intensity,
light geometry, edges, frequency) split by view (even / odd), so they count only structure that
repeats across views; per-view models (view, the per-view shift, the surface's across-view
term) split a seeded random half of the pixels of every view.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from recon.diagnose.data import COVERAGE_THRESHOLD, DiagnosisData
from recon.effects.light_transport import dominant_light, view_directions
from recon.errors import ReconError

# Rec. 709 luminance weights, for the one-number summaries and maps.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
# Pseudo samples of zero residual added to every bin's fit (see the module docstring).
DEFAULT_RIDGE = 1.0
# Fewest samples per cell when a requested grid is coarsened to the data.
MINIMUM_SAMPLES_PER_CELL = 8
# A 3 x 3 box mean removes 1/9 of a white pixel's own value and adds 1/81 of eight neighbours':
# the high-pass r - box(r) keeps (8/9)^2 + 8/81 = 8/9 of the noise variance.
BOX_VARIANCE_FACTOR = 8.0 / 9.0
# Standard deviation = this x median absolute deviation for Gaussian samples.
MAD_TO_SIGMA = 1.4826
# Edges: signed distances to the rendered silhouette are clamped to +-this many pixels.
EDGE_DISTANCE_PIXELS = 4
# Light geometry: angle between the normal and the half vector (degrees); the lobe lives low.
HALF_ANGLE_EDGES_DEGREES = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0, 180.0001)
LIGHT_COSINE_BINS = 8
INTENSITY_BINS = 16
RADIAL_BINS = 16
SPECTRUM_BINS = 12
AUTOCORRELATION_LAGS = (1, 2, 4)
NOISE_BINS = 16
# Fewer high-pass samples than this and the noise floor is not estimated.
MINIMUM_NOISE_SAMPLES = 64


# --------------------------------------------------------------------------------------------
# the gap
# --------------------------------------------------------------------------------------------


def gap_summary(data: DiagnosisData) -> dict:
    """Residual RMSE and PSNR (peak 1, linear radiance) over the region, per view and overall.

    Returns {"rmse", "psnr", "mse", "pixels", "rmse_per_channel" [3], "mean_residual" [3],
    "names" [B], "per_view_rmse" [B], "per_view_psnr" [B], "per_view_pixels" [B]}; a view with
    no region pixels has rmse and psnr None (NaN overall when no view has any), and a residual
    of exactly zero has PSNR inf.
    """
    residual = data.residual.double()
    region = data.region[..., 0] > 0.5  # [B, H, W]
    squared = (residual**2 * region[..., None]).sum(dim=(1, 2))  # [B, 3]
    sums = (residual * region[..., None]).sum(dim=(1, 2))  # [B, 3]
    pixels = region.sum(dim=(1, 2)).double()  # [B]
    total_pixels = float(pixels.sum())
    per_view_rmse, per_view_psnr = [], []
    for view in range(data.view_count):
        if pixels[view] > 0:
            mse = float(squared[view].sum() / (3 * pixels[view]))
            per_view_rmse.append(math.sqrt(mse))
            per_view_psnr.append(_psnr(mse))
        else:
            per_view_rmse.append(None)
            per_view_psnr.append(None)
    if total_pixels == 0:
        mse = float("nan")
        channel_rmse = [float("nan")] * 3
        mean_residual = [float("nan")] * 3
    else:
        mse = float(squared.sum() / (3 * total_pixels))
        channel_rmse = (squared.sum(0) / total_pixels).sqrt().tolist()
        mean_residual = (sums.sum(0) / total_pixels).tolist()
    return {
        "rmse": math.sqrt(mse) if total_pixels else float("nan"),
        "psnr": _psnr(mse) if total_pixels else float("nan"),
        "mse": mse,
        "pixels": int(total_pixels),
        "rmse_per_channel": channel_rmse,
        "mean_residual": mean_residual,
        "names": list(data.names),
        "per_view_rmse": per_view_rmse,
        "per_view_psnr": per_view_psnr,
        "per_view_pixels": [int(value) for value in pixels.tolist()],
    }


def gauge_gain(
    observed: torch.Tensor, rendered: torch.Tensor, region: torch.Tensor
) -> torch.Tensor:
    """The per-channel gain [3] (float64) that best maps rendered onto observed [B, H, W, 3] in
    least squares over region [B, H, W, 1]: the albedo x light gauge of a relit render."""
    region, rendered, observed = region.double(), rendered.double(), observed.double()
    numerator = (observed * rendered * region).sum(dim=(0, 1, 2))
    return numerator / (rendered * rendered * region).sum(dim=(0, 1, 2)).clamp_min(1e-20)


def relight_gap(data: DiagnosisData) -> dict:
    """gap_summary of a relight split rendered with its own (known) light, after the albedo x
    light gauge is fixed: the fitted albedo is only known up to a per-channel scale that the
    fitted light carries, so one gain per channel (least squares over the region of every
    view) rescales the render first. Adds "gauge_gain" [3] to the summary."""
    gain = gauge_gain(data.observed, data.rendered, data.region)
    rendered = data.rendered.double()
    summary = gap_summary(replace(data, rendered=(rendered * gain).to(data.rendered.dtype)))
    summary["gauge_gain"] = gain.tolist()
    return summary


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else 10.0 * math.log10(1.0 / mse)


def noise_floor(data: DiagnosisData, bins: int = NOISE_BINS) -> dict:
    """The irreducible residual: variance = a x intensity + b (Poisson-Gaussian sensor noise).

    The residual's high-frequency part h = r - box3x3(r) (which keeps 8/9 of white noise's
    variance and little of any smooth model error) is taken inside the object, two pixels away
    from its silhouette (edges are where model error is sharp). Per bin of rendered value its
    variance is estimated robustly, (1.4826 MAD)^2 x 9/8, so texture-edge outliers do not
    count as noise, and a, b >= 0 are fitted by weighted least squares (weights count / var^2).

    Returns {"a", "b", "floor_rmse" (the noise's RMSE over the same region and channels as
    gap_summary), "gap_rmse", "gap_above_floor" = sqrt(max(0, gap^2 - floor^2)),
    "highpass_sigma" (non-robust, for reference), "samples", "bins": {"intensity", "variance",
    "counts"}}; a, b and the floors are None when too few interior pixels exist.
    """
    gap = gap_summary(data)
    residual = data.residual.permute(0, 3, 1, 2)  # [B, 3, H, W]
    interior = (data.rendered_mask & (data.observed_alpha[..., 0] > COVERAGE_THRESHOLD)).float()
    # Erode by two pixels: the 3 x 3 box must not reach the silhouette, nor its antialiasing.
    interior = -torch.nn.functional.max_pool2d(-interior[:, None], 5, stride=1, padding=2)
    interior = interior[:, 0] > 0.5  # [B, H, W]
    box = torch.nn.functional.avg_pool2d(residual, 3, stride=1, padding=1)
    highpass = (residual - box).permute(0, 2, 3, 1)[interior].reshape(-1)  # [N x 3]
    intensity = data.rendered[interior].reshape(-1)
    result: dict = {
        "a": None,
        "b": None,
        "floor_rmse": None,
        "gap_rmse": gap["rmse"],
        "gap_above_floor": None,
        "highpass_sigma": None,
        "samples": int(highpass.numel()),
        "bins": {"intensity": [], "variance": [], "counts": []},
    }
    if highpass.numel() < MINIMUM_NOISE_SAMPLES:
        return result
    highpass = highpass.double()
    intensity = intensity.double()
    result["highpass_sigma"] = math.sqrt(float((highpass**2).mean()) / BOX_VARIANCE_FACTOR)
    edges = _quantile_edges(intensity, bins)
    index = torch.bucketize(intensity, edges[1:-1], right=True)
    centres, variances, counts = [], [], []
    for bin_index in range(len(edges) - 1):
        chosen = index == bin_index
        count = int(chosen.sum())
        if count < 8:
            continue
        values = highpass[chosen]
        deviation = (values - values.median()).abs().median()
        centres.append(float(intensity[chosen].mean()))
        variances.append(float((MAD_TO_SIGMA * deviation) ** 2 / BOX_VARIANCE_FACTOR))
        counts.append(count)
    result["bins"] = {"intensity": centres, "variance": variances, "counts": counts}
    if not counts:
        return result
    slope, offset = _fit_noise_model(np.array(centres), np.array(variances), np.array(counts))
    region = data.region[..., 0] > 0.5
    predicted = slope * data.rendered[region].double().clamp_min(0) + offset
    floor_rmse = math.sqrt(float(predicted.mean())) if predicted.numel() else float("nan")
    result.update(
        {
            "a": slope,
            "b": offset,
            "floor_rmse": floor_rmse,
            "gap_above_floor": math.sqrt(max(0.0, gap["rmse"] ** 2 - floor_rmse**2)),
        }
    )
    return result


def _fit_noise_model(
    intensity: np.ndarray, variance: np.ndarray, counts: np.ndarray
) -> tuple[float, float]:
    """variance ~ a intensity + b with a, b >= 0, weighted least squares (two passes)."""
    weights = counts.astype(np.float64)
    slope, offset = 0.0, float(np.average(variance, weights=weights))
    for _ in range(2):
        design = np.stack([intensity, np.ones_like(intensity)], axis=1)
        weighted = design * weights[:, None]
        try:
            slope, offset = np.linalg.solve(design.T @ weighted, weighted.T @ variance)
        except np.linalg.LinAlgError:
            slope, offset = 0.0, float(np.average(variance, weights=weights))
        if slope < 0:
            slope, offset = 0.0, float(np.average(variance, weights=weights))
        elif offset < 0:
            moment = max(float((weights * intensity**2).sum()), 1e-30)
            slope = float((weights * intensity * variance).sum()) / moment
            offset = 0.0
        # A variance estimate's spread grows with the variance: weight by count / var^2.
        predicted = np.maximum(slope * intensity + offset, 1e-20)
        weights = counts / predicted**2
    return float(slope), float(offset)


# --------------------------------------------------------------------------------------------
# binned models and their scores
# --------------------------------------------------------------------------------------------


class _Stage:
    """One binned least-squares model: per (bin, channel), residual ~ features . coefficients.

    features: [N, C, P] per sample and channel; bins: [N] int64 in [0, count) shared by the
    channels, or [N, C] when each channel has its own (bins of the rendered value).
    """

    def __init__(self, features: torch.Tensor, bins: torch.Tensor, count: int) -> None:
        self.features = features.double()
        samples, channels, parameters = self.features.shape
        if bins.ndim == 1:
            bins = bins[:, None].expand(-1, channels)
        # Row of each (sample, channel) in the flat [count x C] coefficient table.
        self.rows = bins * channels + torch.arange(channels)
        self.count = count
        # Every fit sums the same per-sample outer products, only over other samples.
        flat = self.features.reshape(-1, parameters)
        self._outer = (flat[:, :, None] * flat[:, None, :]).reshape(-1, parameters * parameters)

    @property
    def channels(self) -> int:
        return self.features.shape[1]

    @property
    def parameters(self) -> int:
        return self.features.shape[2]

    def fit(self, target: torch.Tensor, train: torch.Tensor | None = None) -> torch.Tensor:
        """Coefficients [count x C, P] fitted on target [N, C] (the train [N] bool samples)."""
        channels, parameters = self.channels, self.parameters
        table = self.count * channels
        rows = self.rows
        if train is not None:
            # Samples outside train go to one extra row that is dropped (no gather, no copy).
            rows = torch.where(train[:, None], rows, table)
        rows = rows.reshape(-1)
        gram = torch.zeros(table + 1, parameters * parameters, dtype=torch.float64)
        moment = torch.zeros(table + 1, parameters, dtype=torch.float64)
        gram.index_add_(0, rows, self._outer)
        flat_features = self.features.reshape(-1, parameters)
        moment.index_add_(0, rows, flat_features * target.reshape(-1, 1))
        gram = gram[:table].view(self.count, channels, parameters, parameters)
        moment = moment[:table].view(self.count, channels, parameters, 1)
        # The ridge is in units of samples: each feature's mean square over the training set.
        used = int(train.sum()) if train is not None else self.features.shape[0]
        diagonal = torch.diagonal(gram, dim1=-2, dim2=-1).sum(0)  # [C, P]
        scale = diagonal / used if used else torch.ones_like(diagonal)
        regulariser = torch.diag_embed(DEFAULT_RIDGE * scale + 1e-12)  # [C, P, P]
        solution = torch.linalg.solve(gram + regulariser, moment)[..., 0]
        return solution.reshape(-1, parameters)

    def predict(self, coefficients: torch.Tensor) -> torch.Tensor:
        """[N, C] prediction for every sample from fit's coefficients."""
        return (self.features * coefficients[self.rows]).sum(-1)


def _fit_stages(
    target: torch.Tensor, stages: list[_Stage], train: torch.Tensor | None = None
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Fit the stages in turn, each on what the previous ones left (on the train samples).

    Returns (coefficients per stage, what all stages leave of target [N, C] for every sample).
    """
    remainder = target
    coefficients = []
    for stage in stages:
        fitted = stage.fit(remainder, train)
        coefficients.append(fitted)
        remainder = remainder - stage.predict(fitted)
    return coefficients, remainder


class _Baseline:
    """What baseline stages leave of target [N, C], fitted on all samples (for in-sample
    scores) and on each half of a split (applied to the other half), computed once and shared
    by every model scored beyond that baseline.

    half: [N] bool, the two halves of the split-half check.
    """

    def __init__(self, target: torch.Tensor, stages: list[_Stage], half: torch.Tensor) -> None:
        self.target = target.double()
        self.half = half
        self.left = _fit_stages(self.target, stages)[1]
        self.left_by_half = [
            (train, _fit_stages(self.target, stages, train)[1]) for train in (half, ~half)
        ]

    def score(self, stage: _Stage) -> tuple[float, float]:
        """(split-half, in-sample) share of what the baseline leaves that stage explains."""
        if self.target.shape[0] == 0:
            return 0.0, 0.0
        total = float((self.left**2).sum())
        after = self.left - stage.predict(stage.fit(self.left))
        in_sample = 1.0 - float((after**2).sum()) / total if total > 0 else 0.0
        error, reference = 0.0, 0.0
        for train, left in self.left_by_half:
            test = ~train
            if not bool(train.any()) or not bool(test.any()):
                continue
            prediction = stage.predict(stage.fit(left, train))
            error += float(((left - prediction)[test] ** 2).sum())
            reference += float((left[test] ** 2).sum())
        out_of_sample = 1.0 - error / reference if reference > 0 else 0.0
        return max(0.0, out_of_sample), max(0.0, in_sample)

    def coefficients(self, stage: _Stage) -> torch.Tensor:
        """stage's coefficients fitted on all samples beyond the baseline."""
        return stage.fit(self.left)


def _constant_features(count: int, channels: int) -> torch.Tensor:
    return torch.ones(count, channels, 1, dtype=torch.float64)


def _affine_features(rendered: torch.Tensor) -> torch.Tensor:
    """[N, C, 2]: (1, rendered value) per channel."""
    return torch.stack([torch.ones_like(rendered), rendered], dim=-1).double()


def _intensity_bins(rendered: torch.Tensor, bins: int = INTENSITY_BINS) -> tuple:
    """(edges [K + 1], per-channel bin [N, C]) of rendered values [N, C] at pooled quantiles."""
    edges = _quantile_edges(rendered.reshape(-1), bins)
    return edges, torch.bucketize(rendered.double(), edges[1:-1], right=True)


def _response(rendered: torch.Tensor) -> _Stage:
    """The baseline of every domain but intensity: a response curve per channel, piecewise
    affine over bins of the rendered value [N, C].

    What depends on the rendered value alone (a gamma, a global gain) is removed first, so it
    cannot reappear in a domain whose bins happen to sort pixels by brightness (texels of one
    albedo, silhouette distances, n.l), where per-bin lines would rebuild the curve piecewise.
    """
    edges, bins = _intensity_bins(rendered)
    return _Stage(_affine_features(rendered), bins, len(edges) - 1)


# --------------------------------------------------------------------------------------------
# samples and splits
# --------------------------------------------------------------------------------------------


class ResidualSamples:
    """Pixels of the region as flat samples, with the baselines every domain shares.

    residual, rendered, observed: [N, 3] float64; view, row, column: [N] int64; selection:
    [B, H, W] bool (which pixels they are); view_count: B; seed: for the random pixel halves.
    """

    def __init__(
        self,
        residual: torch.Tensor,
        rendered: torch.Tensor,
        observed: torch.Tensor,
        view: torch.Tensor,
        row: torch.Tensor,
        column: torch.Tensor,
        selection: torch.Tensor,
        view_count: int,
        seed: int = 0,
    ) -> None:
        self.residual = residual.double()
        self.rendered = rendered.double()
        self.observed = observed.double()
        self.view = view
        self.row = row
        self.column = column
        self.selection = selection
        self.view_count = view_count
        self.seed = seed
        self._baselines: dict[str, _Baseline] = {}

    @staticmethod
    def from_data(data: DiagnosisData, seed: int = 0) -> ResidualSamples:
        """All pixels of data's region."""
        selection = data.region[..., 0] > 0.5
        view, row, column = torch.nonzero(selection, as_tuple=True)
        return ResidualSamples(
            data.residual[selection],
            data.rendered[selection],
            data.observed[selection],
            view,
            row,
            column,
            selection,
            data.view_count,
            seed,
        )

    def __len__(self) -> int:
        return self.residual.shape[0]

    def subset(self, chosen: torch.Tensor) -> ResidualSamples:
        """The samples where chosen [N] bool is true (with baselines of their own)."""
        selection = torch.zeros_like(self.selection)
        selection[self.view[chosen], self.row[chosen], self.column[chosen]] = True
        return ResidualSamples(
            self.residual[chosen],
            self.rendered[chosen],
            self.observed[chosen],
            self.view[chosen],
            self.row[chosen],
            self.column[chosen],
            selection,
            self.view_count,
            self.seed,
        )

    def view_half(self) -> torch.Tensor:
        """[N] bool: even views against odd ones (a random pixel half with a single view)."""
        if self.view_count >= 2:
            return self.view % 2 == 0
        return self.pixel_half()

    def pixel_half(self) -> torch.Tensor:
        """[N] bool: a seeded random half of the pixels (of every view alike)."""
        generator = torch.Generator().manual_seed(self.seed)
        return torch.rand(len(self), generator=generator) < 0.5

    def baseline(self, split: str) -> _Baseline:
        """The response curve (see _response) fitted on all samples and on each half;
        split 'views' (pooled domains) or 'pixels' (per-view models)."""
        if split not in self._baselines:
            half = self.view_half() if split == "views" else self.pixel_half()
            self._baselines[split] = _Baseline(self.residual, [_response(self.rendered)], half)
        return self._baselines[split]

    def binned_score(self, bins: torch.Tensor, count: int, split: str) -> tuple[float, float]:
        """(split-half, in-sample) score of an affine response per bin [N] beyond the shared
        response curve: the default domain model."""
        stage = _Stage(_affine_features(self.rendered), bins, count)
        return self.baseline(split).score(stage)


def _luminance(values: torch.Tensor) -> torch.Tensor:
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=values.dtype, device=values.device)
    return values @ weights


def _adaptive_grid(requested: int, samples: int, per_cell: int = MINIMUM_SAMPLES_PER_CELL) -> int:
    """The requested grid size, coarsened until a cell holds per_cell samples on average."""
    return max(2, min(requested, int(math.sqrt(max(samples, 1) / per_cell))))


def _bin_means(values: torch.Tensor, bins: torch.Tensor, count: int) -> list:
    """Per-bin mean of values [N, C] -> [count][C] lists, None for empty bins."""
    sums = torch.zeros(count, values.shape[1], dtype=torch.float64)
    sums.index_add_(0, bins, values.double())
    counts = torch.bincount(bins, minlength=count).double()
    means = sums / counts.clamp_min(1)[:, None]
    return [
        [float(value) for value in row] if counts[index] > 0 else None
        for index, row in enumerate(means)
    ]


def _scalar_means(values: torch.Tensor, bins: torch.Tensor, count: int) -> list:
    """Per-bin mean of values [N] or [N, 1] -> [count] floats, None for empty bins."""
    means = _bin_means(values.reshape(-1, 1), bins, count)
    return [None if mean is None else mean[0] for mean in means]


def _bin_ratio(
    observed: torch.Tensor, rendered: torch.Tensor, bins: torch.Tensor, count: int
) -> list:
    """Per-bin sum(observed) / sum(rendered) [count][C] (None where the render is ~0)."""
    observed_sums = torch.zeros(count, observed.shape[1], dtype=torch.float64)
    rendered_sums = torch.zeros_like(observed_sums)
    observed_sums.index_add_(0, bins, observed.double())
    rendered_sums.index_add_(0, bins, rendered.double())
    counts = torch.bincount(bins, minlength=count).double().clamp_min(1)
    result = []
    for index in range(count):
        row = []
        for channel in range(observed.shape[1]):
            # A bin whose mean render is below 1e-4 has no meaningful gain.
            if rendered_sums[index, channel] / counts[index] > 1e-4:
                row.append(float(observed_sums[index, channel] / rendered_sums[index, channel]))
            else:
                row.append(None)
        result.append(row)
    return result


def _counts(bins: torch.Tensor, count: int) -> list[int]:
    return [int(value) for value in torch.bincount(bins, minlength=count).tolist()]


def _quantile_edges(values: torch.Tensor, bins: int) -> torch.Tensor:
    """Bin edges [K + 1] at quantiles of values (duplicates merged), outer edges +-inf."""
    probabilities = torch.linspace(0, 1, bins + 1, dtype=torch.float64)[1:-1]
    sample = values.double()
    if sample.numel() > 1_000_000:  # torch.quantile refuses very large inputs
        generator = torch.Generator().manual_seed(0)
        sample = sample[torch.randint(sample.numel(), (1_000_000,), generator=generator)]
    inner = torch.unique(torch.quantile(sample, probabilities))
    infinity = torch.tensor([math.inf], dtype=torch.float64)
    return torch.cat([-infinity, inner, infinity])


# --------------------------------------------------------------------------------------------
# domains
# --------------------------------------------------------------------------------------------


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
    grid = _adaptive_grid(grid_size, len(samples))
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

    residual_luminance = _luminance(samples.residual)[:, None]
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
                _scalar_means(residual_luminance, cells, grid * grid), grid
            ),
            "grid_counts": _grid(_counts(cells, grid * grid), grid),
            "radial_score": radial_score,
            "radial_score_in_sample": radial_in_sample,
            "radial_edges": [index / RADIAL_BINS for index in range(RADIAL_BINS + 1)],
            "radial_mean_residual": _bin_means(samples.residual, rings, RADIAL_BINS),
            "radial_ratio": _bin_ratio(samples.observed, samples.rendered, rings, RADIAL_BINS),
            "radial_counts": _counts(rings, RADIAL_BINS),
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
    grid = _adaptive_grid(grid_size, len(surface), per_cell=4)
    cell_column = (uv[:, 0] * grid).long().clamp(0, grid - 1)
    cell_row = (uv[:, 1] * grid).long().clamp(0, grid - 1)
    cells = cell_row * grid + cell_column
    texel_stage = _Stage(_affine_features(surface.rendered), cells, grid * grid)
    score, in_sample = surface.baseline("views").score(texel_stage)

    views = data.view_count
    cell_views = cells * views + surface.view
    # Beyond the response and the texel cells, fitted on random pixel halves of every view.
    texel_baseline = _Baseline(
        surface.residual, [_response(surface.rendered), texel_stage], surface.pixel_half()
    )
    view_stage = _Stage(_constant_features(len(surface), 3), cell_views, grid * grid * views)
    view_score, view_in_sample = texel_baseline.score(view_stage)

    residual_luminance = _luminance(surface.residual)[:, None]
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
            "mean_luminance": _grid(_scalar_means(residual_luminance, cells, grid * grid), grid),
            "across_view_std": _grid(across_view_std, grid),
            "counts": _grid(_counts(cells, grid * grid), grid),
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
            "mean_residual": _bin_means(samples.residual, samples.view, views),
            "gain": _bin_ratio(samples.observed, samples.rendered, samples.view, views),
            "rmse": [
                math.sqrt(float(squares[view] / counts[view])) if counts[view] > 0 else None
                for view in range(views)
            ],
            "counts": _counts(samples.view, views),
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
    edges, levels = _intensity_bins(samples.rendered)
    level_count = len(edges) - 1
    half = samples.view_half()
    no_bins = torch.zeros(count, dtype=torch.int64)
    channel_means = _Stage(_constant_features(count, channels), no_bins, 1)
    line = _Stage(_affine_features(samples.rendered), no_bins, 1)
    binned = _Stage(_constant_features(count, channels), levels, level_count)
    about_mean = _Baseline(samples.residual, [channel_means], half)
    score, in_sample = about_mean.score(binned)
    linear, linear_in_sample = about_mean.score(line)
    nonlinear, nonlinear_in_sample = _Baseline(samples.residual, [line], half).score(binned)

    def per_channel(values: torch.Tensor) -> list:
        """[N, C] values -> [C][K] bin means (None where empty)."""
        curves = []
        for channel in range(channels):
            means = _bin_means(values[:, channel : channel + 1], levels[:, channel], level_count)
            curves.append([None if mean is None else mean[0] for mean in means])
        return curves

    mean_rendered = per_channel(samples.rendered)
    mean_observed = per_channel(samples.observed)
    ratio = [
        [
            row[0]
            for row in _bin_ratio(
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
            "counts": [_counts(levels[:, channel], level_count) for channel in range(channels)],
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
            "cosine_mean_residual": _bin_means(lit.residual, cosine_bin, LIGHT_COSINE_BINS),
            "cosine_mean_beyond_response": _bin_means(
                lit.baseline("views").left, cosine_bin, LIGHT_COSINE_BINS
            ),
            "cosine_ratio": _bin_ratio(lit.observed, lit.rendered, cosine_bin, LIGHT_COSINE_BINS),
            "cosine_counts": _counts(cosine_bin, LIGHT_COSINE_BINS),
            "half_angle_edges": list(HALF_ANGLE_EDGES_DEGREES),
            "half_angle_mean_residual": _bin_means(lit.residual, angle_bin, angle_bins),
            "half_angle_mean_beyond_response": _bin_means(
                lit.baseline("views").left, angle_bin, angle_bins
            ),
            "half_angle_ratio": _bin_ratio(lit.observed, lit.rendered, angle_bin, angle_bins),
            "half_angle_counts": _counts(angle_bin, angle_bins),
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
    edge_stage = _Stage(features, bins, bin_count)
    edge_score, edge_in_sample = samples.baseline("views").score(edge_stage)

    shift_features = torch.stack([gradient_x[pick].double(), gradient_y[pick].double()], dim=-1)
    shift_stage = _Stage(shift_features, samples.view, data.view_count)
    pixel_baseline = samples.baseline("pixels")
    shift_score, shift_in_sample = pixel_baseline.score(shift_stage)
    shifts = pixel_baseline.coefficients(shift_stage).view(data.view_count, 3, 2)
    # One Laplacian coefficient per channel for all pixels (beyond the response): the blur.
    blur_stage = _Stage(lap[..., None], torch.zeros(len(samples), dtype=torch.int64), 1)
    blur_coefficient = pixel_baseline.coefficients(blur_stage)[:, 0]  # [3]

    magnitude = _luminance(torch.sqrt(gradient_x**2 + gradient_y**2)[pick].double())
    magnitude_edges = _quantile_edges(magnitude, 8)
    magnitude_bins = len(magnitude_edges) - 1
    magnitude_bin = torch.bucketize(magnitude, magnitude_edges[1:-1], right=True)
    residual_luminance = _luminance(samples.residual)[:, None]

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
            "distance_mean_residual": _bin_means(samples.residual, bins, bin_count),
            "distance_mean_beyond_response": _bin_means(
                samples.baseline("views").left, bins, bin_count
            ),
            "distance_rms_residual": _rms(residual_luminance, bins, bin_count),
            "distance_counts": _counts(bins, bin_count),
            "gradient_magnitude": _scalar_means(magnitude, magnitude_bin, magnitude_bins),
            "gradient_mean_residual": _scalar_means(
                residual_luminance, magnitude_bin, magnitude_bins
            ),
            "gradient_rms_residual": _rms(residual_luminance, magnitude_bin, magnitude_bins),
            "gradient_counts": _counts(magnitude_bin, magnitude_bins),
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
    squares = [None if row is None else row[0] for row in _bin_means(values**2, bins, count)]
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
    stage = _Stage(predictor[..., None], torch.zeros(len(view), dtype=torch.int64), 1)
    score, in_sample = _Baseline(target, [], half).score(stage)

    luminance = _luminance(centred)  # [B, H, W]
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
