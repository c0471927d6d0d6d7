"""Agreement of a per-view colour gain between spatially separate halves of each view.

A white balance is one colour gain per view, the same over the whole image of that view. The
albedo absorbs its mean over the training views, so what is left on held-out views is how the
colour of each view departs from that mean: a few per cent. On a fit whose misfit is tens of
per cent (a 20 dB fit of a small image) that is a small share of the held-out error, and a probe
that must remove a share of the error (diagnose.decision.minimum_share) misses it, although the
signature is distinctive. The misfit's own colour error is local: it follows which regions a view
shows and how they are misaligned, so it differs between the two halves of a view.

The check: in each held-out view, split the object's interior pixels into two halves five
ways: at its centroid left | right and top | bottom, and at the view's median of the rendered
intensity, of n.h and of n.v; measure the per-view colour gain (red over green, blue over
green: each half's median of its pixels' colour ratios) on each half; centre them over views.
A camera's white balance gives the same per-view gains in both halves of every split; a local
colour misfit does not, nor does a coloured highlight (its colour follows n.h and n.v, and the
bright half). The statistic is the per-view colour spread the halves share, sqrt of their
covariance over views, each colour ratio weighted by 1 / its variance over views (a log gain;
0.05 is a 5 % change of red or blue against green); its null is the same correlation with the
views of one half permuted (the p-value). The decision (recon.diagnose.decision, row
'agreement') names the candidate when the shared spread clears
diagnose.decision.agreement_allowance and the p-value is below diagnose.decision.agreement_alpha.
A white balance constant over views has no shared spread: the albedo absorbs it. How large a
per-view change the test can name on this data (the halves' colour noise against the
permutation null) is the identifiability check's
(recon.diagnose.identifiability.white_balance_evidence). Measured on the blind check
(docs/decisions/0207-white-balance-exposure.md).
"""

from __future__ import annotations

import math

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData, box_erode
from recon.diagnose.nulls import permuted_correlations
from recon.diagnose.pixel_table import LastResult, dominant_light_direction, view_directions
from recon.diagnose.records import Evidence

KIND = "agreement"
DEFAULTS = DiagnoseConfig()
SPLITS = ["left-right", "top-bottom", "intensity", "n.h", "n.v"]
# The specificity domain (recon.diagnose.specificity) each split tests: a gain the same on both
# halves does not vary along it. Position in the image takes both image splits.
SPLIT_DOMAINS = {
    "left-right": "image_position",
    "top-bottom": "image_position",
    "intensity": "intensity",
    "n.h": "n_dot_h",
    "n.v": "n_dot_v",
}
# Fewer views leave a permutation null with too few orderings to reach any level (two views:
# p >= 1/2) and, once centred, next to no degrees of freedom.
MINIMUM_VIEWS = 3


def interior(data: DiagnosisData, erode_pixels: int) -> torch.Tensor:
    """[B, H, W, 1] float64 0/1: pixels both the observed and the rendered object cover, eroded by
    erode_pixels (a silhouette pixel mixes object and background in different shares in the
    photo and the render: its colour ratio is the misfit's, not the camera's)."""
    covered = (data.observed_alpha > 0.5) & (data.rendered_alpha > 0.5)
    mask = box_erode(covered.double().permute(0, 3, 1, 2), erode_pixels)
    return mask.permute(0, 2, 3, 1).contiguous()


_LAST_ANGLES = LastResult()


def surface_angles(data: DiagnosisData) -> tuple[torch.Tensor, torch.Tensor]:
    """n.h (against the fitted light's main direction, n.v without one) and n.v per pixel
    [B, H, W], as recon.diagnose.pixel_table measures them (the last views' kept: the white
    balance agreement and the exposure's gains ask for the same views' angles)."""
    cameras = data.cameras
    inputs = (data.normals, data.depth, cameras.world_to_cam, cameras.intrinsics, data.lighting)
    return _LAST_ANGLES.get(inputs, lambda: _surface_angles(data))


def _surface_angles(data: DiagnosisData) -> tuple[torch.Tensor, torch.Tensor]:
    """surface_angles, computed."""
    _, to_camera = view_directions(data)
    normals = data.normals.double()
    normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    to_camera = to_camera.double()
    light, _ = dominant_light_direction(data)
    if light is not None and data.lighting.frame == "camera":
        rotation = data.cameras.world_to_cam[:, :3, :3].double()
        toward = (rotation.transpose(1, 2) @ light.double())[:, None, None, :]
    elif light is not None:
        toward = light.double()[None, None, None, :]
    else:
        toward = to_camera
    halfway = toward + to_camera
    halfway = halfway / halfway.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return (normals * halfway).sum(-1), (normals * to_camera).sum(-1)


