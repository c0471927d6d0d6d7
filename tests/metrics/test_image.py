"""Image metrics: PSNR (sRGB / linear / scale-invariant), SSIM, MAE, masks, compositing, errors."""

from __future__ import annotations

import math

import pytest
import torch

from recon.errors import ReconError
from recon.io.images import linear_to_srgb
from recon.metrics import (
    PSNR_CAP_DB,
    composite_over,
    fit_channel_scale,
    image_metrics,
    mae,
    psnr_linear,
    psnr_srgb,
    scale_invariant_psnr,
    ssim,
)

KEYS = {"psnr", "psnr_linear", "ssim", "mae", "psnr_scale_invariant"}


def random_views(views: int = 2, size: int = 24, seed: int = 0) -> torch.Tensor:
    """[views, size, size, 3] linear radiance in [0, 1]."""
    return torch.rand(views, size, size, 3, generator=torch.Generator().manual_seed(seed))


def srgb(value: float) -> float:
    """The sRGB encoding of one linear value, in float64."""
    return float(linear_to_srgb(torch.tensor(value, dtype=torch.float64)))


def srgb_slope(value: float) -> float:
    """d srgb / d linear at a linear value above the 0.0031308 knee."""
    return 1.055 / 2.4 * value ** (1 / 2.4 - 1)


def test_identical_images_hit_the_cap_and_score_ssim_one(device: torch.device) -> None:
    target = random_views().to(device)
    for metric in (psnr_srgb, psnr_linear, scale_invariant_psnr):
        result = metric(target, target.clone())
        assert result.per_view.shape == (2,) and result.per_view.device.type == device.type
        assert torch.all(result.per_view == PSNR_CAP_DB) and result.mean == PSNR_CAP_DB
    assert abs(ssim(target, target.clone()).mean - 1.0) < 1e-6
    assert mae(target, target.clone()).mean == 0.0
    metrics = image_metrics(target, target.clone())
    assert set(metrics) == KEYS and all(isinstance(value, float) for value in metrics.values())
    assert all(math.isfinite(value) for value in metrics.values())


def test_uniform_error_gives_the_formula(device: torch.device) -> None:
    target = torch.full((1, 8, 8, 3), 0.5, device=device)
    prediction = target + 0.01
    # Linear, peak 1: MSE = 1e-4 -> 40 dB.
    assert psnr_linear(prediction, target).mean == pytest.approx(40.0, abs=1e-3)
    # sRGB: every pixel's error is srgb(0.51) - srgb(0.5).
    expected = -20.0 * math.log10(srgb(0.51) - srgb(0.5))
    assert psnr_srgb(prediction, target).mean == pytest.approx(expected, abs=1e-3)
    # Peak = the target's maximum (2.0) instead of 1: + 20 log10(2) dB.
    assert psnr_linear(prediction * 4, target * 4, peak=None).mean == pytest.approx(
        10 * math.log10(4.0 / 0.04**2), abs=1e-3
    )
    assert mae(prediction, target).mean == pytest.approx(0.01, abs=1e-6)
    assert mae(prediction, target, space="srgb").mean == pytest.approx(
        srgb(0.51) - srgb(0.5), abs=1e-6
    )


@pytest.mark.parametrize("level", [0.02, 0.8])
def test_srgb_psnr_differs_from_linear_by_the_curve_slope(level: float) -> None:
    # A small error e in linear becomes slope * e in sRGB, so the two PSNRs differ by
    # -20 log10(slope): sRGB is harsher in the shadows (slope > 1) and milder in the highlights.
    target = torch.full((1, 8, 8, 3), level)
    prediction = target * 1.01
    difference = psnr_srgb(prediction, target).mean - psnr_linear(prediction, target).mean
    slope = srgb_slope(level * 1.005)
    assert difference == pytest.approx(-20 * math.log10(slope), abs=0.05)
    assert (difference < 0) == (level < 0.2)


