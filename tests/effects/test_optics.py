"""Model effects defocus_blur, motion_blur, lens_distortion: identity at zero, kernel moments,
gradients against central differences (float64), and recovery of their own parameters."""

from __future__ import annotations

import math

import pytest
import torch

from recon.effects import DefocusBlur, LensDistortion, MotionBlur
from recon.effects.optics import fft_size, gaussian_blur
from recon.errors import ReconError


def _image(scene) -> tuple[torch.Tensor, torch.Tensor]:
    return scene.output.color.detach(), scene.output.alpha.detach()


def _moments(image: torch.Tensor) -> tuple[float, torch.Tensor]:
    """Total and covariance [2, 2] (x = column, y = row) of an image [H, W] about its centre."""
    height, width = image.shape
    rows = torch.arange(height, dtype=image.dtype) - height // 2
    columns = torch.arange(width, dtype=image.dtype) - width // 2
    y, x = torch.meshgrid(rows, columns, indexing="ij")
    total = image.sum()
    xx, yy, xy = ((image * x * x).sum(), (image * y * y).sum(), (image * x * y).sum())
    return float(total), torch.stack([torch.stack([xx, xy]), torch.stack([xy, yy])]) / total


@pytest.mark.parametrize("effect_class", [DefocusBlur, MotionBlur, LensDistortion])
def test_identity_at_zero_is_exact(effect_class, sphere_scene):
    color, alpha = _image(sphere_scene)
    effect = effect_class(len(sphere_scene.cameras))
    for views in (sphere_scene.views, None):
        new_color, new_alpha = effect(color, alpha, sphere_scene.cameras, views)
        assert torch.equal(new_color, color) and torch.equal(new_alpha, alpha)


def test_blur_kernels_have_the_parameterised_second_moments():
    impulse = torch.zeros(2, 41, 41, 1, dtype=torch.float64)
    impulse[:, 20, 20] = 1.0
    covariance = torch.tensor(
        [[[2.0, 0.0], [0.0, 2.0]], [[3.0, 1.5], [1.5, 1.0]]], dtype=torch.float64
    )
    blurred = gaussian_blur(impulse, covariance, max_padding=20)
    for view in range(2):
        total, moments = _moments(blurred[view, ..., 0])
        assert total == pytest.approx(1.0, abs=1e-9)
        torch.testing.assert_close(moments, covariance[view], atol=1e-6, rtol=0)
    # The FFT lengths are few and fast (2^a 3^b 5^c).
    assert [fft_size(n) for n in (1, 7, 41, 97, 100)] == [1, 8, 45, 100, 100]


def test_motion_blur_is_a_line_along_its_angle():
    effect = MotionBlur(2, pinned_view=None).double()
    length, angle = 6.0, math.radians(30.0)
    # |w| = L^2 / 24 along the doubled angle.
    magnitude = length**2 / 24
    with torch.no_grad():
        effect.line.copy_(
            torch.tensor(
                [[magnitude * math.cos(2 * angle), magnitude * math.sin(2 * angle)], [0, 0]]
            )
        )
    summary = effect.parameters_summary()
    assert summary["lengths_px"][0] == pytest.approx(length, rel=0.02)
    assert summary["angles_deg"][0] == pytest.approx(30.0, abs=1e-6)
    assert summary["minor_sigma_px"][0] < 0.05 and summary["lengths_px"][1] == 0.0
    impulse = torch.zeros(2, 41, 41, 1, dtype=torch.float64)
    impulse[:, 20, 20] = 1.0
    blurred, _ = effect(impulse, impulse, None, torch.tensor([0, 1]))
    _, moments = _moments(blurred[0, ..., 0].detach())
    eigenvalues, eigenvectors = torch.linalg.eigh(moments)
    assert math.sqrt(12 * float(eigenvalues[1])) == pytest.approx(length, rel=0.02)
    major = eigenvectors[:, 1] * torch.sign(eigenvectors[0, 1])
    torch.testing.assert_close(
        major,
        torch.tensor([math.cos(angle), math.sin(angle)], dtype=torch.float64),
        atol=1e-4,
        rtol=0,
    )
    assert torch.equal(blurred[1], impulse[1])  # the other view is unblurred


