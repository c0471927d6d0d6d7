"""Optical image effects: defocus blur, motion blur, lens distortion.

They move light between pixels, so they act on the premultiplied colour and on the alpha alike
(zero padding: outside the frame is black and uncovered, as in the premultiplied render against
a black background).

Blur kernels. A centred blur changes an image to second order in its width, so a width
parameter has no gradient at zero and an optimiser started there never moves. The blurs are
therefore parameterised by their second moments (variance in px^2), to which the image
responds to first order (the heat equation: d image / d variance = Laplacian / 2). The kernel
with covariance C is the discrete analogue of the Gaussian (Lindeberg's discrete Gaussian,
anisotropic), built from its Fourier transform

    K^(w) = exp(-Q(w)),  Q(w) = C_xx (1 - cos w_x) + C_yy (1 - cos w_y) + C_xy sin w_x sin w_y,

by a trapezoid rule over N x N frequencies, which is differentiable in C, exactly the identity
at C = 0 and has second moments C. Only the excess K - delta is built (from expm1), and added to
the image: at zero it is exactly zero, so the effect is bit-exact at zero parameters.

- defocus_blur: one isotropic discrete Gaussian for all views, parameter the variance
  (px^2; sigma = sqrt(variance)). The world uses a pillbox (disk) PSF instead; a disk of radius
  R has the same second moments as a Gaussian of sigma R / 2.
- motion_blur: per view, a Gaussian along a line: C = |w| I + [[p, q], [q, -p]] with
  w = (p, q) (a smooth |w|), whose major variance 2 |w| is that of a uniform segment of length
  L = sqrt(24 |w|) at angle atan2(q, p) / 2, the minor ~ 0. The world uses curved trajectories.
- lens_distortion: radial only, x_distorted = x (1 + k1 r^2 + k2 r^4) in normalised camera
  coordinates (x = (u - cx) / fx), shared by all views; each output pixel samples the rendered
  image at the undistorted position found by fixed-point iteration (see LensDistortion). The
  world uses Brown-Conrady with k3 and tangential terms, inverted by Newton's method.
"""

from __future__ import annotations

import math

import torch

from recon.camera import Cameras
from recon.effects.base import ModelEffect, check_image, to_float, to_list
from recon.errors import ReconError

# Kernel half-width in standard deviations of the widest direction.
_KERNEL_SIGMAS = 3.5


def kernel_half_width(covariance: torch.Tensor, max_half_width: int) -> int:
    """Half-width in taps covering _KERNEL_SIGMAS standard deviations of covariances [B, 2, 2]."""
    with torch.no_grad():
        eigenvalues = torch.linalg.eigvalsh(covariance.detach().double())
        largest = float(eigenvalues.abs().max()) if eigenvalues.numel() else 0.0
    return int(min(max_half_width, math.ceil(_KERNEL_SIGMAS * math.sqrt(largest)) + 1))