def test_srgb_psnr_clamps_to_the_displayable_range() -> None:
    # Both above 1 in linear: clamped to the same white, so no error in sRGB; linear sees it.
    target = torch.full((1, 8, 8, 3), 1.5)
    prediction = torch.full((1, 8, 8, 3), 3.0)
    assert psnr_srgb(prediction, target).mean == PSNR_CAP_DB
    assert psnr_linear(prediction, target).mean == pytest.approx(10 * math.log10(1 / 2.25))


def test_mean_of_per_view_psnr_is_not_the_pooled_psnr() -> None:
    # Documented choice (nvdiffrec's): mean of per-view PSNR. View 0 has MSE 1e-4 (40 dB), view 1
    # MSE 1e-2 (20 dB): the mean is 30 dB, the PSNR of the pooled MSE only 22.97 dB (Jensen).
    target = torch.full((2, 8, 8, 3), 0.5)
    prediction = target.clone()
    prediction[0] += 0.01
    prediction[1] += 0.1
    result = psnr_linear(prediction, target)
    assert result.per_view.tolist() == pytest.approx([40.0, 20.0], abs=1e-3)
    assert result.mean == pytest.approx(30.0, abs=1e-3)
    pooled = 10 * math.log10(1 / ((1e-4 + 1e-2) / 2))
    assert pooled == pytest.approx(22.967, abs=1e-3) and result.mean > pooled


def test_masked_metrics_ignore_outside_pixels() -> None:
    target = random_views(seed=1)
    mask = torch.zeros(2, 24, 24, 1)
    mask[:, 4:20, 6:18] = 1.0
    inside = mask.bool().expand_as(target)
    noise = random_views(seed=2)
    # Error only outside the mask: every masked metric is perfect, the unmasked ones are not.
    prediction = torch.where(inside, target, noise)
    metrics = image_metrics(prediction, target, mask)
    assert set(metrics) == KEYS | {key + "_masked" for key in KEYS}
    assert metrics["psnr_masked"] == PSNR_CAP_DB and metrics["psnr_linear_masked"] == PSNR_CAP_DB
    assert metrics["mae_masked"] == 0.0 and metrics["ssim_masked"] == pytest.approx(1.0, abs=1e-6)
    assert metrics["psnr_scale_invariant_masked"] == PSNR_CAP_DB
    assert metrics["psnr"] < 20 and metrics["ssim"] < 0.9
    # With error inside as well, the outside pixels of either image still do not matter.
    blurred = target * 0.9 + 0.05
    first = torch.where(inside, blurred, noise)
    second = torch.where(inside, blurred, 1.0 - noise)
    other_target = torch.where(inside, target, noise * 0.3)
    first_metrics = image_metrics(first, target, mask)
    second_metrics = image_metrics(second, other_target, mask)
    for key in KEYS:
        assert first_metrics[key + "_masked"] == pytest.approx(
            second_metrics[key + "_masked"], rel=1e-5
        )
    # A bool mask and a [B, H, W] mask are accepted alike.
    assert psnr_srgb(first, target, mask=mask[..., 0] > 0.5).mean == pytest.approx(
        first_metrics["psnr_masked"], rel=1e-6
    )


def test_views_with_empty_masks_are_left_out_of_the_mean() -> None:
    target = torch.full((2, 8, 8, 3), 0.5)
    prediction = target + 0.01
    mask = torch.zeros(2, 8, 8, 1)
    mask[0] = 1.0
    result = psnr_linear(prediction, target, mask=mask)
    assert math.isnan(float(result.per_view[1])) and result.mean == pytest.approx(40.0, abs=1e-3)
    with pytest.raises(ReconError, match="mask"):
        psnr_linear(prediction, target, mask=torch.zeros(2, 8, 8, 1))


