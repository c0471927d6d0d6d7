"""Image metrics on held-out views: PSNR (sRGB and linear), SSIM, MAE, scale-invariant PSNR.

Images are batches of views [B, H, W, C] float32 in LINEAR radiance (C colour channels, any C;
alpha is passed separately as [B, H, W, 1]). Masks are [B, H, W, 1] (or [B, H, W]); a pixel
counts when its mask value is > 0.5.

Conventions, chosen to match what the peers report:

- Every metric is computed per view and then averaged over views (the mean of per-view PSNR, as
  nvdiffrec's validation does), not from one MSE pooled over all views. Because PSNR is a convex
  function of the MSE, the mean of per-view PSNR is never below the pooled PSNR
  (Jensen); the two agree only when every view has the same MSE.
- PSNR is capped at PSNR_CAP_DB = 100 dB: identical images would otherwise give +inf, which
  breaks averages and JSON. The cap is applied by flooring the MSE at peak^2 * 1e-10.
- A view whose mask selects no pixel gets NaN and is left out of the mean; when no view has a
  pixel, a ReconError names the mask.
- Compositing (when an alpha is given) happens in linear space with straight (non-premultiplied)
  alpha, colour = alpha * colour + (1 - alpha) * background, before sRGB encoding, as nvdiffrec
  does with torch.lerp(background, colour, alpha) for both its render and its reference.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import kornia
import torch

from recon.errors import ReconError
from recon.io.images import linear_to_srgb

PSNR_CAP_DB = 100.0
# The MSE floor that makes the cap: 10 * log10(1 / 1e-10) = 100 dB.
_MSE_FLOOR_RATIO = 10.0 ** (-PSNR_CAP_DB / 10.0)
SSIM_WINDOW = 11
_SPACES = ("srgb", "linear")


class ViewMetric(NamedTuple):
    """A metric per view and its mean over views.

    per_view: [B] float32 on the images' device (NaN for a view whose mask selects no pixel).
    mean: Python float, the mean over views with a value (NaNs left out).
    """

    per_view: torch.Tensor
    mean: float


# --------------------------------------------------------------------------------------------
# Validation and shared helpers
# --------------------------------------------------------------------------------------------


def _check_images(prediction: torch.Tensor, target: torch.Tensor) -> None:
    """Raise ReconError unless prediction and target are finite float [B, H, W, C], alike."""
    for name, image in (("prediction", prediction), ("target", target)):
        if not isinstance(image, torch.Tensor):
            raise ReconError(f"{name}: expected a torch.Tensor, got {type(image).__name__}")
        if image.ndim != 4 or min(image.shape) == 0:
            raise ReconError(
                f"{name}: expected a non-empty batch of views [B, H, W, C], "
                f"got shape {tuple(image.shape)}"
            )
        if not image.is_floating_point():
            raise ReconError(f"{name}: expected a float tensor, got {image.dtype}")
    if prediction.device != target.device:
        raise ReconError(
            f"target: on device {target.device}, but prediction is on {prediction.device}"
        )
    if prediction.shape != target.shape:
        raise ReconError(
            f"target: expected the shape of prediction {tuple(prediction.shape)}, "
            f"got {tuple(target.shape)}"
        )
    for name, image in (("prediction", prediction), ("target", target)):
        if not bool(torch.isfinite(image).all()):
            raise ReconError(f"{name}: contains NaN or inf")


def _check_plane(plane: torch.Tensor | None, like: torch.Tensor, name: str) -> torch.Tensor | None:
    """Validate a mask or alpha [B, H, W, 1] (or [B, H, W]) against like [B, H, W, C].

    Returns it as float [B, H, W, 1] on like's device, or None when plane is None.
    """
    if plane is None:
        return None
    if not isinstance(plane, torch.Tensor):
        raise ReconError(f"{name}: expected a torch.Tensor, got {type(plane).__name__}")
    if plane.device != like.device:
        raise ReconError(f"{name}: on device {plane.device}, but the images are on {like.device}")
    if plane.ndim == 3:
        plane = plane[..., None]
    if plane.shape != (*like.shape[:3], 1):
        raise ReconError(
            f"{name}: expected shape {(*like.shape[:3], 1)} (one value per pixel), "
            f"got {tuple(plane.shape)}"
        )
    plane = plane.to(like.dtype)  # bool and integer masks become 0 / 1
    if not bool(torch.isfinite(plane).all()):
        raise ReconError(f"{name}: contains NaN or inf")
    return plane


def _check_space(space: str) -> None:
    if space not in _SPACES:
        raise ReconError(f"space: expected one of {_SPACES}, got {space!r}")


def _selection(mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """Pixel weights [B, H, W, 1]: 1 where the pixel counts (mask > 0.5, or everywhere)."""
    if mask is None:
        return torch.ones((*like.shape[:3], 1), dtype=like.dtype, device=like.device)
    return (mask > 0.5).to(like.dtype)


def _masked_mean(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Per-view mean [B] of values [B, H, W, C] over pixels with weight 1 (weights [B, H, W, 1]).

    NaN for a view with no selected pixel (0 / 0), left to the caller to drop from the mean.
    """
    total = (values * weights).sum(dim=(1, 2, 3))
    count = weights.sum(dim=(1, 2, 3)) * values.shape[-1]
    return total / count