def gaussian_excess_kernels(covariance: torch.Tensor, half_width: int) -> torch.Tensor:
    """K - delta [B, k, k] (k = 2 half_width + 1) of discrete Gaussians with covariance [B, 2, 2].

    Tap (row i, column j) is the offset (dx, dy) = (j - half_width, i - half_width) in pixels,
    x along columns, y along rows (down). Exactly zero for C = 0; the taps sum to 0 (mass kept).
    """
    dtype, device = covariance.dtype, covariance.device
    size = 2 * half_width + 1
    # Quadrature points: the periodic image of the kernel repeats every N taps, far beyond
    # the support.
    count = max(16, 4 * half_width + 8)
    frequencies = 2 * math.pi * torch.arange(count, dtype=torch.float64) / count
    offsets = torch.arange(-half_width, half_width + 1, dtype=torch.float64)
    phase = offsets[:, None] * frequencies[None, :]  # [k, N]
    cosine_table = torch.cos(phase).to(device=device, dtype=dtype)
    sine_table = torch.sin(phase).to(device=device, dtype=dtype)
    one_minus_cosine = (1 - torch.cos(frequencies)).to(device=device, dtype=dtype)
    sine = torch.sin(frequencies).to(device=device, dtype=dtype)
    cxx = covariance[:, 0, 0][:, None, None]
    cyy = covariance[:, 1, 1][:, None, None]
    cxy = covariance[:, 0, 1][:, None, None]
    # Q[b, y-frequency, x-frequency]
    quadratic = (
        cxx * one_minus_cosine[None, None, :]
        + cyy * one_minus_cosine[None, :, None]
        + cxy * (sine[None, :, None] * sine[None, None, :])
    )
    excess_spectrum = torch.expm1(-quadratic) / (count * count)
    # K[b, i, j] = sum_{y, x} E[b, y, x] cos(w_y dy_i + w_x dx_j), split into cos and sin parts.
    excess = cosine_table @ excess_spectrum @ cosine_table.T - (
        sine_table @ excess_spectrum @ sine_table.T
    )
    # Truncation drops a tiny tail: put its mass back on the centre tap so the blur keeps the
    # image's total (exactly 0 + 0 at the identity).
    centre = torch.zeros(size, size, dtype=dtype, device=device)
    centre[half_width, half_width] = 1.0
    return excess - excess.sum(dim=(1, 2), keepdim=True) * centre


def convolve_excess(image: torch.Tensor, excess: torch.Tensor) -> torch.Tensor:
    """image [B, H, W, C] + image * (K - delta), per batch entry (excess [1 or B, k, k]).

    Zero padding; the kernels are symmetric, so correlation equals convolution.
    """
    batch, height, width, channels = image.shape
    half_width = excess.shape[-1] // 2
    kernels = excess.to(image).expand(batch, -1, -1)
    weight = kernels[:, None].repeat_interleave(channels, dim=0)  # [B * C, 1, k, k]
    planes = image.permute(0, 3, 1, 2).reshape(1, batch * channels, height, width)
    filtered = torch.nn.functional.conv2d(
        planes, weight, padding=half_width, groups=batch * channels
    )
    return image + filtered.reshape(batch, channels, height, width).permute(0, 2, 3, 1)