def test_scale_invariant_psnr_ignores_per_channel_scale() -> None:
    target = random_views(seed=3)
    scales = torch.tensor([[0.5, 2.0, 1.3], [3.0, 0.25, 0.8]])  # per view, per channel
    scaled = target * scales[:, None, None, :]
    assert scale_invariant_psnr(scaled, target).mean == PSNR_CAP_DB
    assert psnr_srgb(scaled, target).mean < 15
    assert torch.allclose(fit_channel_scale(scaled, target), 1 / scales, rtol=1e-5)
    # With a genuine error left over, scaling the prediction changes nothing either.
    noisy = target + 0.05 * (random_views(seed=4) - 0.5)
    for space in ("srgb", "linear"):
        reference = scale_invariant_psnr(noisy, target, space=space).per_view
        rescaled = scale_invariant_psnr(noisy * scales[:, None, None, :], target, space=space)
        assert torch.allclose(rescaled.per_view, reference, atol=1e-3)
        assert float(reference.min()) >= float(psnr_srgb(noisy, target).per_view.min()) - 1.0
    # A black channel keeps scale 1 instead of dividing by zero.
    black = scaled.clone()
    black[..., 2] = 0.0
    assert torch.all(fit_channel_scale(black, target)[:, 2] == 1.0)


def test_ssim_drops_with_noise_and_is_symmetric() -> None:
    target = random_views(seed=5) * 0.5 + 0.25
    prediction = (target + 0.1 * (random_views(seed=6) - 0.5)).clamp(0, 1)
    forward, backward = ssim(prediction, target), ssim(target, prediction)
    assert 0.0 < forward.mean < 0.99
    assert torch.allclose(forward.per_view, backward.per_view, atol=1e-6)
    with pytest.raises(ReconError, match="prediction"):
        ssim(torch.rand(1, 5, 5, 3), torch.rand(1, 5, 5, 3))


def test_alpha_is_composited_over_the_background_in_linear_space() -> None:
    # A half-covered black target over white is linear 0.5 (nvdiffrec's lerp), before sRGB.
    target = torch.zeros(1, 8, 8, 3)
    target_alpha = torch.full((1, 8, 8, 1), 0.5)
    prediction = torch.full((1, 8, 8, 3), 0.5)
    assert psnr_srgb(prediction, target, background=1.0, target_alpha=target_alpha).mean == (
        PSNR_CAP_DB
    )
    composited = composite_over(target, target_alpha, torch.tensor([1.0, 1.0, 1.0]))
    assert torch.allclose(composited, prediction)
    # Both with alpha 0: only the background is left, whatever the colours.
    zero = torch.zeros(1, 8, 8, 1)
    assert (
        psnr_srgb(
            torch.rand(1, 8, 8, 3),
            torch.rand(1, 8, 8, 3),
            background=0.3,
            prediction_alpha=zero,
            target_alpha=zero,
        ).mean
        == PSNR_CAP_DB
    )
    metrics = image_metrics(prediction, target, target_alpha=target_alpha, background=1.0)
    assert metrics["psnr"] == PSNR_CAP_DB and metrics["mae"] == 0.0


def test_bad_inputs_name_the_argument() -> None:
    images = random_views()
    with pytest.raises(ReconError, match="prediction"):
        psnr_srgb(images[0], images[0])
    with pytest.raises(ReconError, match="target"):
        psnr_srgb(images, images[:1])
    with pytest.raises(ReconError, match="target"):
        psnr_srgb(images, images.to("meta"))
    with pytest.raises(ReconError, match="mask"):
        psnr_srgb(images, images, mask=torch.ones(2, 24, 24, 3))
    with pytest.raises(ReconError, match="mask"):
        psnr_srgb(images, images, mask=torch.ones(2, 24, 24, 1, device="meta"))
    with pytest.raises(ReconError, match="background"):
        psnr_srgb(images, images, background=1.0)
    with pytest.raises(ReconError, match="prediction"):
        psnr_srgb(images.clone().fill_(math.nan), images)
    with pytest.raises(ReconError, match="space"):
        mae(images, images, space="log")
    with pytest.raises(ReconError, match="peak"):
        psnr_linear(images, images, peak=0.0)
    with pytest.raises(ReconError, match="prediction"):
        image_metrics(images.to(torch.int64), images)