def test_gradients_match_central_differences(sphere_scene, central_difference):
    color, alpha = (tensor.double() for tensor in _image(sphere_scene))
    cameras, views = sphere_scene.cameras, sphere_scene.views
    weights = torch.rand(
        color.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64
    )
    defocus = DefocusBlur().double()
    motion = MotionBlur(3).double()
    lens = LensDistortion().double()
    with torch.no_grad():
        motion.line.copy_(torch.tensor([[0.5, 0.2], [0.0, 0.0], [-0.3, 0.4]]))
        lens.set_radial_coefficients(0.2, -0.05)
    checks = [
        (defocus, defocus.variance, [()], 0.0),  # at zero: the blur is first order in variance
        (motion, motion.line, [(0, 0), (1, 1), (2, 0)], 0.0),
        (lens, lens.coefficients, [(0,), (1,)], 1e-7),
    ]
    for effect, parameter, indices, step_floor in checks:

        def loss(effect=effect):
            return (effect(color, alpha, cameras, views)[0] * weights).sum()

        effect.zero_grad()
        loss().backward()
        for index in indices:
            expected = central_difference(loss, parameter, index, step=max(1e-6, step_floor))
            assert parameter.grad[index].item() == pytest.approx(expected, rel=1e-4, abs=1e-7)
            assert expected != 0.0


def test_defocus_gradient_at_zero_points_towards_a_blurrier_target(sphere_scene):
    color, alpha = _image(sphere_scene)
    effect = DefocusBlur()
    with torch.no_grad():
        effect.variance.fill_(1.0)
        target, _ = effect(color, alpha, None, None)
    effect.reset_parameters()
    loss = ((effect(color, alpha, None, None)[0] - target) ** 2).sum()
    loss.backward()
    assert float(effect.variance.grad) < 0


def test_defocus_recovers_sigma(sphere_scene, adam_fit):
    color, alpha = _image(sphere_scene)
    effect = DefocusBlur()
    with torch.no_grad():
        effect.variance.fill_(1.5**2)
        target = effect(color, alpha, None, None)
    assert effect.parameters_summary()["sigma_px"] == pytest.approx(1.5)
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, None, None), target, 100)
    assert effect.parameters_summary()["sigma_px"] == pytest.approx(1.5, rel=0.1)


def test_motion_blur_recovers_per_view_lengths_and_angles(sphere_scene, adam_fit):
    color, alpha = _image(sphere_scene)
    views = sphere_scene.views
    effect = MotionBlur(3)
    with torch.no_grad():
        effect.line.copy_(torch.tensor([[1.0, 0.5], [-0.8, 0.6], [0.0, -1.2]]))
        target = effect(color, alpha, None, views)
    truth = effect.parameters_summary()
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, None, views), target, 150)
    recovered = effect.parameters_summary()
    torch.testing.assert_close(
        torch.tensor(recovered["lengths_px"]), torch.tensor(truth["lengths_px"]), rtol=0.1, atol=0
    )
    angle_error = (
        torch.tensor(recovered["angles_deg"]) - torch.tensor(truth["angles_deg"]) + 90
    ) % 180 - 90
    assert float(angle_error.abs().max()) < 5.0


def test_lens_distortion_undistorts_by_newton(plane_scene):
    cameras = plane_scene.cameras
    effect = LensDistortion().double()
    effect.set_radial_coefficients(0.3, -0.1)
    k1, k2 = (float(value.detach()) for value in effect.radial_coefficients())
    assert (k1, k2) == (pytest.approx(0.3), pytest.approx(-0.1))
    like = torch.zeros((), dtype=torch.float64)
    du, dv = effect.source_offsets(cameras, 40, 40, like)
    focal, centre = float(cameras.intrinsics[0, 0, 0]), 20.0
    pixels = torch.arange(40, dtype=torch.float64) + 0.5
    x_distorted = ((pixels[None, :] - centre) / focal).expand(40, 40)
    y_distorted = ((pixels[:, None] - centre) / focal).expand(40, 40)
    x = x_distorted + du[0].detach() / focal
    y = y_distorted + dv[0].detach() / focal
    squared = x * x + y * y
    radial = 1 + k1 * squared + k2 * squared * squared
    torch.testing.assert_close(x * radial, x_distorted, atol=1e-9, rtol=0)
    torch.testing.assert_close(y * radial, y_distorted, atol=1e-9, rtol=0)