def _view_metric(per_view: torch.Tensor) -> ViewMetric:
    """Wrap per-view values [B]; the mean leaves out NaN views (empty masks)."""
    valid = ~torch.isnan(per_view)
    if not bool(valid.any()):
        raise ReconError("mask: selects no pixel (> 0.5) in any view")
    # The mean is taken in float64 so that the reported number does not depend on the batch order.
    mean = float(per_view[valid].double().mean())
    return ViewMetric(per_view=per_view.float(), mean=mean)


def _psnr_from_mse(mse: torch.Tensor, peak: torch.Tensor | float) -> torch.Tensor:
    """PSNR in dB [B] from MSE [B], capped at PSNR_CAP_DB (the MSE is floored at peak^2 * 1e-10)."""
    peak_squared = torch.as_tensor(peak, dtype=mse.dtype, device=mse.device) ** 2
    floored = torch.maximum(mse, peak_squared * _MSE_FLOOR_RATIO)
    return 10.0 * torch.log10(peak_squared / floored)


def to_display(image: torch.Tensor) -> torch.Tensor:
    """Linear radiance [..., C] -> sRGB-encoded values clamped to [0, 1] (what a PNG would show)."""
    return linear_to_srgb(image).clamp(0.0, 1.0)


def composite_over(
    colour: torch.Tensor,
    alpha: torch.Tensor | None,
    background: float | torch.Tensor | None = None,
) -> torch.Tensor:
    """Composite straight-alpha colour [B, H, W, C] over a background, in linear space.

    alpha: [B, H, W, 1] coverage in [0, 1], or None (colour is returned unchanged).
    background: linear colour broadcastable to [B, H, W, C] (a float, [C], or an image);
        None means black.
    Returns alpha * colour + (1 - alpha) * background, [B, H, W, C].
    """
    if alpha is None:
        return colour
    alpha = _check_plane(alpha, colour, "alpha")
    if background is None:
        background = 0.0
    background = torch.as_tensor(background, dtype=colour.dtype, device=colour.device)
    try:
        return torch.lerp(background.expand_as(colour), colour, alpha)
    except RuntimeError as error:
        raise ReconError(
            f"background: shape {tuple(background.shape)} does not broadcast to the images "
            f"{tuple(colour.shape)}"
        ) from error


