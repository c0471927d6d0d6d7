"""The residual observed - rendered, sampled and scored in bins: the machinery behind the
where-analysis (recon.diagnose.domains binds it to its seven domains).

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

import copy
import math

import torch

from recon.diagnose.data import DiagnosisData

# Rec. 709 luminance weights, for the one-number summaries and maps.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
# Pseudo samples of zero residual added to every bin's fit (see the module docstring).
DEFAULT_RIDGE = 1.0
# Fewest samples per cell when a requested grid is coarsened to the data.
MINIMUM_SAMPLES_PER_CELL = 8
INTENSITY_BINS = 16

# --------------------------------------------------------------------------------------------
# binned models and their scores
# --------------------------------------------------------------------------------------------


class BinStage:
    """One binned least-squares model: per (bin, channel), residual ~ features . coefficients.

    features: [N, C, P] per sample and channel; bins: [N] int64 in [0, count) shared by the
    channels, or [N, C] when each channel has its own (bins of the rendered value).
    """

    def __init__(self, features: torch.Tensor, bins: torch.Tensor, count: int) -> None:
        self.features = features.double()
        samples, channels, parameters = self.features.shape
        self._set_bins(bins, count)
        # Every fit sums the same per-sample outer products, only over other samples.
        flat = self.features.reshape(-1, parameters)
        self._outer = (flat[:, :, None] * flat[:, None, :]).reshape(-1, parameters * parameters)

    def _set_bins(self, bins: torch.Tensor, count: int) -> None:
        if bins.ndim == 1:
            bins = bins[:, None].expand(-1, self.channels)
        # Row of each (sample, channel) in the flat [count x C] coefficient table.
        self.rows = bins * self.channels + torch.arange(self.channels)
        self.count = count

    def rebinned(self, bins: torch.Tensor, count: int) -> BinStage:
        """The same features in other bins (bins [N] or [N, C] in [0, count)): a new stage
        that shares the features and their outer products (most domains bin the same affine
        features of the render)."""
        stage = copy.copy(self)
        stage._set_bins(bins, count)
        return stage

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
        samples, channels, parameters = self.features.shape
        chosen = coefficients.index_select(0, self.rows.reshape(-1))
        chosen = chosen.view(samples, channels, parameters)
        # Parameter by parameter: the products summed in order, as .sum(-1) adds the few
        # parameters of a bin model, without the [N, C, P] product and its reduction pass.
        prediction = self.features[..., 0] * chosen[..., 0]
        for parameter in range(1, parameters):
            prediction = prediction + self.features[..., parameter] * chosen[..., parameter]
        return prediction


def _fit_stages(
    target: torch.Tensor, stages: list[BinStage], train: torch.Tensor | None = None
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


class BinBaseline:
    """What baseline stages leave of target [N, C], fitted on all samples (for in-sample
    scores) and on each half of a split (applied to the other half), computed once and shared
    by every model scored beyond that baseline.

    half: [N] bool, the two halves of the split-half check.
    """

    def __init__(self, target: torch.Tensor, stages: list[BinStage], half: torch.Tensor) -> None:
        self.target = target.double()
        self.half = half
        self.left = _fit_stages(self.target, stages)[1]
        self.left_by_half = [
            (train, _fit_stages(self.target, stages, train)[1]) for train in (half, ~half)
        ]

    def score(self, stage: BinStage) -> tuple[float, float]:
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

    def coefficients(self, stage: BinStage) -> torch.Tensor:
        """stage's coefficients fitted on all samples beyond the baseline."""
        return stage.fit(self.left)


def constant_features(count: int, channels: int) -> torch.Tensor:
    return torch.ones(count, channels, 1, dtype=torch.float64)


def affine_features(rendered: torch.Tensor) -> torch.Tensor:
    """[N, C, 2]: (1, rendered value) per channel."""
    return torch.stack([torch.ones_like(rendered), rendered], dim=-1).double()


def intensity_bins(rendered: torch.Tensor, bins: int = INTENSITY_BINS) -> tuple:
    """(edges [K + 1], per-channel bin [N, C]) of rendered values [N, C] at pooled quantiles."""
    edges = quantile_edges(rendered.reshape(-1), bins)
    return edges, torch.bucketize(rendered.double(), edges[1:-1], right=True)


