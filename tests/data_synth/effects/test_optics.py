"""World optics effects: cos^p x mechanical vignetting, Brown-Conrady distortion (a dot moves
where the model says), disk defocus PSF, trajectory motion blur."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.optimize import brentq

from data_synth.effects.base import Capture
from data_synth.effects.optics import (
    DefocusBlur,
    LensDistortion,
    MotionBlur,
    Vignetting,
    brown_conrady,
    disk_kernel,
    pupil_transmission,
    undistort,
)
from recon.camera.cameras import orbit_cameras


def make_capture(images: torch.Tensor, alpha: torch.Tensor | None = None) -> Capture:
    count, height, width = images.shape[:3]
    if alpha is None:
        alpha = torch.ones(count, height, width, 1)
    return Capture(images.clone(), alpha.clone(), orbit_cameras(count, (height, width)))


def gaussian_dot(size: int, column: float, row: float, sigma: float = 1.0) -> torch.Tensor:
    """[size, size] Gaussian of std sigma centred at pixel position (column, row)."""
    centres = torch.arange(size, dtype=torch.float64) + 0.5
    rows, columns = torch.meshgrid(centres, centres, indexing="ij")
    return torch.exp(-((columns - column) ** 2 + (rows - row) ** 2) / (2 * sigma**2)).float()


def centroid(image: torch.Tensor) -> tuple[float, float]:
    """(column, row) intensity centroid of image [H, W] (pixel centres at i + 0.5)."""
    height, width = image.shape
    rows = torch.arange(height, dtype=torch.float64) + 0.5
    columns = torch.arange(width, dtype=torch.float64) + 0.5
    weights = image.double()
    total = weights.sum()
    return float((weights.sum(0) * columns).sum() / total), float(
        (weights.sum(1) * rows).sum() / total
    )


def second_moments(image: torch.Tensor) -> torch.Tensor:
    """Intensity covariance [2, 2] of image [H, W] in (column, row) axes."""
    height, width = image.shape
    rows, columns = torch.meshgrid(
        torch.arange(height, dtype=torch.float64),
        torch.arange(width, dtype=torch.float64),
        indexing="ij",
    )
    weights = image.double() / image.double().sum()
    mean_column, mean_row = (weights * columns).sum(), (weights * rows).sum()
    dc, dr = columns - mean_column, rows - mean_row
    return torch.stack(
        [
            torch.stack([(weights * dc * dc).sum(), (weights * dc * dr).sum()]),
            torch.stack([(weights * dc * dr).sum(), (weights * dr * dr).sum()]),
        ]
    )


# ------------------------------------------------------------------------------- vignetting


def lens_area_fraction(distance: float, radius: float) -> float:
    """Overlap of a unit circle and a circle of radius at distance, over pi (segment form)."""
    if distance <= radius - 1:
        return 1.0
    if distance >= radius + 1:
        return 0.0
    to_chord = (distance**2 - radius**2 + 1) / (2 * distance)  # from the unit circle's centre
    from_barrel = distance - to_chord
    segment_unit = math.acos(to_chord) - to_chord * math.sqrt(1 - to_chord**2)
    segment_barrel = radius**2 * math.acos(from_barrel / radius) - from_barrel * math.sqrt(
        radius**2 - from_barrel**2
    )
    return (segment_unit + segment_barrel) / math.pi


def test_pupil_transmission_is_the_circle_overlap() -> None:
    for radius in (1.0, 1.5, 2.5):
        distances = torch.linspace(max(radius - 1.2, 0.01), radius + 1.2, 23, dtype=torch.float64)
        computed = pupil_transmission(distances, radius)
        expected = torch.tensor(
            [lens_area_fraction(float(d), radius) for d in distances], dtype=torch.float64
        )
        torch.testing.assert_close(computed, expected, atol=1e-9, rtol=0)
        assert bool((computed.diff() <= 1e-12).all())  # farther off axis, less light


def test_vignetting_natural_falloff_is_cos4_of_the_field_angle() -> None:
    capture = make_capture(torch.ones(2, 32, 48, 3))
    fx, fy = capture.cameras.intrinsics[0, 0, 0].item(), capture.cameras.intrinsics[0, 1, 1].item()
    applied = Vignetting({"cos_power": 4.0, "strength": 0.0}).apply(capture, torch.Generator())
    # Corner pixel centre (0.5, 0.5); the principal point is the image centre (24, 16).
    tan_squared = ((0.5 - 24) / fx) ** 2 + ((0.5 - 16) / fy) ** 2
    expected_corner = math.cos(math.atan(math.sqrt(tan_squared))) ** 4
    for view in range(2):
        assert abs(float(capture.images[view, 0, 0, 0]) - expected_corner) < 1e-5
        assert abs(float(capture.images[view, -1, -1, 2]) - expected_corner) < 1e-5
        assert abs(applied.parameters["corner_falloff"][view] - expected_corner) < 1e-5
    assert abs(applied.parameters["mechanical_corner_falloff"][0] - 1.0) < 1e-9
    # Half the half diagonal from the centre: one field angle all round the circle.
    half_radius = 0.25 * math.hypot(32, 48)
    # The principal point is the image centre and fx == fy here, so tan = radius / fx.
    expected_half = math.cos(math.atan(half_radius / fx)) ** 4
    assert abs(fx - fy) < 1e-9
    assert abs(applied.parameters["half_radius_falloff"][1] - expected_half) < 1e-6


def test_vignetting_corners_darken_by_the_analytic_cos4_times_mechanical_ratio() -> None:
    height, width, strength, radius, offset = 40, 40, 0.3, 1.5, (3.0, -2.0)
    capture = make_capture(torch.full((2, height, width, 3), 0.5))
    effect = Vignetting(
        {
            "cos_power": 4.0,
            "strength": strength,
            "barrel_radius": radius,
            "offset_x_px": offset[0],
            "offset_y_px": offset[1],
        }
    )
    applied = effect.apply(capture, torch.Generator())
    fx = capture.cameras.intrinsics[0, 0, 0].item()
    corner_radius = math.hypot(width / 2 / fx, height / 2 / fx)
    # The barrel separation that cuts a fraction strength of the pupil at the corner radius.
    separation = brentq(
        lambda d: lens_area_fraction(d, radius) - (1 - strength), radius - 1, radius + 1
    )

    def falloff(column: float, row: float) -> float:
        natural = (1 + ((column - width / 2) / fx) ** 2 + ((row - height / 2) / fx) ** 2) ** -2
        mechanical_radius = math.hypot(
            (column - width / 2 - offset[0]) / fx, (row - height / 2 - offset[1]) / fx
        )
        return natural * lens_area_fraction(separation * mechanical_radius / corner_radius, radius)

    corners = [(0.5, 0.5), (width - 0.5, 0.5), (0.5, height - 0.5), (width - 0.5, height - 0.5)]
    for column, row in corners:
        observed = float(capture.images[1, int(row), int(column), 1]) / 0.5
        assert abs(observed - falloff(column, row)) < 1e-5
    expected_ratio = sum(falloff(c, r) for c, r in corners) / 4 / falloff(width / 2, height / 2)
    assert abs(applied.parameters["corner_falloff"][1] - expected_ratio) < 1e-5
    assert 0.3 < expected_ratio < 0.75
    # The decentred barrel darkens the corner opposite the offset direction most.
    assert float(capture.images[0, -1, 0, 0]) < float(capture.images[0, 0, -1, 0])


def test_vignetting_strength_is_the_pupil_cut_at_the_geometric_corner() -> None:
    capture = make_capture(torch.ones(1, 32, 32, 3))
    effect = Vignetting({"cos_power": 0.0, "strength": 0.4, "barrel_radius": 2.0})
    natural, mechanical = effect.falloff(
        capture.cameras, torch.tensor([32.0, 0.0, 16.0]), torch.tensor([32.0, 0.0, 16.0])
    )
    torch.testing.assert_close(natural, torch.ones_like(natural))
    torch.testing.assert_close(mechanical[0], torch.tensor([0.6, 0.6, 1.0], dtype=mechanical.dtype))


def test_vignetting_zero_strength_is_the_identity() -> None:
    images = torch.rand(2, 16, 16, 3)
    capture = make_capture(images)
    Vignetting({"cos_power": 0.0, "strength": 0.0}).apply(capture, torch.Generator())
    torch.testing.assert_close(capture.images, images, rtol=1e-7, atol=0)


def test_vignetting_sampled_corner_falloff_is_in_range() -> None:
    cameras = orbit_cameras(1, (64, 64), fov_x_deg=50.0)
    for seed in range(6):
        parameters = Vignetting.sample_strength(torch.Generator().manual_seed(seed), cameras)
        capture = Capture(torch.ones(1, 64, 64, 3), torch.ones(1, 64, 64, 1), cameras)
        ratio = (
            Vignetting(parameters).apply(capture, torch.Generator()).parameters["corner_falloff"][0]
        )
        assert 0.5 < ratio < 0.85, (parameters, ratio)


# -------------------------------------------------------------------------- lens distortion


def brown_conrady_reference(x: float, y: float, k1, k2, k3, p1, p2) -> tuple[float, float]:
    """OpenCV's distortion model written out independently."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


