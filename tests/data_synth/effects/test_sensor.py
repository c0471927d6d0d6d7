"""World sensor effects: exposure ratios and clipping, white balance on the Planckian locus,
Poisson-Gaussian noise whose variance follows a * I + b."""

from __future__ import annotations

import torch

from data_synth.effects.base import Capture
from data_synth.effects.sensor import Exposure, Noise, WhiteBalance, blackbody_rgb
from recon.camera.cameras import orbit_cameras


def make_capture(images: torch.Tensor) -> Capture:
    """A capture of images [B, H, W, 3], fully covered, from orbit cameras."""
    count, height, width = images.shape[:3]
    alpha = torch.ones(count, height, width, 1)
    return Capture(images.clone(), alpha, orbit_cameras(count, (height, width)))


def random_images(count: int = 4, size: int = 32, seed: int = 0) -> torch.Tensor:
    return torch.rand(count, size, size, 3, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------------------------- exposure


def test_exposure_scales_each_view_by_its_realised_ratio() -> None:
    images = random_images()
    capture = make_capture(images)
    applied = Exposure({"spread_stops": 0.7}).apply(capture, torch.Generator().manual_seed(3))
    ratios = torch.tensor(applied.parameters["ratios"])
    assert len(ratios) == 4 and float((ratios - 1).abs().max()) > 0.05
    expected = images * ratios[:, None, None, None]
    torch.testing.assert_close(capture.images, expected, rtol=1e-5, atol=1e-7)
    stops = torch.tensor(applied.parameters["stops"])
    torch.testing.assert_close(torch.exp2(stops), ratios, rtol=1e-5, atol=0)
    assert torch.equal(capture.alpha, torch.ones_like(capture.alpha))


def test_exposure_clips_at_the_full_well_and_leaves_the_rest_exact() -> None:
    images = random_images()
    capture = make_capture(images)
    applied = Exposure({"spread_stops": 0.5, "full_well": 0.6}).apply(
        capture, torch.Generator().manual_seed(4)
    )
    ratios = torch.tensor(applied.parameters["ratios"])
    scaled = images * ratios[:, None, None, None]
    assert float(capture.images.max()) <= 0.6 + 1e-6
    below = scaled < 0.6
    torch.testing.assert_close(capture.images[below], scaled[below], rtol=1e-5, atol=1e-7)
    expected_fraction = float((scaled > 0.6).double().mean())
    assert abs(applied.parameters["clipped_fraction"] - expected_fraction) < 1e-3


def test_exposure_zero_spread_is_the_identity() -> None:
    images = random_images()
    capture = make_capture(images)
    applied = Exposure({"spread_stops": 0.0}).apply(capture, torch.Generator().manual_seed(0))
    assert torch.equal(capture.images, images)
    assert applied.parameters["ratios"] == [1.0] * 4


# ----------------------------------------------------------------------------- white balance


def test_white_balance_applies_per_channel_gains_with_green_one() -> None:
    images = random_images()
    capture = make_capture(images)
    effect = WhiteBalance({"spread_kelvin": 1500.0, "spread_tint": 0.02})
    applied = effect.apply(capture, torch.Generator().manual_seed(5))
    gains = torch.tensor(applied.parameters["gains"])
    assert gains.shape == (4, 3)
    torch.testing.assert_close(gains[:, 1], torch.ones(4))
    torch.testing.assert_close(
        capture.images, images * gains[:, None, None, :], rtol=1e-5, atol=1e-7
    )
    # The gains follow from the realised temperatures and tints (Planckian locus, then tint).
    kelvin = torch.tensor(applied.parameters["kelvin"], dtype=torch.float64)
    tint = torch.tensor(applied.parameters["tint"], dtype=torch.float64)
    torch.testing.assert_close(effect.gains(kelvin, tint).float(), gains, rtol=1e-4, atol=0)


def test_blackbody_colour_runs_from_red_to_blue() -> None:
    kelvin = torch.tensor([2500.0, 4000.0, 6500.0, 10000.0, 20000.0], dtype=torch.float64)
    rgb = blackbody_rgb(kelvin)
    torch.testing.assert_close(rgb[:, 1], torch.ones(5, dtype=torch.float64))
    assert bool((rgb[:, 0].diff() < 0).all()) and bool((rgb[:, 2].diff() > 0).all())
    assert bool((rgb > 0).all())
    # 6500 K is close to D65 (white in sRGB): within a few percent per channel.
    assert float((rgb[2] - 1).abs().max()) < 0.07


def test_white_balance_warmer_view_has_more_red() -> None:
    effect = WhiteBalance({"reference_kelvin": 6500.0})
    gains = effect.gains(
        torch.tensor([5000.0, 6500.0, 8000.0], dtype=torch.float64),
        torch.zeros(3, dtype=torch.float64),
    )
    torch.testing.assert_close(gains[1], torch.ones(3, dtype=torch.float64))
    assert float(gains[0, 0]) > 1.1 and float(gains[0, 2]) < 0.9  # a warmer light
    assert float(gains[2, 0]) < 1.0 and float(gains[2, 2]) > 1.1  # a cooler light


def test_white_balance_zero_spread_is_the_identity() -> None:
    images = random_images()
    capture = make_capture(images)
    WhiteBalance({"spread_kelvin": 0.0, "spread_tint": 0.0}).apply(
        capture, torch.Generator().manual_seed(0)
    )
    torch.testing.assert_close(capture.images, images, rtol=1e-6, atol=0)


# ------------------------------------------------------------------------------------- noise


def test_noise_variance_follows_a_times_signal_plus_b() -> None:
    levels = torch.tensor([0.2, 0.35, 0.5, 0.65, 0.8, 0.95])
    images = levels[:, None, None, None].expand(6, 64, 64, 3).contiguous()
    capture = make_capture(images)
    effect = Noise({"full_well_photons": 200.0, "read_noise": 0.03})
    applied = effect.apply(capture, torch.Generator().manual_seed(7))
    a, b = applied.parameters["a"], applied.parameters["b"]
    assert abs(a - 1 / 200) < 1e-9 and abs(b - 0.03**2) < 1e-9
    noisy = capture.images.double().reshape(6, -1)
    means, variances = noisy.mean(dim=1), noisy.var(dim=1)
    torch.testing.assert_close(means, levels.double(), atol=2e-3, rtol=0)  # unbiased
    design = torch.stack([levels.double(), torch.ones(6, dtype=torch.float64)], dim=-1)
    slope, intercept = torch.linalg.lstsq(design, variances[:, None]).solution[:, 0].tolist()
    assert abs(slope - a) < 0.1 * a, (slope, a)
    assert abs(intercept - b) < 0.1 * b, (intercept, b)


def test_noise_is_non_negative_and_leaves_alpha() -> None:
    images = random_images() * 0.05
    capture = make_capture(images)
    Noise({"full_well_photons": 100.0, "read_noise": 0.05}).apply(
        capture, torch.Generator().manual_seed(1)
    )
    assert float(capture.images.min()) >= 0.0
    assert torch.equal(capture.alpha, torch.ones_like(capture.alpha))


def test_noise_sampled_like_a_camera_at_iso_400_to_1600() -> None:
    for seed in range(5):
        parameters = Noise.sample_strength(torch.Generator().manual_seed(seed))
        assert 1250 * 0.999 <= parameters["full_well_photons"] <= 5000 * 1.001
        electrons = parameters["read_noise"] * parameters["full_well_photons"]
        assert 1.5 - 1e-3 <= electrons <= 4.0 + 1e-3
