"""How large the sim-to-real gap is: the residual observed - rendered in linear radiance.

gap_summary: RMSE and PSNR of the residual in linear radiance over the region (object plus a
band around its silhouette), per view and overall.

relight_gap: the same on the relight split, after one least-squares gain per channel
(gauge_gain) takes out the albedo x light scale that the fit could not pin under one light.

noise_floor: the part of the residual no forward model removes (sensor noise, quantisation),
from the high-frequency part of the residual against the predicted intensity.

Where the gap lies is recon.diagnose.domains.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from recon.diagnose.data import COVERAGE_THRESHOLD, DiagnosisData, box_erode
from recon.diagnose.residuals import quantile_edges

# A 3 x 3 box mean removes 1/9 of a white pixel's own value and adds 1/81 of eight neighbours':
# the high-pass r - box(r) keeps (8/9)^2 + 8/81 = 8/9 of the noise variance.
BOX_VARIANCE_FACTOR = 8.0 / 9.0
# Standard deviation = this x median absolute deviation for Gaussian samples.
MAD_TO_SIGMA = 1.4826
NOISE_BINS = 16
# Fewer high-pass samples than this and the noise floor is not estimated.
MINIMUM_NOISE_SAMPLES = 64


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
    interior = box_erode(interior[:, None], 2)
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
    edges = quantile_edges(intensity, bins)
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