COEFFICIENTS = {"k1": 0.5, "k2": -0.05, "k3": 0.05, "p1": 0.02, "p2": -0.015}


def test_undistort_inverts_brown_conrady() -> None:
    coefficients = tuple(COEFFICIENTS.values())
    x = torch.linspace(-0.5, 0.5, 21, dtype=torch.float64)[:, None].expand(21, 21)
    y = x.T
    x_distorted, y_distorted = brown_conrady(x, y, coefficients)
    expected = brown_conrady_reference(0.31, -0.22, *coefficients)
    computed = brown_conrady(torch.tensor(0.31), torch.tensor(-0.22), coefficients)
    assert (
        abs(float(computed[0]) - expected[0]) < 1e-6
        and abs(float(computed[1]) - expected[1]) < 1e-6
    )
    x_back, y_back, valid = undistort(x_distorted, y_distorted, coefficients)
    assert bool(valid.all())
    torch.testing.assert_close(x_back, x, atol=1e-9, rtol=0)
    torch.testing.assert_close(y_back, y, atol=1e-9, rtol=0)


@pytest.mark.parametrize("ideal", [(8.3, 7.6), (55.4, 10.2), (12.6, 52.7), (50.0, 50.0)])
def test_distortion_moves_a_dot_where_brown_conrady_puts_it(ideal: tuple[float, float]) -> None:
    size = 64
    dot = gaussian_dot(size, *ideal, sigma=1.0)
    images = dot[None, :, :, None].expand(1, size, size, 3).contiguous()
    capture = make_capture(images, alpha=dot[None, :, :, None])
    applied = LensDistortion(COEFFICIENTS).apply(capture, torch.Generator())
    intrinsics = capture.cameras.intrinsics[0]
    fx, fy, cx, cy = (float(intrinsics[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    x_distorted, y_distorted = brown_conrady_reference(
        (ideal[0] - cx) / fx, (ideal[1] - cy) / fy, *COEFFICIENTS.values()
    )
    expected = (fx * x_distorted + cx, fy * y_distorted + cy)
    moved = math.hypot(expected[0] - ideal[0], expected[1] - ideal[1])
    assert moved > 1.0  # the test means something
    # ... and near the corners the tangential terms matter: a radial-only model misplaces it.
    radial_only = brown_conrady_reference(
        (ideal[0] - cx) / fx, (ideal[1] - cy) / fy, *list(COEFFICIENTS.values())[:3], 0, 0
    )
    tangential_shift = math.hypot(
        fx * radial_only[0] + cx - expected[0], fy * radial_only[1] + cy - expected[1]
    )
    assert tangential_shift > (0.3 if max(abs(ideal[0] - cx), abs(ideal[1] - cy)) > 19 else 0.1)
    for image in (capture.images[0, :, :, 0], capture.alpha[0, :, :, 0]):
        column, row = centroid(image)
        assert math.hypot(column - expected[0], row - expected[1]) < 0.3, (column, row, expected)
    assert applied.parameters["folded_fraction"] == 0.0
    assert applied.parameters["max_displacement_px"] > moved


def test_distortion_zero_coefficients_is_the_identity() -> None:
    images = torch.rand(2, 16, 16, 3)
    capture = make_capture(images)
    LensDistortion({}).apply(capture, torch.Generator())
    assert torch.equal(capture.images, images)


def test_distortion_keeps_colour_premultiplied() -> None:
    size = 32
    alpha = gaussian_dot(size, 16.0, 16.0, sigma=6.0).clamp(max=1.0)[None, :, :, None]
    colour = torch.tensor([0.2, 0.5, 0.8])
    capture = make_capture(alpha * colour, alpha=alpha)
    LensDistortion({"k1": -0.4, "p1": 0.01}).apply(capture, torch.Generator())
    torch.testing.assert_close(capture.images, capture.alpha * colour, atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------- defocus blur


@pytest.mark.parametrize("radius", [1.5, 2.5, 4.0])
def test_disk_kernel_is_a_disk_with_second_moment_r2_over_2(radius: float) -> None:
    kernel = disk_kernel(radius, torch.float64)
    size = kernel.shape[0]
    assert size % 2 == 1 and abs(float(kernel.sum()) - 1) < 1e-12
    offsets = torch.arange(size, dtype=torch.float64) - size // 2
    rows, columns = torch.meshgrid(offsets, offsets, indexing="ij")
    distance = torch.hypot(rows, columns)
    # Taps wholly inside the disk share one weight; taps wholly outside are 0.
    inside = kernel[distance < radius - math.sqrt(0.5)]
    torch.testing.assert_close(inside, torch.full_like(inside, float(inside[0])))
    assert float(kernel[distance > radius + math.sqrt(0.5)].abs().max()) == 0.0
    # E|x|^2 of a uniform disk is r^2/2: the radius it implies is the configured one (to
    # within the pixel-box antialiasing, which adds at most a few percent).
    moment = float((kernel * distance**2).sum())
    assert abs(math.sqrt(2 * moment) - radius) < 0.03 + 0.02 * radius, (moment, radius)
    assert abs(float(inside[0]) - 1 / (math.pi * radius**2)) < 0.02 / radius**2


def test_defocus_preserves_energy_and_blurs_alpha_alike() -> None:
    dot = torch.zeros(1, 33, 33, 1)
    dot[0, 16, 16] = 1.0
    capture = make_capture(dot.expand(1, 33, 33, 3).contiguous(), alpha=dot)
    applied = DefocusBlur({"radius_px": 3.0}).apply(capture, torch.Generator())
    kernel = disk_kernel(3.0)
    half = kernel.shape[0] // 2
    blurred = capture.images[0, :, :, 0]
    assert abs(float(blurred.sum()) - 1.0) < 1e-5
    torch.testing.assert_close(
        blurred[16 - half : 17 + half, 16 - half : 17 + half], kernel, atol=1e-7, rtol=0
    )
    torch.testing.assert_close(capture.alpha[0, :, :, 0], blurred)
    assert applied.parameters == {"radius_px": 3.0, "kernel_size": kernel.shape[0]}


def test_defocus_zero_radius_is_the_identity() -> None:
    images = torch.rand(1, 16, 16, 3)
    capture = make_capture(images)
    DefocusBlur({"radius_px": 0.0}).apply(capture, torch.Generator())
    assert torch.equal(capture.images, images)


# ----------------------------------------------------------------------------- motion blur


def test_motion_blur_preserves_energy_and_elongates_along_the_realised_angle() -> None:
    size, count = 48, 3
    dot = gaussian_dot(size, 24.0, 24.0, sigma=0.8)
    images = dot[None, :, :, None].expand(count, size, size, 3).contiguous()
    capture = make_capture(images, alpha=dot[None, :, :, None].expand(count, size, size, 1))
    effect = MotionBlur({"length_px": 9.0, "length_spread": 0.0, "curvature_deg": 0.0})
    applied = effect.apply(capture, torch.Generator().manual_seed(11))
    lengths = applied.parameters["lengths_px"]
    assert lengths == [9.0] * count
    before = second_moments(dot)
    for view in range(count):
        blurred = capture.images[view, :, :, 0]
        assert abs(float(blurred.sum()) - float(dot.sum())) < 1e-3
        centre = centroid(blurred)
        assert math.hypot(centre[0] - 24.0, centre[1] - 24.0) < 0.05  # no shift
        covariance = second_moments(blurred) - before
        values, vectors = torch.linalg.eigh(covariance)
        major = vectors[:, 1]
        angle = math.degrees(math.atan2(float(major[1]), float(major[0]))) % 180
        realised = applied.parameters["angles_deg"][view] % 180
        difference = min(abs(angle - realised), 180 - abs(angle - realised))
        assert difference < 2.0, (angle, realised)
        # A uniform segment of length L adds L^2/12 along it and (almost) nothing across.
        assert abs(float(values[1]) - 9.0**2 / 12) < 0.1 * 9.0**2 / 12
        assert float(values[0]) < 0.3  # bilinear splats only
        torch.testing.assert_close(capture.alpha[view, :, :, 0], blurred)


def test_curved_motion_blur_keeps_the_centroid_and_energy() -> None:
    size = 48
    dot = gaussian_dot(size, 24.0, 24.0, sigma=0.8)
    capture = make_capture(dot[None, :, :, None].expand(2, size, size, 3).contiguous())
    applied = MotionBlur({"length_px": 10.0, "curvature_deg": 180.0}).apply(
        capture, torch.Generator().manual_seed(2)
    )
    assert max(abs(turn) for turn in applied.parameters["turns_deg"]) > 10
    for view in range(2):
        blurred = capture.images[view, :, :, 0]
        assert abs(float(blurred.sum()) - float(dot.sum())) < 1e-3
        column, row = centroid(blurred)
        assert math.hypot(column - 24.0, row - 24.0) < 0.05


def test_motion_blur_zero_length_is_the_identity() -> None:
    images = torch.rand(2, 16, 16, 3)
    capture = make_capture(images)
    MotionBlur({"length_px": 0.0}).apply(capture, torch.Generator())
    assert torch.equal(capture.images, images)


@pytest.mark.parametrize("size", [32, 48, 64, 128])
def test_a_sampled_motion_blur_on_a_small_image_leaves_the_centre_tap_under_half(
    size: int,
) -> None:
    # Scaled with the image, the 128 px range drew 0.95 px at 48 px: a kernel with 70 % of its
    # weight in the centre tap. The floor keeps the median path at 2 px or more.
    from data_synth.effects.optics import rasterise_trajectories, trajectory_points

    cameras = orbit_cameras(2, (size, size))
    for seed in range(6):
        generator = torch.Generator().manual_seed(seed)
        length = MotionBlur.sample_strength(generator, cameras)["length_px"]
        assert length >= MotionBlur.SMALLEST_SAMPLED_LENGTH_PX
        points = trajectory_points(
            torch.tensor([length]), torch.tensor([0.3]), torch.tensor([0.0]), 16
        )
        assert float(rasterise_trajectories(points).max()) < 0.5
    # The floor only raises small images: at 128 px the draws stay in the old 2-5 px range.
    if size == 128:
        assert length <= 5.0


def bent_disc(size: int, cameras, coefficients: dict | None, fine: int) -> torch.Tensor:
    """[size, size] coverage of a disc (radius 0.3 in normalised coordinates, off the centre)
    seen through the lens (None: an ideal one), each pixel integrated over fine x fine samples:
    the optical image a sensor integrates."""
    intrinsics = cameras.intrinsics[0].double()
    fx, fy, cx, cy = (intrinsics[i, j] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    centres = (torch.arange(size * fine, dtype=torch.float64) + 0.5) / fine
    rows, columns = torch.meshgrid(centres, centres, indexing="ij")
    x, y = (columns - cx) / fx, (rows - cy) / fy
    if coefficients is not None:
        keys = ("k1", "k2", "k3", "p1", "p2")
        x, y, _ = undistort(x[None], y[None], tuple(coefficients[key] for key in keys))
        x, y = x[0], y[0]
    inside = (((x - 0.05) ** 2 + y**2) < 0.3**2).double()
    return torch.nn.functional.avg_pool2d(inside[None, None], fine)[0, 0].float()


def test_a_distortion_bent_on_the_supersampled_optical_image_adds_no_blur() -> None:
    # A hard-edged disc bent by a barrel distortion (5 px at the corners of a 48 px view):
    # bending the finished 48 px image resamples it bilinearly and widens its edge by 75 %;
    # bending a 4x rendering and averaging each pixel's 16 samples lands within 6 % of the
    # exactly integrated optical image, its error a ninth.
    from data_synth.effects.registry import apply_effects

    size, scale = 48, 4
    coefficients = {"k1": -0.35, "k2": 0.0, "k3": 0.0, "p1": 0.004, "p2": -0.003}
    native = orbit_cameras(1, (size, size))
    truth = bent_disc(size, native, coefficients, 16)

    def capture_of(coverage: torch.Tensor, cameras, pixel_scale: int) -> Capture:
        alpha = coverage[None, ..., None]
        return Capture(alpha.expand(-1, -1, -1, 3).clone(), alpha.clone(), cameras, pixel_scale)

    finished = capture_of(bent_disc(size, native, None, 16), native, 1)
    LensDistortion(coefficients).apply(finished, torch.Generator())
    high = native.with_image_size((size * scale, size * scale))
    optical = capture_of(bent_disc(size * scale, high, None, 4), high, scale)
    applied = apply_effects(optical, [LensDistortion(coefficients)], torch.Generator())
    # Back at the output resolution, on the output cameras, premultiplied.
    assert optical.pixel_scale == 1 and optical.cameras.image_size == (size, size)
    torch.testing.assert_close(optical.cameras.intrinsics, native.intrinsics)
    torch.testing.assert_close(optical.images[..., :1], optical.alpha)

    def error(capture: Capture) -> float:
        return float((capture.alpha[0, ..., 0] - truth).pow(2).mean().sqrt())

    def edge(coverage: torch.Tensor) -> float:  # partly covered pixels' share, ~ edge width
        return float((coverage * (1 - coverage)).sum())

    assert error(optical) < error(finished) / 5
    assert edge(finished.alpha[0, ..., 0]) > 1.5 * edge(truth)
    assert edge(optical.alpha[0, ..., 0]) == pytest.approx(edge(truth), rel=0.08)
    # Reported in output pixels, like the unsupersampled distortion's (its outermost samples lie
    # a little nearer the corners than the outermost pixel centres).
    unsampled = LensDistortion(coefficients).apply(capture_of(truth, native, 1), torch.Generator())
    assert applied[0].parameters["max_displacement_px"] == pytest.approx(
        unsampled.parameters["max_displacement_px"], rel=0.1
    )