def _blur(
    color: torch.Tensor, alpha: torch.Tensor, covariance: torch.Tensor, max_half_width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    half_width = kernel_half_width(covariance, max_half_width)
    excess = gaussian_excess_kernels(covariance, half_width)
    stacked = convolve_excess(torch.cat([color, alpha], dim=-1), excess)
    channels = color.shape[-1]
    return stacked[..., :channels], stacked[..., channels:]


class DefocusBlur(ModelEffect):
    """Isotropic discrete Gaussian blur shared by all views, parameter: variance in px^2.

    The variance is clamped to [-0.25, max_sigma_px^2]: a small negative variance sharpens
    (useful as a signed score when the model is blurrier than the data).
    """

    name = "defocus_blur"
    stage = "image"
    per_view = False
    default_learning_rate = 0.05
    default_lock_fraction = 0.3

    def __init__(self, view_count: int | None = None, max_sigma_px: float = 8.0, **options):
        super().__init__(view_count, **options)
        self.max_sigma_px = float(max_sigma_px)
        self.variance = torch.nn.Parameter(torch.zeros(()))

    def effective_variance(self) -> torch.Tensor:
        return self.variance.clamp(-0.25, self.max_sigma_px**2)

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        check_image(color, alpha, self.name)
        variance = self.effective_variance().to(color)
        covariance = (variance * torch.eye(2, dtype=color.dtype, device=color.device))[None]
        return _blur(color, alpha, covariance, math.ceil(_KERNEL_SIGMAS * self.max_sigma_px) + 1)

    def parameters_summary(self) -> dict:
        variance = float(self.effective_variance().detach())
        sigma = math.sqrt(max(variance, 0.0))
        return {
            "sigma_px": to_float(sigma),
            "variance_px2": to_float(variance),
            "equivalent_disk_radius_px": to_float(2 * sigma),
        }


# Smoothing of |w| at 0 in px^2 (keeps the isotropic part differentiable there).
_LINE_EPSILON = 0.05


class MotionBlur(ModelEffect):
    """Per-view blur along a line, parameters w_v = (p, q) in px^2 per view.

    Covariance C = (sqrt(|w|^2 + eps^2) - eps) I + [[p, q], [q, -p]]: major variance ~ 2 |w|
    along the angle atan2(q, p) / 2, minor ~ 0. A uniform segment of length L has variance
    L^2 / 12, so L = sqrt(24 |w|). No view is pinned (a blur is no gauge).
    """

    name = "motion_blur"
    stage = "image"
    per_view = True
    default_learning_rate = 0.05
    default_lock_fraction = 0.3

    def __init__(self, view_count: int, max_length_px: float = 24.0, **options) -> None:
        super().__init__(view_count, **options)
        self.max_length_px = float(max_length_px)
        self.line = torch.nn.Parameter(torch.zeros(self.view_count, 2))

    def covariances(self) -> torch.Tensor:
        """[V, 2, 2] per-view covariances in px^2."""
        line = self.masked(self.line)
        p, q = line.unbind(-1)
        isotropic = torch.sqrt(p * p + q * q + _LINE_EPSILON**2) - _LINE_EPSILON
        return torch.stack(
            [torch.stack([isotropic + p, q], -1), torch.stack([q, isotropic - p], -1)], -2
        )

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch = check_image(color, alpha, self.name)[0]
        covariance = self.select_views(self.covariances(), view_indices, batch).to(color)
        max_sigma = self.max_length_px / math.sqrt(12.0)
        return _blur(color, alpha, covariance, math.ceil(_KERNEL_SIGMAS * max_sigma) + 1)

    def parameters_summary(self) -> dict:
        with torch.no_grad():
            covariance = self.covariances().double()
            eigenvalues = torch.linalg.eigvalsh(covariance)  # ascending
            line = self.masked(self.line).double()
            angles = 0.5 * torch.rad2deg(torch.atan2(line[:, 1], line[:, 0])) % 180.0
            lengths = torch.sqrt(12.0 * eigenvalues[:, 1].clamp(min=0.0))
        return {
            "lengths_px": to_list(lengths),
            "angles_deg": to_list(angles),
            "minor_sigma_px": to_list(eigenvalues[:, 0].clamp(min=0.0).sqrt()),
            "angle_convention": "from +column toward +row (image down), modulo 180",
        }


class LensDistortion(ModelEffect):
    """Radial distortion x_d = x (1 + k1 r^2 + k2 r^4), normalised coordinates, all views.

    Each output pixel (distorted position x_d) samples the rendered (ideal) image bilinearly at
    x = x_d / (1 + k1 |x|^2 + k2 |x|^4), solved by `iterations` fixed-point steps from x = x_d.
    One step is exact to first order in k (error ~ k1^2 r^5); three (the default) bring the error
    to ~k1^4 r^9, below 0.01 px for |k1| r^2 < 0.2 at 128 px. The result is written as
    image + sample(x) - sample(x_d) so it is bit-exact at zero (grid_sample rounds at pixel
    centres). Outside the frame is black and uncovered.
    """

    name = "lens_distortion"
    stage = "image"
    per_view = False
    default_learning_rate = 0.005
    default_lock_fraction = 0.3

    def __init__(self, view_count: int | None = None, iterations: int = 3, **options) -> None:
        super().__init__(view_count, **options)
        if int(iterations) < 1:
            raise ReconError(f"effect {self.name}: iterations must be >= 1, got {iterations}")
        self.iterations = int(iterations)
        self.coefficients = torch.nn.Parameter(torch.zeros(2))  # (k1, k2)
        # Corner radius (normalised) of the last cameras seen, for the summary's pixel shift.
        self._last_geometry: tuple[float, float] | None = None

    def source_offsets(
        self, cameras: Cameras, height: int, width: int, like: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel offsets (du, dv) [B, H, W] from each output pixel to where it samples."""
        intrinsics = cameras.intrinsics.to(device=like.device, dtype=like.dtype)
        fx, fy, cx, cy = (
            intrinsics[:, row, column][:, None, None]
            for row, column in ((0, 0), (1, 1), (0, 2), (1, 2))
        )
        columns = torch.arange(width, device=like.device, dtype=like.dtype) + 0.5
        rows = torch.arange(height, device=like.device, dtype=like.dtype) + 0.5
        x_distorted = (columns[None, None, :] - cx) / fx
        y_distorted = (rows[None, :, None] - cy) / fy
        k1, k2 = self.coefficients.to(like).unbind()
        x, y = x_distorted, y_distorted
        for _ in range(self.iterations):
            squared = x * x + y * y
            # Past the fold of strong barrel distortion the radial factor would reach 0.
            radial = (1 + squared * (k1 + k2 * squared)).clamp(min=0.1)
            x, y = x_distorted / radial, y_distorted / radial
        return fx * (x - x_distorted), fy * (y - y_distorted)

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch, height, width = check_image(color, alpha, self.name)
        if cameras is None or len(cameras) != batch:
            raise ReconError(f"effect {self.name}: needs the {batch} cameras of the batch")
        self._remember_geometry(cameras, height, width)
        du, dv = self.source_offsets(cameras, height, width, color)
        columns = torch.arange(width, device=color.device, dtype=color.dtype) + 0.5
        rows = torch.arange(height, device=color.device, dtype=color.dtype) + 0.5
        # grid_sample, align_corners=False: -1 and +1 are the outer pixel edges, so pixel
        # position u (centres at i + 0.5) is 2 u / W - 1.
        base_x = (2 * columns / width - 1)[None, None, :].expand(batch, height, width)
        base_y = (2 * rows / height - 1)[None, :, None].expand(batch, height, width)
        grid = torch.stack([base_x + 2 * du / width, base_y + 2 * dv / height], dim=-1)
        base_grid = torch.stack([base_x, base_y], dim=-1)
        channels = color.shape[-1]
        stacked = torch.cat([color, alpha], dim=-1).permute(0, 3, 1, 2)
        options = {"mode": "bilinear", "padding_mode": "zeros", "align_corners": False}
        sampled = torch.nn.functional.grid_sample(stacked, grid, **options)
        at_centres = torch.nn.functional.grid_sample(stacked, base_grid, **options)
        result = (stacked + (sampled - at_centres)).permute(0, 2, 3, 1)
        return result[..., :channels], result[..., channels:]

    def _remember_geometry(self, cameras: Cameras, height: int, width: int) -> None:
        intrinsics = cameras.intrinsics[0].detach().double().cpu()
        fx, fy, cx, cy = (float(intrinsics[r, c]) for r, c in ((0, 0), (1, 1), (0, 2), (1, 2)))
        corner_x = max(cx, width - cx) / fx
        corner_y = max(cy, height - cy) / fy
        self._last_geometry = (math.hypot(corner_x, corner_y), fx)

    def parameters_summary(self) -> dict:
        k1, k2 = (float(value) for value in self.coefficients.detach())
        summary = {
            "k1": to_float(k1),
            "k2": to_float(k2),
            "model": "x_distorted = x (1 + k1 r^2 + k2 r^4), normalised coordinates",
        }
        if self._last_geometry is not None:
            corner, focal = self._last_geometry
            squared = corner * corner
            # Radial shift of the ideal corner point, in pixels (positive = outward).
            summary["corner_radius_normalised"] = to_float(corner)
            summary["corner_shift_px"] = to_float(focal * corner * squared * (k1 + k2 * squared))
        return summary