def test_lens_distortion_recovers_k1_and_k2(plane_scene, adam_fit):
    color, alpha = _image(plane_scene)
    cameras = plane_scene.cameras
    effect = LensDistortion()
    effect.set_radial_coefficients(-0.2, 0.1)
    with torch.no_grad():
        target = effect(color, alpha, cameras, None)
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(color, alpha, cameras, None), target, 150)
    summary = effect.parameters_summary()
    assert summary["k1"] == pytest.approx(-0.2, rel=0.1)
    assert summary["k2"] == pytest.approx(0.1, abs=0.03)
    assert summary["corner_shift_px"] < 0  # barrel: the ideal corner moves inward


def test_lens_distortion_rejects_bad_options(plane_scene):
    with pytest.raises(ReconError, match="iterations"):
        LensDistortion(iterations=0)
    color, alpha = _image(plane_scene)
    with pytest.raises(ReconError, match="cameras"):
        LensDistortion()(color, alpha, None, None)


def test_a_blur_module_reuses_its_inputs_spectrum_for_the_same_values():
    """Without gradients a blur module keeps the spectrum of the image it last blurred: blurring
    the same tensors again with another covariance gives the values computed anew, and a
    changed image (in place) is transformed again."""
    from recon.effects.optics import _blur

    generator = torch.Generator().manual_seed(3)
    color = torch.rand(2, 24, 20, 3, generator=generator)
    alpha = torch.rand(2, 24, 20, 1, generator=generator)
    module = MotionBlur(view_count=2)
    padding = math.ceil(3.5 * module.max_length_px / math.sqrt(12.0)) + 1
    with torch.no_grad():
        for line in ([[0.5, 0.2], [0.1, -0.3]], [[0.6, 0.2], [0.1, -0.3]], [[4.0, 1.0], [0, 0]]):
            module.line.copy_(torch.tensor(line))
            kept = module(color, alpha, None, torch.arange(2))
            covariance = module.covariances()
            plain = _blur(color, alpha, covariance, padding)  # no keeper: computed anew
            assert torch.equal(kept[0], plain[0]) and torch.equal(kept[1], plain[1])
        assert module._kept_spectra[3]  # spectra were kept
        color.mul_(0.5)  # the same tensor changed: not the kept spectrum
        again = module(color, alpha, None, torch.arange(2))
        assert torch.equal(again[0], _blur(color, alpha, module.covariances(), padding)[0])


def test_a_blur_module_keeps_a_bounded_number_of_spectra_and_the_latest():
    """Blurs of growing size need growing paddings (other FFT sizes): the module keeps at most
    _KEPT_SPECTRA of them, the oldest dropped first, the one just used always kept."""
    from recon.effects.optics import _KEPT_SPECTRA

    generator = torch.Generator().manual_seed(4)
    color = torch.rand(2, 24, 20, 3, generator=generator)
    alpha = torch.rand(2, 24, 20, 1, generator=generator)
    module = MotionBlur(view_count=2, max_length_px=24.0)
    sizes = []
    with torch.no_grad():
        for length in (0.5, 2.0, 4.0, 6.0, 9.0, 12.0, 16.0, 20.0):
            module.line.copy_(torch.tensor([[length, 0.0], [0.0, length]]))
            module(color, alpha, None, torch.arange(2))
            spectra = module._kept_spectra[3]
            sizes.append(len(spectra))
    # more paddings than kept were used; the kept ones are bounded and never all dropped at once
    assert len(set(sizes)) > 1 and sizes == sorted(sizes)
    assert max(sizes) <= _KEPT_SPECTRA and sizes[-1] == _KEPT_SPECTRA