def _median_split(weight: torch.Tensor, value: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """weight [B, H, W, 1] split at each view's median of value [B, H, W] (below | above)."""
    below = torch.zeros_like(weight)
    for view in range(weight.shape[0]):
        inside = weight[view, ..., 0] > 0
        if inside.any():
            below[view, ..., 0] = (value[view] < value[view][inside].median()).to(weight)
    return weight * below, weight * (1 - below)


def half_masks(
    data: DiagnosisData, weight: torch.Tensor | None = None
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The two halves [B, H, W, 1] of each view's pixels (weight; default the region) for every
    split of SPLITS: at the centroid left | right and top | bottom, and at the view's median of
    the rendered intensity, of n.h and of n.v. A camera's white balance is the same in both
    halves of each; a coloured highlight (n.h, n.v, intensity) or a local colour misfit (the
    image halves) is not."""
    _, height, width, _ = data.observed.shape
    region = data.region.double() if weight is None else weight.double()
    rows = torch.arange(height, dtype=torch.float64)[None, :, None, None]
    columns = torch.arange(width, dtype=torch.float64)[None, None, :, None]
    area = region.sum(dim=(1, 2, 3)).clamp_min(1e-30)
    halves = []
    for coordinate in (columns, rows):
        centre = (region * coordinate).sum(dim=(1, 2, 3)) / area
        below = (coordinate < centre[:, None, None, None]).double()
        halves.append((region * below, region * (1 - below)))
    n_dot_h, n_dot_v = surface_angles(data)
    for value in (data.rendered.double().mean(dim=-1), n_dot_h, n_dot_v):
        halves.append(_median_split(region, value))
    return halves


def colour_gains(
    data: DiagnosisData, weight: torch.Tensor, dark_fraction: float = DEFAULTS.colour_dark_fraction
) -> torch.Tensor:
    """Per-view log colour gains [B, 2] (red and blue over green) over weight, centred over views:
    each view's median of its pixels' colour ratios log(observed / rendered), red and blue
    against green. A median, not a least-squares gain: a coloured highlight or a misfit patch
    moves a few pixels' ratios far and a least-squares gain with them (it weights pixels by
    their energy, so the brightest, a highlight's, dominate); a camera's white balance moves
    every pixel's ratio alike. Pixels darker than dark_fraction of the view's brightest (in the
    photo or the render) are left out: their ratios are noise."""
    return _colour_gains(_colour_ratios(data, dark_fraction), weight)


def _colour_ratios(data: DiagnosisData, dark_fraction: float) -> tuple[torch.Tensor, torch.Tensor]:
    """What colour_gains reads of data whatever the weight: the colour log ratios [B, H, W, 2]
    and the pixels bright enough in both photo and render [B, H, W] bool."""
    observed, rendered = data.observed.double(), data.rendered.double()
    ratios = torch.log(observed.clamp_min(1e-6)) - torch.log(rendered.clamp_min(1e-6))
    colour = torch.stack([ratios[..., 0] - ratios[..., 1], ratios[..., 2] - ratios[..., 1]], -1)
    observed_luminance, rendered_luminance = observed.mean(dim=-1), rendered.mean(dim=-1)
    bright = torch.zeros(observed.shape[:3], dtype=torch.bool, device=observed.device)
    for view in range(observed.shape[0]):
        bright[view] = (
            observed_luminance[view] > dark_fraction * observed_luminance[view].max()
        ) & (rendered_luminance[view] > dark_fraction * rendered_luminance[view].max())
    return colour, bright


def _colour_gains(ratios: tuple[torch.Tensor, torch.Tensor], weight: torch.Tensor) -> torch.Tensor:
    """colour_gains from _colour_ratios (computed once for the many halves of split_gains)."""
    colour, bright = ratios
    gains = torch.zeros(colour.shape[0], 2, dtype=torch.float64)
    for view in range(colour.shape[0]):
        chosen = (weight[view, ..., 0] > 0) & bright[view]
        if chosen.any():
            gains[view] = colour[view][chosen].median(dim=0).values
    return gains - gains.mean(dim=0, keepdim=True)


def view_covariates(data: DiagnosisData, settings: DiagnoseConfig = DEFAULTS) -> torch.Tensor:
    """Per-view quantities [B, K] a view's colour may follow without any white balance: the mean
    of (n.h)^p over the view's interior pixels for each p of settings.colour_highlight_powers
    (weighted by the rendered luminance: how much of a highlight's lobe the view shows, from the
    fitted geometry and light alone, so an exposure does not move it), and the view's median
    log ratio of observed over rendered green (how much brighter than the model the view is). A
    coloured highlight (a metal's: gold's is gold) tints a view by how much of it the view
    shows, so its per-view colour follows these; a camera's white balance does not."""
    weight = interior(data, settings.colour_erode_pixels)[..., 0]
    n_dot_h, _ = surface_angles(data)
    n_dot_h = n_dot_h.clamp_min(0.0)
    observed, rendered = data.observed.double(), data.rendered.double()
    luminance = rendered.mean(dim=-1) * weight
    total = luminance.sum(dim=(1, 2)).clamp_min(1e-30)
    columns = [
        (n_dot_h.pow(power) * luminance).sum(dim=(1, 2)) / total
        for power in settings.colour_highlight_powers
    ]
    green = torch.log(observed[..., 1].clamp_min(1e-6)) - torch.log(
        rendered[..., 1].clamp_min(1e-6)
    )
    brightness = torch.zeros(observed.shape[0], dtype=torch.float64)
    for view in range(observed.shape[0]):
        inside = weight[view] > 0
        if inside.any():
            brightness[view] = green[view][inside].median()
    columns.append(brightness)
    return torch.stack(columns, dim=1)


def residual_projection(covariates: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The projection [B, B] onto what the views' centring and covariates [B, K] do not explain,
    and the degrees of freedom it leaves (B minus the rank of [1, covariates]). With too few
    views to spare (fewer than 3 left), only the centring."""
    views = covariates.shape[0]
    centred = covariates.double() - covariates.double().mean(dim=0, keepdim=True)
    # Unit columns: the rank sees which covariates vary over views, whatever their units.
    centred = centred / centred.norm(dim=0, keepdim=True).clamp_min(1e-30)
    design = torch.cat([torch.ones(views, 1, dtype=torch.float64) / views**0.5, centred], dim=1)
    rank = int(torch.linalg.matrix_rank(design, rtol=1e-6))
    if views - rank < 3:
        design, rank = torch.ones(views, 1, dtype=torch.float64), 1
    projection = torch.eye(views, dtype=torch.float64) - design @ torch.linalg.pinv(design)
    return projection, views - rank


def split_gains(
    data: DiagnosisData, settings: DiagnoseConfig = DEFAULTS
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The per-view colour gains [B, 2 x len(SPLITS)] of the first and second halves of every
    split (red and blue over green) on the interior pixels, with what the views' covariates
    (view_covariates) explain removed, and the degrees of freedom left over views."""
    weight = interior(data, settings.colour_erode_pixels)
    first, second = [], []
    ratios = _colour_ratios(data, settings.colour_dark_fraction)
    for one, other in half_masks(data, weight):
        first.append(_colour_gains(ratios, one))
        second.append(_colour_gains(ratios, other))
    projection, freedom = residual_projection(view_covariates(data, settings))
    return projection @ torch.cat(first, dim=1), projection @ torch.cat(second, dim=1), freedom


def spread_statistics(
    data: DiagnosisData,
    permutations: int,
    seed: int,
    alpha: float,
    settings: DiagnoseConfig = DEFAULTS,
) -> dict:
    """The agreement's statistics over the held-out views. Each component (a colour ratio in one
    split) is weighted by 1 / its variance over views (both halves pooled: the same weights
    under any permutation of the views): a channel the object hardly reflects (the blue of a
    gold or brown object) has ratios ten times noisier than the others and would otherwise
    decide alone. Moments over views are divided by the degrees of freedom the covariates
    leave (split_gains), so that the spread is a per-view RMS whatever was removed.

    spread: the per-view colour change both halves share, sqrt of their weighted covariance
      over views (an RMS log gain; 0 when negative); correlation and p_value: the weighted
      correlation of the halves and the share of view permutations of one half reaching it;
      views: B; freedom: the degrees of freedom over views.
    noise: the weighted RMS log gain by which one half's per-view colour misses the view's own,
      from the halves' difference (a white balance is the same in both halves and cancels in
      it): the fit's colour misfit as the per-view gains see it.
    detectable: the smallest per-view colour change the test names on this data: a change of
      RMS s over noise n gives halves that correlate by s^2 / (s^2 + n^2), and the test needs the
      (1 - alpha) quantile r of the permutation null, so s = n sqrt(r / (1 - r)).
    """
    one, other, freedom = split_gains(data, settings)
    variance = (one.pow(2).sum(dim=0) + other.pow(2).sum(dim=0)) / (2 * freedom)
    weights = 1.0 / variance.clamp_min(1e-12)
    weights = weights / weights.sum()
    covariance = float((weights * (one * other).sum(dim=0)).sum()) / freedom
    noise = (float((weights * (one - other).pow(2).sum(dim=0)).sum()) / (2 * freedom)) ** 0.5
    correlation, p_value, null = _weighted_agreement(one, other, weights, permutations, seed)
    critical = min(float(torch.quantile(null.double(), 1.0 - alpha)), 1.0 - 1e-9)
    detectable = noise * (max(critical, 0.0) / (1.0 - critical)) ** 0.5
    per_split = {}
    for index, split in enumerate(SPLITS):
        # Each split's two colour ratios alone, weighted as in the pooled statistic.
        columns = slice(2 * index, 2 * index + 2)
        split_correlation, split_p_value, _ = _weighted_agreement(
            one[:, columns], other[:, columns], weights[columns], permutations, seed
        )
        per_split[split] = {"correlation": split_correlation, "p_value": split_p_value}
    return {
        "spread": max(covariance, 0.0) ** 0.5,
        "correlation": correlation,
        "p_value": p_value,
        "views": int(one.shape[0]),
        "freedom": freedom,
        "noise": noise,
        "critical_correlation": critical,
        "detectable": detectable,
        "per_split": per_split,
    }


def _weighted_agreement(
    one: torch.Tensor, other: torch.Tensor, weights: torch.Tensor, permutations: int, seed: int
) -> tuple[float, float, torch.Tensor]:
    """(correlation, permutation p-value, null correlations [permutations]) of the halves' gains
    one and other [B, K] over views, each component weighted by weights [K]."""
    scaled_one, scaled_other = one * weights.sqrt(), other * weights.sqrt()
    scale = (scaled_one.pow(2).sum() * scaled_other.pow(2).sum()).sqrt().clamp_min(1e-30)
    correlation = float((scaled_one * scaled_other).sum() / scale)
    null = permuted_correlations(scaled_one, scaled_other, permutations, seed)
    p_value = float((1 + (null >= correlation).sum()) / (1 + null.numel()))
    return correlation, p_value, null


def domain_p_values(per_split: dict[str, dict]) -> dict[str, float]:
    """Per specificity domain (recon.diagnose.specificity), the largest permutation p-value of
    the splits that test it (SPLIT_DOMAINS): the domain counts as tested by the agreement only
    where every one of its splits' halves agree on their own (recon.diagnose.decision compares
    it with diagnose.decision.agreement_alpha). A pooled agreement can come from four splits
    while the fifth disagrees: a colour change that differs between the bright and the dark
    half of each view is no camera's, whatever the image halves show."""
    values: dict[str, float] = {}
    for split, domain in SPLIT_DOMAINS.items():
        values[domain] = max(values.get(domain, 0.0), per_split[split]["p_value"])
    return values


def shared_spread(
    data: DiagnosisData, permutations: int, seed: int
) -> tuple[float, float, float, int]:
    """(shared spread, correlation, permutation p-value, views): the per-view colour gains of the
    halves of every split, their covariance over views as an RMS log gain (0 when negative), its
    correlation and the share of view permutations of one half reaching it."""
    statistics = spread_statistics(data, permutations, seed, alpha=0.01)
    return (
        statistics["spread"],
        statistics["correlation"],
        statistics["p_value"],
        statistics["views"],
    )


def agreement_evidence(data: DiagnosisData, name: str, settings: DiagnoseConfig) -> Evidence:
    """Whether the candidate's per-view colour gain is common to separate halves of each view
    (the threshold and passed are the decision config's; recon.diagnose.decision re-derives
    them)."""
    decision = settings.decision
    views = data.observed.shape[0]
    if views < MINIMUM_VIEWS:
        # A change from view to view needs views to compare: with one held-out view the
        # centring alone leaves no degree of freedom, and nothing can be said either way.
        return Evidence(
            kind=KIND,
            candidate=name,
            statistic=math.nan,
            threshold=math.nan,
            passed=False,
            reason=f"{name}: per-view colour gains need at least {MINIMUM_VIEWS} held-out views "
            f"to agree over, got {views}",
            details={"views": views, "too_few_views": True},
        )
    statistics = spread_statistics(
        data, settings.nulls.permutations, settings.nulls.seed, decision.agreement_alpha, settings
    )
    spread, correlation = statistics["spread"], statistics["correlation"]
    p_value, views = statistics["p_value"], statistics["views"]
    threshold = max(decision.agreement_minimum, decision.agreement_allowance.get(name, 0.0))
    passed = spread > threshold and p_value < decision.agreement_alpha
    reason = (
        f"{name}: the per-view colour gains of separate halves of each view agree (r = "
        f"{correlation:.2f} over {views} views, p = {p_value:.2g} against permuted views); the "
        "colour change they share, RMS log gain"
    )
    return Evidence(
        kind=KIND,
        candidate=name,
        statistic=spread,
        threshold=threshold,
        passed=passed,
        reason=reason,
        details={
            "correlation": correlation,
            "p_value": p_value,
            "views": views,
            "splits": SPLITS,
            "noise": statistics["noise"],
            "critical_correlation": statistics["critical_correlation"],
            "detectable": statistics["detectable"],
            "per_split": statistics["per_split"],
            "domain_p_values": domain_p_values(statistics["per_split"]),
        },
    )
