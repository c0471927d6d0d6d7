"""Agreement of a per-view colour gain between spatially separate halves of each view.

A white balance is one colour gain per view, the same over the whole image of that view. The
albedo absorbs its mean over the training views, so what is left on held-out views is how the
colour of each view departs from that mean: a few per cent. On a fit whose misfit is tens of
per cent (a 20 dB fit of a small image) that is a small share of the held-out error, and a probe
that must remove a share of the error (diagnose.decision.minimum_share) misses it, although the
signature is distinctive. The misfit's own colour error is local: it follows which regions a view
shows and how they are misaligned, so it differs between the two halves of a view.

The check: in each held-out view, split the object's pixels at its centroid into left and right
halves, and into top and bottom halves; fit the per-view colour gains (red over green, blue over
green; least squares, recon.diagnose.nulls.per_view_log_gains) on each half; centre them over
views. A camera's white balance gives the same per-view gains in both halves of every split; a
local colour misfit does not. The statistic is the per-view colour spread the halves share,
sqrt of their covariance over views (a log gain; 0.05 is a 5 % change of red or blue against
green); its null is the same covariance with the views of one half permuted (the p-value).
The decision (recon.diagnose.decision, row 'agreement') names the candidate when the shared
spread clears diagnose.decision.agreement_allowance and the p-value is below
diagnose.decision.agreement_alpha. A white balance constant over views has no shared spread:
the albedo absorbs it. How large a per-view change the test can name on this data (the halves'
colour noise against the permutation null) is the identifiability check's
(recon.diagnose.identifiability.white_balance_evidence).
"""

from __future__ import annotations

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.nulls import per_view_log_gains, permuted_correlations
from recon.diagnose.records import Evidence

KIND = "agreement"


def half_masks(data: DiagnosisData) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The two halves [B, H, W, 1] of each view's region split at the region's centroid, left |
    right and top | bottom."""
    _, height, width, _ = data.observed.shape
    region = data.region.double()
    rows = torch.arange(height, dtype=torch.float64)[None, :, None, None]
    columns = torch.arange(width, dtype=torch.float64)[None, None, :, None]
    area = region.sum(dim=(1, 2, 3)).clamp_min(1e-30)
    halves = []
    for coordinate in (columns, rows):
        centre = (region * coordinate).sum(dim=(1, 2, 3)) / area
        below = (coordinate < centre[:, None, None, None]).double()
        halves.append((region * below, region * (1 - below)))
    return halves


def colour_gains(data: DiagnosisData, weight: torch.Tensor) -> torch.Tensor:
    """Per-view log colour gains [B, 2] (red and blue over green) over weight, centred over
    views."""
    gains = per_view_log_gains(data, weight)
    ratios = torch.stack([gains[:, 0] - gains[:, 1], gains[:, 2] - gains[:, 1]], dim=-1)
    return ratios - ratios.mean(dim=0, keepdim=True)


def split_gains(data: DiagnosisData) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-view colour gains [B, 4] of the first and second halves of every split (red and
    blue over green, left | right then top | bottom), each centred over views."""
    first, second = [], []
    for one, other in half_masks(data):
        first.append(colour_gains(data, one))
        second.append(colour_gains(data, other))
    return torch.cat(first, dim=1), torch.cat(second, dim=1)


def spread_statistics(data: DiagnosisData, permutations: int, seed: int, alpha: float) -> dict:
    """The agreement's statistics over the held-out views:

    spread: the per-view colour change both halves share, sqrt of their covariance over views
      (an RMS log gain; 0 when negative); correlation and p_value: their correlation and the
      share of view permutations of one half reaching it; views: B.
    noise: the RMS log gain by which one half's per-view colour misses the view's own, from the
      halves' difference (a white balance is the same in both halves and cancels in it): the
      fit's local colour misfit as the per-view gains see it.
    detectable: the smallest per-view colour change the test names on this data: a change of
      RMS s over noise n gives halves that correlate by s^2 / (s^2 + n^2), and the test needs the
      (1 - alpha) quantile r of the permutation null, so s = n sqrt(r / (1 - r)).
    """
    one, other = split_gains(data)
    covariance = float((one * other).mean())
    scale = ((one * one).sum() * (other * other).sum()).sqrt().clamp_min(1e-30)
    correlation = float((one * other).sum() / scale)
    null = permuted_correlations(one, other, permutations, seed)
    p_value = float((1 + (null >= correlation).sum()) / (1 + null.numel()))
    noise = float((one - other).pow(2).mean().sqrt()) / 2**0.5
    critical = min(float(torch.quantile(null.double(), 1.0 - alpha)), 1.0 - 1e-9)
    detectable = noise * (max(critical, 0.0) / (1.0 - critical)) ** 0.5
    return {
        "spread": max(covariance, 0.0) ** 0.5,
        "correlation": correlation,
        "p_value": p_value,
        "views": int(one.shape[0]),
        "noise": noise,
        "critical_correlation": critical,
        "detectable": detectable,
    }


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
    statistics = spread_statistics(
        data, settings.nulls.permutations, settings.nulls.seed, decision.agreement_alpha
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
            "splits": ["left-right", "top-bottom"],
            "noise": statistics["noise"],
            "critical_correlation": statistics["critical_correlation"],
            "detectable": statistics["detectable"],
        },
    )