def _prepare(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None,
    background: float | torch.Tensor | None = None,
    prediction_alpha: torch.Tensor | None = None,
    target_alpha: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Validate, composite each image that has an alpha, and return (prediction, target, mask)."""
    _check_images(prediction, target)
    mask = _check_plane(mask, prediction, "mask")
    prediction_alpha = _check_plane(prediction_alpha, prediction, "prediction_alpha")
    target_alpha = _check_plane(target_alpha, target, "target_alpha")
    if background is not None and prediction_alpha is None and target_alpha is None:
        # A background without any alpha would be silently ignored: say so instead.
        raise ReconError("background: given, but neither prediction_alpha nor target_alpha is")
    prediction = composite_over(prediction, prediction_alpha, background)
    target = composite_over(target, target_alpha, background)
    return prediction, target, mask


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------


def psnr_srgb(
    prediction: torch.Tensor,
    target: torch.Tensor,
    background: float | torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    prediction_alpha: torch.Tensor | None = None,
    target_alpha: torch.Tensor | None = None,
) -> ViewMetric:
    """PSNR in dB the way nvdiffrec reports it: on sRGB-encoded values clamped to [0, 1].

    prediction, target: [B, H, W, C] linear radiance. Each one with an alpha [B, H, W, 1] is first
    composited over `background` (linear; black when None) in linear space. Then both are
    sRGB-encoded and clamped to [0, 1], the MSE is taken over each view's pixels and channels
    (only pixels with mask > 0.5 when a mask [B, H, W, 1] is given) and PSNR = 10 log10(1 / MSE),
    capped at 100 dB. Returns per-view PSNR [B] and its mean over views.
    """
    prediction, target, mask = _prepare(
        prediction, target, mask, background, prediction_alpha, target_alpha
    )
    squared = (to_display(prediction) - to_display(target)) ** 2
    mse = _masked_mean(squared, _selection(mask, prediction))
    return _view_metric(_psnr_from_mse(mse, 1.0))


def psnr_linear(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    peak: float | None = 1.0,
) -> ViewMetric:
    """PSNR in dB on linear radiance, unclamped (HDR values above 1 count as they are).

    prediction, target: [B, H, W, C] linear; mask: [B, H, W, 1] or None.
    peak: the signal peak in PSNR = 10 log10(peak^2 / MSE). The default 1.0 is fixed so that
    numbers compare across views, scenes and methods; None uses each view's target maximum over
    the counted pixels instead (so one bright specular highlight raises that view's PSNR, which
    is why it is not the default). Capped at 100 dB. Returns per-view PSNR [B] and the mean.
    """
    prediction, target, mask = _prepare(prediction, target, mask)
    weights = _selection(mask, prediction)
    mse = _masked_mean((prediction - target) ** 2, weights)
    if peak is None:
        counted = torch.where(weights > 0, target, torch.full_like(target, -math.inf))
        view_peak = counted.amax(dim=(1, 2, 3))
        # A black target has no peak to speak of: fall back to 1 rather than dividing by 0.
        view_peak = torch.where(view_peak > 0, view_peak, torch.ones_like(view_peak))
    else:
        if not peak > 0:
            raise ReconError(f"peak: expected a positive value or None, got {peak}")
        view_peak = peak
    return _view_metric(_psnr_from_mse(mse, view_peak))


def mae(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    space: str = "linear",
) -> ViewMetric:
    """Mean absolute error per view over pixels and channels.

    prediction, target: [B, H, W, C] linear; mask: [B, H, W, 1] or None.
    space: "linear" (default: radiance as given, unclamped) or "srgb" (encoded and clamped to
    [0, 1], like psnr_srgb). Returns per-view MAE [B] and the mean.
    """
    _check_space(space)
    prediction, target, mask = _prepare(prediction, target, mask)
    if space == "srgb":
        prediction, target = to_display(prediction), to_display(target)
    error = _masked_mean((prediction - target).abs(), _selection(mask, prediction))
    return _view_metric(error)


def ssim(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    window_size: int = SSIM_WINDOW,
) -> ViewMetric:
    """SSIM per view via kornia.metrics.ssim on sRGB values clamped to [0, 1].

    prediction, target: [B, H, W, C] linear (H and W must exceed window_size // 2, since kornia
    reflect-pads by that much); mask: [B, H, W, 1] or None.
    Gaussian window of window_size taps (sigma 1.5), data range 1, eps 0 (so identical images
    score exactly 1). Unmasked: the mean of the full SSIM map. Masked: both images are set to 0
    outside the mask first (as Stanford-ORB masks by multiplication) so that neither image's
    outside pixels can reach the windows that straddle the border, and the map is averaged over
    the mask's pixels and all channels. Returns per-view SSIM [B] and the mean.
    """
    prediction, target, mask = _prepare(prediction, target, mask)
    height, width = prediction.shape[1:3]
    if min(height, width) <= window_size // 2:
        raise ReconError(
            f"prediction: SSIM with a {window_size}-tap window needs images larger than "
            f"{window_size // 2} pixels on each side, got {height} x {width}"
        )
    weights = _selection(mask, prediction)
    prediction, target = to_display(prediction), to_display(target)
    if mask is not None:
        prediction, target = prediction * weights, target * weights
    # kornia wants channels first: [B, H, W, C] -> [B, C, H, W], and back for the mean.
    similarity = kornia.metrics.ssim(
        prediction.permute(0, 3, 1, 2),
        target.permute(0, 3, 1, 2),
        window_size,
        max_val=1.0,
        eps=0.0,
        padding="same",
    ).permute(0, 2, 3, 1)
    return _view_metric(_masked_mean(similarity, weights))


def fit_channel_scale(
    prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Least-squares per-view, per-channel scale s [B, C] minimising |s * prediction - target|^2.

    prediction, target: [B, H, W, C] linear; mask: [B, H, W, 1] or None (fit over mask > 0.5).
    s = sum(prediction * target) / sum(prediction^2) over the counted pixels; a channel whose
    prediction is (nearly) all zero keeps s = 1, as in Stanford-ORB.
    """
    _check_images(prediction, target)
    mask = _check_plane(mask, prediction, "mask")
    weights = _selection(mask, prediction)
    numerator = (prediction * target * weights).sum(dim=(1, 2))
    denominator = (prediction * prediction * weights).sum(dim=(1, 2))
    usable = denominator > 1e-12
    return torch.where(usable, numerator / denominator.clamp(min=1e-12), torch.ones_like(numerator))


def scale_invariant_psnr(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    space: str = "srgb",
) -> ViewMetric:
    """PSNR after scaling each prediction channel, per view, by its least-squares fit to target.

    This removes the albedo x light-intensity ambiguity of relighting, as Stanford-ORB does: the
    scale (fit_channel_scale) is fitted in linear radiance over the counted pixels (mask > 0.5, or
    all), applied to the whole prediction, and then the PSNR is taken in `space`: "srgb"
    (default; as psnr_srgb, Stanford-ORB's PSNR-L) or "linear" (as psnr_linear with peak 1,
    their PSNR-H without the clip). prediction, target: [B, H, W, C]; mask: [B, H, W, 1] or None.
    Returns per-view PSNR [B] and the mean.
    """
    _check_space(space)
    scale = fit_channel_scale(prediction, target, mask)  # validates the inputs
    scaled = prediction * scale[:, None, None, :]
    if space == "srgb":
        return psnr_srgb(scaled, target, mask=mask)
    return psnr_linear(scaled, target, mask=mask)


def image_metrics(
    prediction: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    background: float | torch.Tensor | None = None,
    prediction_alpha: torch.Tensor | None = None,
    target_alpha: torch.Tensor | None = None,
) -> dict[str, float]:
    """All image metrics, each the mean over views, as Python floats.

    prediction, target: [B, H, W, C] linear radiance; mask: [B, H, W, 1] or None. When alphas
    are given, each image is composited over `background` first (see psnr_srgb) and every metric
    sees the composited images.

    Keys: psnr (sRGB, nvdiffrec's), psnr_linear (peak 1), ssim (sRGB, window 11), mae (linear),
    psnr_scale_invariant (per-channel scale, sRGB); with a mask also the same keys with a
    "_masked" suffix, computed over mask > 0.5 only.
    """
    prediction, target, mask = _prepare(
        prediction, target, mask, background, prediction_alpha, target_alpha
    )
    results: dict[str, float] = {}
    for suffix, selection in (("", None), ("_masked", mask)):
        if suffix and mask is None:
            continue
        results["psnr" + suffix] = psnr_srgb(prediction, target, mask=selection).mean
        results["psnr_linear" + suffix] = psnr_linear(prediction, target, mask=selection).mean
        results["ssim" + suffix] = ssim(prediction, target, mask=selection).mean
        results["mae" + suffix] = mae(prediction, target, mask=selection).mean
        results["psnr_scale_invariant" + suffix] = scale_invariant_psnr(
            prediction, target, mask=selection
        ).mean
    return results
