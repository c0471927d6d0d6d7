"""Optics-stage world effects on linear radiance: motion blur, defocus blur, lens distortion,
vignetting (applied in that order, see registry.APPLICATION_ORDER).

Why that order: the scene moves during the exposure, so the optical image is integrated over
the camera's path first; the lens then blurs and bends that image; vignetting is an irradiance
falloff fixed to the sensor, so it multiplies last. Geometric effects (blurs, distortion) move
coverage too and are applied to the premultiplied images and the alpha alike.

Each is richer than the model's module on purpose: a disk or trajectory PSF instead of a
Gaussian; Brown-Conrady with tangential terms instead of radial only; the cos^p law of the real
field angle times an off-centre mechanical (barrel) vignetting instead of an even polynomial.
"""

from __future__ import annotations

import functools
import math

import kornia
import torch

from data_synth.effects.base import AppliedEffect, Capture
from data_synth.effects.world_effect import (
    ParameterSpec,
    WorldEffect,
    check_capture,
    corner_radius_normalised,
    nominal_geometry,
    pixel_grid,
    round_float,
    sample_sign,
    sample_uniform,
    standard_normal,
    to_list,
    uniform,
)
from recon.camera import Cameras

# --------------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------------


def _intrinsics(cameras: Cameras, like: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(fx, fy, cx, cy), each [B, 1, 1] on like's device and dtype, ready to broadcast on [B, H, W]."""
    intrinsics = cameras.intrinsics.to(device=like.device, dtype=like.dtype)
    return tuple(
        intrinsics[:, row, column][:, None, None]
        for row, column in ((0, 0), (1, 1), (0, 2), (1, 2))
    )


def filter_capture(capture: Capture, kernels: torch.Tensor) -> None:
    """Convolve images and alpha with point spread functions kernels [1 or B, k, k] (in place).

    Premultiplied colour and coverage are blurred alike, so the colour stays premultiplied.
    Zero padding: outside the frame is background (black, uncovered). Convolution (not
    correlation): the kernel is the PSF itself, so an asymmetric trajectory is not mirrored.
    """
    images, alpha = capture.images, capture.alpha
    stacked = torch.cat([images, alpha], dim=-1).permute(0, 3, 1, 2)  # [B, 4, H, W]
    filtered = kornia.filters.filter2d(
        stacked, kernels.to(stacked), border_type="constant", behaviour="conv"
    ).permute(0, 2, 3, 1)
    # A PSF is non-negative; the clamp only removes float round-off below zero.
    capture.images = filtered[..., :3].clamp(min=0.0).contiguous()
    capture.alpha = filtered[..., 3:].clamp(0.0, 1.0).contiguous()


# --------------------------------------------------------------------------------------------
# defocus blur
# --------------------------------------------------------------------------------------------

# Sub-samples per kernel tap side when integrating the disk's coverage of each tap.
_DISK_SUPERSAMPLING = 16


def disk_kernel(radius_px: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Antialiased pillbox PSF [k, k] (k odd) of a defocused lens with a circular aperture.

    Each tap holds the area of its pixel square inside the disk of radius_px (integrated with
    16 x 16 sub-samples), normalised to sum 1; radius 0 is the identity [[1]].
    """
    if radius_px <= 0:
        return torch.ones(1, 1, dtype=dtype)
    half = math.ceil(radius_px + 0.5)
    taps = torch.arange(-half, half + 1, dtype=torch.float64)
    offsets = (
        torch.arange(_DISK_SUPERSAMPLING, dtype=torch.float64) + 0.5
    ) / _DISK_SUPERSAMPLING - 0.5
    positions = (taps[:, None] + offsets[None, :]).reshape(-1)  # sub-sample coordinates
    y, x = torch.meshgrid(positions, positions, indexing="ij")
    inside = ((x**2 + y**2) <= radius_px**2).double()
    size = taps.numel()
    coverage = inside.reshape(size, _DISK_SUPERSAMPLING, size, _DISK_SUPERSAMPLING).sum(dim=(1, 3))
    return (coverage / coverage.sum()).to(dtype)


class DefocusBlur(WorldEffect):
    """Defocus as a geometric-optics pillbox PSF (the aperture's image), not a Gaussian.

    Realised: the radius and the kernel size.
    """

    name = "defocus_blur"
    stage = "optics"
    PARAMETERS = {
        "radius_px": ParameterSpec(1.5, 0.0, 32.0, "radius of the circle of confusion in pixels"),
    }

    # The smallest radius the sampler draws, in pixels of the image itself. A disk whose radius
    # is below half a pixel lies inside the centre pixel's square: its antialiased kernel is the
    # identity and the "defocused" images equal the sharp ones (at 48 px the scaled range gave
    # 0.38-0.94 px). One pixel is the first radius whose disk reaches over the four neighbours.
    SMALLEST_SAMPLED_RADIUS_PX = 1.0

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """radius 1-2.5 px at 128 px, scaled with the smaller image side, at least 1 px."""
        (height, width), _ = nominal_geometry(cameras)
        scale = min(height, width) / 128.0
        radius = max(sample_uniform(generator, 1.0, 2.5) * scale, cls.SMALLEST_SAMPLED_RADIUS_PX)
        return {"radius_px": round_float(radius)}

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] and alpha [B, H, W, 1] convolved with the disk; cameras unchanged."""
        check_capture(capture, self.name)
        radius = float(self.parameters["radius_px"])
        kernel = disk_kernel(radius, capture.images.dtype)
        if radius > 0:
            filter_capture(capture, kernel[None])
        return AppliedEffect(self.name, {"radius_px": radius, "kernel_size": kernel.shape[-1]})


# --------------------------------------------------------------------------------------------
# motion blur
# --------------------------------------------------------------------------------------------


def trajectory_points(
    lengths: torch.Tensor, angles_rad: torch.Tensor, curvatures_rad: torch.Tensor, samples: int
) -> torch.Tensor:
    """Image-plane positions [B, S, 2] (column, row offsets in pixels) of constant-speed arcs.

    Each path has length lengths[b], starts heading angles_rad[b] - curvatures_rad[b] / 2 and
    turns uniformly by curvatures_rad[b] (a straight segment at 0), sampled at S equal time steps
    and centred on its mean: the PSF's centroid stays put, so the blur does not also shift the
    image (that would be a pose error).
    """
    time = torch.linspace(0.0, 1.0, samples, dtype=torch.float64, device=lengths.device)
    length = lengths.double()[:, None]
    turn = curvatures_rad.double()[:, None]
    start = angles_rad.double()[:, None] - 0.5 * turn
    heading = start + turn * time[None, :]
    straight = turn.abs() < 1e-6
    safe_turn = torch.where(straight, torch.ones_like(turn), turn)
    # Integral of (cos, sin)(heading) over time, times the length: an arc of a circle.
    arc_x = length / safe_turn * (torch.sin(heading) - torch.sin(start))
    arc_y = -length / safe_turn * (torch.cos(heading) - torch.cos(start))
    line_x = length * time * torch.cos(start)
    line_y = length * time * torch.sin(start)
    points = torch.stack(
        [torch.where(straight, line_x, arc_x), torch.where(straight, line_y, arc_y)], dim=-1
    )
    return points - points.mean(dim=1, keepdim=True)


def rasterise_trajectories(points: torch.Tensor) -> torch.Tensor:
    """PSFs [B, k, k] (k odd, shared) with the points [B, S, 2] splatted bilinearly, sum 1.

    Kernel tap (row i, column j) is the offset (j - k // 2, i - k // 2) in pixels.
    """
    count, samples = points.shape[:2]
    half = int(math.ceil(float(points.abs().max()))) + 1
    size = 2 * half + 1
    position = points + half
    base = position.floor()
    fraction = position - base
    base = base.long()
    kernels = torch.zeros(count, size * size, dtype=torch.float64, device=points.device)
    for step_x in (0, 1):
        for step_y in (0, 1):
            weight_x = fraction[..., 0] if step_x else 1 - fraction[..., 0]
            weight_y = fraction[..., 1] if step_y else 1 - fraction[..., 1]
            index = (base[..., 1] + step_y) * size + (base[..., 0] + step_x)
            kernels.scatter_add_(1, index, weight_x * weight_y / samples)
    kernels = kernels.reshape(count, size, size)
    return kernels / kernels.sum(dim=(1, 2), keepdim=True)


class MotionBlur(WorldEffect):
    """Camera shake during the exposure: each view's PSF is a constant-speed arc.

    Per view: length = length_px * exp(length_spread * N(0, 1)) pixels, direction angle
    U[0, 360) degrees measured from the +column axis toward +row (image down), and a total turn
    U[-curvature_deg, curvature_deg] along the path. The path is rasterised into a kernel (four
    samples per pixel, bilinear splats). Realised: per-view lengths, angles and turns (degrees).
    """

    name = "motion_blur"
    stage = "optics"
    PARAMETERS = {
        "length_px": ParameterSpec(3.0, 0.0, 64.0, "median path length in pixels"),
        "length_spread": ParameterSpec(0.3, 0.0, 1.0, "std of the log path length across views"),
        "curvature_deg": ParameterSpec(
            30.0, 0.0, 360.0, "largest total turn of a path in degrees (0 = straight)"
        ),
    }

    # The smallest median path length the sampler draws, in pixels of the image itself. A
    # path centred on a pixel reaches its neighbours' centres (both sides) at 2 px; shorter, the
    # bilinear kernel keeps most of its weight in the centre tap (0.7 at the 0.95 px that the
    # scaled range gave at 48 px: a blur the fit's texture absorbs). The low end of the 128 px
    # range, as the defocus floor is (decision 0202).
    SMALLEST_SAMPLED_LENGTH_PX = 2.0

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """median length 2-5 px at 128 px (scaled with the image, at least 2 px), spread 0.2-0.5,
        turn <= 20-60 degrees."""
        (height, width), _ = nominal_geometry(cameras)
        scale = min(height, width) / 128.0
        length = max(sample_uniform(generator, 2.0, 5.0) * scale, cls.SMALLEST_SAMPLED_LENGTH_PX)
        return {
            "length_px": round_float(length),
            "length_spread": round_float(sample_uniform(generator, 0.2, 0.5)),
            "curvature_deg": round_float(sample_uniform(generator, 20.0, 60.0)),
        }

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] and alpha [B, H, W, 1] convolved with per-view PSFs."""
        count = check_capture(capture, self.name)[0]
        like = torch.empty(0, dtype=torch.float64, device=capture.images.device)
        normal = standard_normal((count,), generator, like)
        draws = uniform((2, count), generator, like)
        lengths = self.parameters["length_px"] * torch.exp(
            self.parameters["length_spread"] * normal
        )
        angles_deg = 360.0 * draws[0]
        turns_deg = self.parameters["curvature_deg"] * (2.0 * draws[1] - 1.0)
        if float(lengths.max()) > 0:
            samples = int(math.ceil(4.0 * float(lengths.max()))) + 2
            points = trajectory_points(
                lengths, torch.deg2rad(angles_deg), torch.deg2rad(turns_deg), samples
            )
            filter_capture(capture, rasterise_trajectories(points))
        return AppliedEffect(
            self.name,
            {
                "lengths_px": to_list(lengths),
                "angles_deg": to_list(angles_deg),
                "turns_deg": to_list(turns_deg),
            },
        )


# --------------------------------------------------------------------------------------------
# lens distortion
# --------------------------------------------------------------------------------------------

_NEWTON_ITERATIONS = 20
# Normalised-coordinate residual under which the inversion counts as converged (~1e-4 px).
_NEWTON_TOLERANCE = 1e-6


def brown_conrady(
    x: torch.Tensor, y: torch.Tensor, coefficients: tuple[float, float, float, float, float]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distorted normalised coordinates (x_d, y_d) of ideal ones (x, y) (OpenCV's model).

    r^2 = x^2 + y^2, radial = 1 + k1 r^2 + k2 r^4 + k3 r^6,
    x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2),  y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y.
    """
    k1, k2, k3, p1, p2 = coefficients
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    x_distorted = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    y_distorted = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return x_distorted, y_distorted


def _distortion_jacobian(
    x: torch.Tensor, y: torch.Tensor, coefficients: tuple[float, float, float, float, float]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entries (d x_d/dx, d x_d/dy = d y_d/dx, d y_d/dy) of brown_conrady's Jacobian."""
    k1, k2, k3, p1, p2 = coefficients
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    radial_slope = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r^2
    dxx = radial + 2 * x * x * radial_slope + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * radial_slope + 2 * p1 * x + 2 * p2 * y
    dyy = radial + 2 * y * y * radial_slope + 6 * p1 * y + 2 * p2 * x
    return dxx, dxy, dyy


def undistort(
    x_distorted: torch.Tensor,
    y_distorted: torch.Tensor,
    coefficients: tuple[float, float, float, float, float],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Invert brown_conrady by Newton's method with the analytic 2x2 Jacobian.

    Starts at the distorted position (the identity is close for real lenses) and stops once
    every point has converged. Returns (x, y, valid): valid is False where the iteration did not
    converge or the mapping folds over (Jacobian determinant <= 0, past the radius where strong
    barrel distortion turns back); those pixels see nothing of the ideal image.
    """
    x, y = x_distorted.clone(), y_distorted.clone()
    for _ in range(_NEWTON_ITERATIONS):
        forward_x, forward_y = brown_conrady(x, y, coefficients)
        error_x, error_y = forward_x - x_distorted, forward_y - y_distorted
        if float(torch.maximum(error_x.abs(), error_y.abs()).max()) < 1e-3 * _NEWTON_TOLERANCE:
            break
        dxx, dxy, dyy = _distortion_jacobian(x, y, coefficients)
        determinant = dxx * dyy - dxy * dxy
        safe = torch.where(determinant.abs() > 1e-12, determinant, torch.ones_like(determinant))
        x = x - (dyy * error_x - dxy * error_y) / safe
        y = y - (dxx * error_y - dxy * error_x) / safe
        # Keep diverging points finite; they are marked invalid below.
        x, y = x.clamp(-1e3, 1e3), y.clamp(-1e3, 1e3)
    forward_x, forward_y = brown_conrady(x, y, coefficients)
    residual = torch.hypot(forward_x - x_distorted, forward_y - y_distorted)
    dxx, dxy, dyy = _distortion_jacobian(x, y, coefficients)
    valid = (residual < _NEWTON_TOLERANCE) & (dxx * dyy - dxy * dxy > 0) & torch.isfinite(residual)
    return x, y, valid


class LensDistortion(WorldEffect):
    """Brown-Conrady lens distortion: radial k1, k2, k3 and tangential (decentring) p1, p2.

    The dataset keeps the ideal pinhole intrinsics; each output pixel at distorted normalised
    position x_d looks up the ideal image at the x with brown_conrady(x) = x_d (Newton
    inversion), bilinearly (torch grid_sample). Positive k1 is pincushion, negative barrel.
    Outside the ideal frame is background. Realised: the five coefficients, the largest pixel
    displacement (in output pixels) and the fraction of pixels where the mapping folded.

    It bends the optical image (supersampled): given a capture rendered above the output
    resolution (config capture.distortion_supersampling), the bilinear lookup's smoothing is a
    fraction of an output pixel, and averaging down integrates each pixel like a sensor.
    Bent at the output resolution, the lookup would blur by up to 0.5 px (sigma), as much as
    the smallest defocus the blind check draws.
    """

    name = "lens_distortion"
    stage = "optics"
    supersampled = True
    PARAMETERS = {
        "k1": ParameterSpec(0.0, -1.0, 1.0, "r^2 radial coefficient (normalised coordinates)"),
        "k2": ParameterSpec(0.0, -1.0, 1.0, "r^4 radial coefficient"),
        "k3": ParameterSpec(0.0, -1.0, 1.0, "r^6 radial coefficient"),
        "p1": ParameterSpec(0.0, -0.05, 0.05, "tangential (decentring) coefficient p1"),
        "p2": ParameterSpec(0.0, -0.05, 0.05, "tangential (decentring) coefficient p2"),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """At the image corner radius r_c: |k1| r_c^2 in [0.05, 0.2] (either sign),
        |k2| r_c^4 <= 0.3 |k1| r_c^2, |k3| r_c^6 <= 0.1 |k1| r_c^2, |p1|, |p2| in
        [0.002, 0.006] (either sign): a few pixels of radial and a fraction of a pixel of
        tangential displacement at 128 px."""
        corner = corner_radius_normalised(cameras)
        radial = sample_sign(generator) * sample_uniform(generator, 0.05, 0.2)
        k2 = sample_uniform(generator, -0.3, 0.3) * abs(radial) / corner**4
        k3 = sample_uniform(generator, -0.1, 0.1) * abs(radial) / corner**6
        p1 = sample_sign(generator) * sample_uniform(generator, 0.002, 0.006)
        p2 = sample_sign(generator) * sample_uniform(generator, 0.002, 0.006)
        values = (radial / corner**2, k2, k3, p1, p2)
        return {
            key: round_float(
                min(max(value, cls.PARAMETERS[key].minimum), cls.PARAMETERS[key].maximum)
            )
            for key, value in zip(("k1", "k2", "k3", "p1", "p2"), values, strict=True)
        }

    def coefficients(self) -> tuple[float, float, float, float, float]:
        return tuple(float(self.parameters[key]) for key in ("k1", "k2", "k3", "p1", "p2"))

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] and alpha [B, H, W, 1] resampled; cameras unchanged."""
        _, height, width = check_capture(capture, self.name)
        coefficients = self.coefficients()
        if all(value == 0.0 for value in coefficients):
            return AppliedEffect(
                self.name, {**self.parameters, "max_displacement_px": 0.0, "folded_fraction": 0.0}
            )
        like = torch.empty(0, dtype=torch.float64, device=capture.images.device)
        # The sampling map depends on the intrinsics only: solve it once per distinct camera
        # (usually one for the whole capture) and index it per view.
        intrinsics = capture.cameras.intrinsics.to(like)
        rows, columns = torch.tensor([0, 1, 0, 1]), torch.tensor([0, 1, 2, 2])
        distinct, view_to_distinct = torch.unique(
            intrinsics[:, rows, columns], dim=0, return_inverse=True
        )
        fx, fy, cx, cy = (distinct[:, index][:, None, None] for index in range(4))
        u, v = pixel_grid(height, width, like)
        x_distorted = (u[None] - cx) / fx  # [D, H, W]
        y_distorted = (v[None] - cy) / fy
        x, y, valid = undistort(x_distorted, y_distorted, coefficients)
        source_u, source_v = fx * x + cx, fy * y + cy
        # grid_sample with align_corners=False: -1 and +1 are the outer pixel edges, so a pixel
        # position u (centres at i + 0.5) is 2 u / W - 1.
        grid = torch.stack([2 * source_u / width - 1, 2 * source_v / height - 1], dim=-1)
        grid = torch.where(valid[..., None], grid, torch.full_like(grid, -10.0))
        # In the images' precision before it is repeated per view (a float64 grid per view of a
        # supersampled split is as large as the images).
        grid = grid.to(capture.images.dtype)[view_to_distinct]
        stacked = torch.cat([capture.images, capture.alpha], dim=-1).permute(0, 3, 1, 2)
        sampled = torch.nn.functional.grid_sample(
            stacked,
            grid,
            mode="bilinear",
            padding_mode="zeros",
            align_corners=False,
        ).permute(0, 2, 3, 1)
        capture.images = sampled[..., :3].clamp(min=0.0).contiguous()
        capture.alpha = sampled[..., 3:].clamp(0.0, 1.0).contiguous()
        displacement = torch.hypot(source_u - u[None], source_v - v[None])[valid]
        return AppliedEffect(
            self.name,
            {
                **self.parameters,
                "max_displacement_px": round_float(
                    float(displacement.max()) / capture.pixel_scale if displacement.numel() else 0.0
                ),
                "folded_fraction": round_float(
                    1.0 - float(valid[view_to_distinct].double().mean())
                ),
            },
        )


# --------------------------------------------------------------------------------------------
# vignetting
# --------------------------------------------------------------------------------------------

_BISECTION_STEPS = 80


def pupil_transmission(distance: torch.Tensor, barrel_radius: float) -> torch.Tensor:
    """Fraction of a unit-radius entrance pupil inside the barrel's aperture circle.

    Mechanical ("cat's eye") vignetting: seen from an off-axis image point, the lens barrel's
    aperture (radius barrel_radius, in pupil radii) is displaced by distance from the pupil; the
    light passes through the two circles' overlap (the lens-shaped intersection area over pi).
    1 for distance <= R - 1, 0 for distance >= R + 1.
    """
    radius = float(barrel_radius)
    d = distance.clamp(min=1e-12)
    cos_pupil = ((d * d + 1 - radius * radius) / (2 * d)).clamp(-1.0, 1.0)
    cos_barrel = ((d * d + radius * radius - 1) / (2 * d * radius)).clamp(-1.0, 1.0)
    kite = (-d + 1 + radius) * (d + 1 - radius) * (d - 1 + radius) * (d + 1 + radius)
    area = (
        torch.acos(cos_pupil)
        + radius * radius * torch.acos(cos_barrel)
        - 0.5 * torch.sqrt(kite.clamp(min=0.0))
    )
    overlap = area / math.pi
    overlap = torch.where(distance <= radius - 1, torch.ones_like(overlap), overlap)
    overlap = torch.where(distance >= radius + 1, torch.zeros_like(overlap), overlap)
    return overlap.clamp(0.0, 1.0)


@functools.lru_cache(maxsize=64)
def barrel_distance_for_strength(strength: float, barrel_radius: float) -> float:
    """The pupil-barrel separation (pupil radii) at which a fraction strength of the pupil is
    cut off (bisection; pupil_transmission decreases with distance)."""
    low, high = barrel_radius - 1.0, barrel_radius + 1.0
    target = 1.0 - strength
    for _ in range(_BISECTION_STEPS):
        middle = 0.5 * (low + high)
        transmission = float(
            pupil_transmission(torch.tensor(middle, dtype=torch.float64), barrel_radius)
        )
        if transmission > target:
            low = middle
        else:
            high = middle
    return 0.5 * (low + high)


HALF_RADIUS_SAMPLES = 64


class Vignetting(WorldEffect):
    """Optical vignetting: the natural cos^p falloff of the real field angle times an
    off-centre mechanical (barrel) vignetting.

    falloff(u, v) = cos(theta)^cos_power * pupil_transmission(D * rho_m / rho_corner, R), where
    tan(theta) = |((u - cx) / fx, (v - cy) / fy)| (the field angle from the principal point; the
    ideal thin-lens law is cos^4), rho_m the same measured from the mechanical centre
    (cx + offset_x_px, cy + offset_y_px) (a decentred barrel), rho_corner = |(W/2/fx, H/2/fy)|
    and D chosen so that a fraction strength of the pupil is cut at rho_m = rho_corner. The
    mechanical centre offset is a lens property, so it is a parameter (drawn by sample_strength),
    shared by every split. Realised: per-view corner falloff (mean of the four corner pixels over
    the image-centre value) and its natural and mechanical factors, and the offset.
    """

    name = "vignetting"
    stage = "optics"
    PARAMETERS = {
        "cos_power": ParameterSpec(
            4.0, 0.0, 8.0, "exponent of the natural cos falloff (4 = cos^4 law)"
        ),
        "strength": ParameterSpec(
            0.2, 0.0, 0.95, "fraction of the pupil cut by the barrel at the image-corner radius"
        ),
        "barrel_radius": ParameterSpec(
            1.5, 1.0, 5.0, "barrel aperture radius over pupil radius (larger = later onset)"
        ),
        "offset_x_px": ParameterSpec(0.0, -4096.0, 4096.0, "mechanical centre offset, columns"),
        "offset_y_px": ParameterSpec(0.0, -4096.0, 4096.0, "mechanical centre offset, rows"),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """Nominal corner falloff 0.55-0.8 for the given (or nominal) field of view: 40-80 % of
        its log taken by the cos^p law (p <= 8), the rest by the barrel; onset R in [1.2, 2.5];
        mechanical centre offset up to 5 % of the smaller image side."""
        (height, width), _ = nominal_geometry(cameras)
        corner = corner_radius_normalised(cameras)
        target = sample_uniform(generator, 0.55, 0.8)
        natural_share = sample_uniform(generator, 0.4, 0.8)
        power = min(-2.0 * natural_share * math.log(target) / math.log1p(corner**2), 8.0)
        natural = (1.0 + corner**2) ** (-0.5 * power)
        strength = min(max(1.0 - target / natural, 0.0), 0.95)
        offset = sample_uniform(generator, 0.0, 0.05) * min(height, width)
        direction = sample_uniform(generator, 0.0, 2.0 * math.pi)
        return {
            "cos_power": round_float(power),
            "strength": round_float(strength),
            "barrel_radius": round_float(sample_uniform(generator, 1.2, 2.5)),
            "offset_x_px": round_float(offset * math.cos(direction)),
            "offset_y_px": round_float(offset * math.sin(direction)),
        }

    def falloff(
        self, cameras: Cameras, u: torch.Tensor, v: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Natural and mechanical factors [B, ...] at pixel positions u, v [...] (columns, rows)."""
        like = u if u.is_floating_point() else u.double()
        fx, fy, cx, cy = (
            value.reshape(-1, *([1] * u.ndim)) for value in _intrinsics(cameras, like)
        )
        tan_squared = ((u[None] - cx) / fx) ** 2 + ((v[None] - cy) / fy) ** 2
        natural = (1.0 + tan_squared) ** (-0.5 * float(self.parameters["cos_power"]))
        strength = float(self.parameters["strength"])
        if strength == 0.0:
            return natural, torch.ones_like(natural)
        height, width = cameras.image_size
        corner = torch.hypot(0.5 * width / fx, 0.5 * height / fy)
        mechanical_u = (u[None] - cx - float(self.parameters["offset_x_px"])) / fx
        mechanical_v = (v[None] - cy - float(self.parameters["offset_y_px"])) / fy
        radius = float(self.parameters["barrel_radius"])
        separation = barrel_distance_for_strength(strength, radius)
        distance = separation * torch.hypot(mechanical_u, mechanical_v) / corner
        return natural, pupil_transmission(distance, radius)

    def _centre_falloff(
        self, cameras: Cameras, height: int, width: int, like: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Natural and mechanical factors [B, 1] at the image centre (like's dtype and device)."""
        centre = torch.tensor([0.5 * width], dtype=like.dtype, device=like.device)
        middle = torch.tensor([0.5 * height], dtype=like.dtype, device=like.device)
        return self.falloff(cameras, centre, middle)

    def relative_falloff(
        self, cameras: Cameras, u: torch.Tensor, v: torch.Tensor, height: int, width: int
    ) -> torch.Tensor:
        """Total falloff [B, ...] at pixel positions u, v [...] over its value at the centre of
        a height x width image."""
        natural, mechanical = self.falloff(cameras, u, v)
        natural_centre, mechanical_centre = self._centre_falloff(cameras, height, width, u)
        centre = natural_centre * mechanical_centre
        return natural * mechanical / centre.reshape(-1, *([1] * u.ndim))

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] *= falloff [B, H, W]; alpha and cameras unchanged (coverage is
        geometry; vignetting only dims the light)."""
        _, height, width = check_capture(capture, self.name)
        like = torch.empty(0, dtype=torch.float64, device=capture.images.device)
        u, v = pixel_grid(height, width, like)
        natural, mechanical = self.falloff(capture.cameras, u, v)
        capture.images = capture.images * (natural * mechanical).to(capture.images.dtype)[..., None]
        # Corner pixels' centres and the image centre, for the realised falloff ratios.
        corners_u = torch.tensor(
            [0.5, width - 0.5, 0.5, width - 0.5], dtype=torch.float64, device=like.device
        )
        corners_v = torch.tensor(
            [0.5, 0.5, height - 0.5, height - 0.5], dtype=torch.float64, device=like.device
        )
        natural_corners, mechanical_corners = self.falloff(capture.cameras, corners_u, corners_v)
        natural_centre, mechanical_centre = self._centre_falloff(
            capture.cameras, height, width, like
        )
        total = self.relative_falloff(capture.cameras, corners_u, corners_v, height, width)
        # Half-way to the corner (mean round the circle): a centred object covers this radius in
        # every view, unlike the corners, so a model fitted to its pixels can be scored here.
        angles = torch.arange(HALF_RADIUS_SAMPLES, dtype=torch.float64, device=like.device)
        angles = angles * (2.0 * math.pi / HALF_RADIUS_SAMPLES)
        half_radius = 0.25 * math.hypot(height, width)
        circle_u = 0.5 * width + half_radius * torch.cos(angles)
        circle_v = 0.5 * height + half_radius * torch.sin(angles)
        half_radius_falloff = self.relative_falloff(
            capture.cameras, circle_u, circle_v, height, width
        )
        return AppliedEffect(
            self.name,
            {
                "corner_falloff": to_list(total.mean(dim=1)),
                "half_radius_falloff": to_list(half_radius_falloff.mean(dim=1)),
                "natural_corner_falloff": to_list(
                    natural_corners.mean(dim=1) / natural_centre[:, 0]
                ),
                "mechanical_corner_falloff": to_list(
                    mechanical_corners.mean(dim=1) / mechanical_centre[:, 0]
                ),
                "offset_px": [self.parameters["offset_x_px"], self.parameters["offset_y_px"]],
                **{key: self.parameters[key] for key in ("cos_power", "strength", "barrel_radius")},
            },
        )