def shared_response(rendered: torch.Tensor, bins: tuple | None = None) -> BinStage:
    """The baseline of every domain but intensity: a response curve per channel, piecewise
    affine over bins of the rendered value [N, C] (bins: intensity_bins(rendered) when the
    caller has them).

    What depends on the rendered value alone (a gamma, a global gain) is removed first, so it
    cannot reappear in a domain whose bins happen to sort pixels by brightness (texels of one
    albedo, silhouette distances, n.l), where per-bin lines would rebuild the curve piecewise.
    """
    edges, levels = bins if bins is not None else intensity_bins(rendered)
    return BinStage(affine_features(rendered), levels, len(edges) - 1)


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
        self._baselines: dict[str, BinBaseline] = {}
        # Built on first use, then shared (both splits' baselines, the domains' bins).
        self._intensity_bins: tuple[torch.Tensor, torch.Tensor] | None = None
        self._response: BinStage | None = None

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

    def intensity_bins(self) -> tuple[torch.Tensor, torch.Tensor]:
        """intensity_bins of the samples' render (computed once)."""
        if self._intensity_bins is None:
            self._intensity_bins = intensity_bins(self.rendered)
        return self._intensity_bins

    def response(self) -> BinStage:
        """shared_response of the samples' render (built once: a stage is not changed by
        fitting it)."""
        if self._response is None:
            self._response = shared_response(self.rendered, self.intensity_bins())
        return self._response

    def baseline(self, split: str) -> BinBaseline:
        """The response curve (see shared_response) fitted on all samples and on each half;
        split 'views' (pooled domains) or 'pixels' (per-view models)."""
        if split not in self._baselines:
            half = self.view_half() if split == "views" else self.pixel_half()
            self._baselines[split] = BinBaseline(self.residual, [self.response()], half)
        return self._baselines[split]

    def binned_score(self, bins: torch.Tensor, count: int, split: str) -> tuple[float, float]:
        """(split-half, in-sample) score of an affine response per bin [N] beyond the shared
        response curve: the default domain model."""
        return self.baseline(split).score(self.response().rebinned(bins, count))


def luminance_of(values: torch.Tensor) -> torch.Tensor:
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=values.dtype, device=values.device)
    return values @ weights


def adaptive_grid(requested: int, samples: int, per_cell: int = MINIMUM_SAMPLES_PER_CELL) -> int:
    """The requested grid size, coarsened until a cell holds per_cell samples on average."""
    return max(2, min(requested, int(math.sqrt(max(samples, 1) / per_cell))))


def bin_means(values: torch.Tensor, bins: torch.Tensor, count: int) -> list:
    """Per-bin mean of values [N, C] -> [count][C] lists, None for empty bins."""
    sums = torch.zeros(count, values.shape[1], dtype=torch.float64)
    sums.index_add_(0, bins, values.double())
    counts = torch.bincount(bins, minlength=count).double()
    means = sums / counts.clamp_min(1)[:, None]
    return [
        [float(value) for value in row] if counts[index] > 0 else None
        for index, row in enumerate(means)
    ]


def scalar_means(values: torch.Tensor, bins: torch.Tensor, count: int) -> list:
    """Per-bin mean of values [N] or [N, 1] -> [count] floats, None for empty bins."""
    means = bin_means(values.reshape(-1, 1), bins, count)
    return [None if mean is None else mean[0] for mean in means]


def bin_ratio(
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


def bin_counts(bins: torch.Tensor, count: int) -> list[int]:
    return [int(value) for value in torch.bincount(bins, minlength=count).tolist()]


def quantile_edges(values: torch.Tensor, bins: int) -> torch.Tensor:
    """Bin edges [K + 1] at quantiles of values (duplicates merged), outer edges +-inf."""
    probabilities = torch.linspace(0, 1, bins + 1, dtype=torch.float64)[1:-1]
    sample = values.double()
    if sample.numel() > 1_000_000:  # torch.quantile refuses very large inputs
        generator = torch.Generator().manual_seed(0)
        sample = sample[torch.randint(sample.numel(), (1_000_000,), generator=generator)]
    inner = torch.unique(torch.quantile(sample, probabilities))
    infinity = torch.tensor([math.inf], dtype=torch.float64)
    return torch.cat([-infinity, inner, infinity])
