"""Optical image effects: defocus blur, motion blur, lens distortion.

They move light between pixels, so they act on the premultiplied colour and on the alpha alike
(zero padding: outside the frame is black and uncovered, as in the premultiplied render against
a black background).

Blur kernels. A centred blur changes an image to second order in its width, so a width
parameter has no gradient at zero and an optimiser started there never moves. The blurs are
therefore parameterised by their second moments (variance in px^2), to which the image
responds to first order (the heat equation: d image / d variance = Laplacian / 2). The kernel
with covariance C is the discrete analogue of the Gaussian (Lindeberg's discrete Gaussian,
made anisotropic), defined by its transfer function

    K^(w) = exp(-Q(w)),  Q(w) = C_xx (1 - cos w_x) + C_yy (1 - cos w_y) + C_xy sin w_x sin w_y,

and applied by FFT on the zero-padded image: differentiable in C, exactly the identity at C = 0,
second moments exactly C. Only the excess K^ - 1 (from expm1) filters the image and is added to
it: at zero it is exactly zero, so the effect is bit-exact at zero parameters.

- defocus_blur: one isotropic discrete Gaussian for all views, parameter the variance
  (px^2; sigma = sqrt(variance)). The world uses a pillbox (disk) PSF instead; a disk of radius
  R has the same second moments as a Gaussian of sigma R / 2.
- motion_blur: per view, a Gaussian along a line: C = |w| I + [[p, q], [q, -p]] with
  w = (p, q) (a smooth |w|), whose major variance 2 |w| is that of a uniform segment of length
  L = sqrt(24 |w|) at angle atan2(q, p) / 2, the minor ~ 0. The world uses curved trajectories.
- lens_distortion: radial only, x_distorted = x (1 + k1 r^2 + k2 r^4) in normalised camera
  coordinates (x = (u - cx) / fx), shared by all views; each output pixel samples the rendered
  image at the undistorted position found by Newton's method (see LensDistortion). The
  world uses Brown-Conrady with k3 and tangential terms, inverted by Newton's method.
"""

from __future__ import annotations

import math
import weakref

import torch

from recon.camera import Cameras
from recon.effects.base import ModelEffect, check_image, to_float, to_list
from recon.effects.facts import DiagnosisFacts
from recon.errors import ReconError

# Zero padding of the FFT blur, in standard deviations of the widest direction.
_KERNEL_SIGMAS = 3.5


def blur_padding(covariance: torch.Tensor, max_padding: int) -> int:
    """Zero padding in pixels covering _KERNEL_SIGMAS standard deviations of the widest
    direction of covariances [B, 2, 2] (the FFT's wrap-around stays outside the image)."""
    with torch.no_grad():
        eigenvalues = torch.linalg.eigvalsh(covariance.detach().double())
        largest = float(eigenvalues.abs().max()) if eigenvalues.numel() else 0.0
    return int(min(max_padding, math.ceil(_KERNEL_SIGMAS * math.sqrt(largest)) + 1))


def gaussian_transfer_excess(covariance: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """expm1(-Q(w)) [B, height, width // 2 + 1] on the rfft2 frequency grid of a
    height x width image: the discrete Gaussian's transfer function minus 1 (exactly 0 at C = 0).

    Q(w) = C_xx (1 - cos w_x) + C_yy (1 - cos w_y) + C_xy sin w_x sin w_y, x along columns.
    """
    dtype, device = covariance.dtype, covariance.device
    frequency_y = 2 * math.pi * torch.fft.fftfreq(height, dtype=dtype, device=device)
    frequency_x = 2 * math.pi * torch.fft.rfftfreq(width, dtype=dtype, device=device)
    cxx = covariance[:, 0, 0][:, None, None]
    cyy = covariance[:, 1, 1][:, None, None]
    cxy = covariance[:, 0, 1][:, None, None]
    quadratic = (
        cxx * (1 - torch.cos(frequency_x))[None, None, :]
        + cyy * (1 - torch.cos(frequency_y))[None, :, None]
        + cxy * (torch.sin(frequency_y)[:, None] * torch.sin(frequency_x)[None, :])[None]
    )
    return torch.expm1(-quadratic)


def fft_size(minimum: int) -> int:
    """The smallest 2^a 3^b 5^c >= minimum: fast FFT lengths, and few distinct ones, so the
    FFT plans are reused while a blur's width changes during a fit."""
    size = max(1, int(minimum))
    while True:
        remainder = size
        for factor in (2, 3, 5):
            while remainder % factor == 0:
                remainder //= factor
        if remainder == 1:
            return size
        size += 1


def gaussian_blur(
    image: torch.Tensor,
    covariance: torch.Tensor,
    max_padding: int,
    spectra: dict | None = None,
) -> torch.Tensor:
    """image [B, H, W, C] convolved with discrete Gaussians of covariance [1 or B, 2, 2] (px^2).

    Computed as image + irfft2(rfft2(padded image) x expm1(-Q)) on the image zero-padded by at
    least blur_padding on every side (the FFT is circular; the padding keeps the wrap-around
    off the image): bit-exact at C = 0, differentiable in C and in the image, O(HW log HW)
    whatever the blur's size.

    spectra: the padded image's rfft2 by padding, kept for a caller that blurs this same image
    again with other covariances (without gradients: a Gauss-Newton probe's Jacobian).
    """
    batch, height, width, channels = image.shape
    padding = blur_padding(covariance, max_padding)
    padded_height = fft_size(height + 2 * padding)
    padded_width = fft_size(width + 2 * padding)
    key = (padding, padded_height, padded_width)
    if spectra is not None and key in spectra:
        image_spectrum = spectra[key]
    else:
        planes = torch.nn.functional.pad(
            image.permute(0, 3, 1, 2),
            (padding, padded_width - width - padding, padding, padded_height - height - padding),
        )
        image_spectrum = torch.fft.rfft2(planes)
        if spectra is not None:
            spectra[key] = image_spectrum
    transfer = gaussian_transfer_excess(covariance.to(image), padded_height, padded_width)
    spectrum = image_spectrum * transfer[:, None]
    excess = torch.fft.irfft2(spectrum, s=(padded_height, padded_width))
    excess = excess[..., padding : padding + height, padding : padding + width]
    return image + excess.permute(0, 2, 3, 1)


# Paddings whose image spectra a blur module keeps for its last input (a few FFT sizes).
_KEPT_SPECTRA = 4


def _blur(
    color: torch.Tensor,
    alpha: torch.Tensor,
    covariance: torch.Tensor,
    max_padding: int,
    keeper: ModelEffect | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """color [B, H, W, C] and alpha [B, H, W, 1] blurred alike. keeper: the blur module; without
    gradients it keeps the spectra of the last colour and alpha it blurred (the same tensors,
    unchanged: identity and version), which a probe's Jacobian blurs again and again with
    other covariances (the same values as computing them anew)."""
    spectra = None
    if keeper is not None and not torch.is_grad_enabled():
        versions = (color._version, alpha._version)
        kept = getattr(keeper, "_kept_spectra", None)
        if kept is None or kept[0]() is not color or kept[1]() is not alpha or kept[2] != versions:
            kept = (weakref.ref(color), weakref.ref(alpha), versions, {})
            keeper._kept_spectra = kept
        spectra = kept[3]
    elif keeper is not None:
        keeper._kept_spectra = None
    stacked = gaussian_blur(torch.cat([color, alpha], dim=-1), covariance, max_padding, spectra)
    if spectra is not None and len(spectra) > _KEPT_SPECTRA:
        # The oldest padding goes (dicts keep insertion order); a kept one is never dropped
        # before it is asked for again.
        spectra.pop(next(iter(spectra)))
    channels = color.shape[-1]
    return stacked[..., :channels], stacked[..., channels:]


class DefocusBlur(ModelEffect):
    """Isotropic discrete Gaussian blur shared by all views, parameter: variance in px^2.

    The variance is clamped to [-0.25, max_sigma_px^2]: a small negative variance sharpens
    (useful as a signed score when the model is blurrier than the data).
    """

    name = "defocus_blur"
    diagnosis = DiagnosisFacts(
        family="camera",
        confusable=("motion_blur", "lens_distortion"),
        identifiable_when="sharp texture or silhouette edges in every view",
    )
    stage = "image"
    per_view = False
    default_learning_rate = 0.1
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
        max_padding = math.ceil(_KERNEL_SIGMAS * self.max_sigma_px) + 1
        return _blur(color, alpha, covariance, max_padding, self)

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
    diagnosis = DiagnosisFacts(
        family="camera",
        probe_start=("line", 0.5),
        confusable=("defocus_blur", "lens_distortion", "pose_error"),
        identifiable_when="sharp edges in several directions in every view",
    )
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
        return _blur(color, alpha, covariance, math.ceil(_KERNEL_SIGMAS * max_sigma) + 1, self)

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

    Each output pixel (distorted position x_d, radius r_d) samples the rendered (ideal) image
    bilinearly at x = t x_d, where the radial scale t solves t (1 + k1 r_d^2 t^2 +
    k2 r_d^4 t^4) = 1 by `iterations` Newton steps from t = 1 (quadratic convergence: four
    steps leave < 1e-6 px for displacements of tens of pixels; autograd through the steps gives
    the implicit-function gradient). The result is written as image + sample(x) - sample(x_d)
    so it is bit-exact at zero (grid_sample rounds at pixel centres). Outside the frame is
    black and uncovered.

    Parameters (alpha, beta): 1 + k1 r^2 + k2 r^4 = 1 + alpha p^2 + beta (p^4 - 0.75 p^2) with
    p = r / reference_radius (about the corner radius of a 50-60 degree camera): orthogonal
    over the disc p <= 1 and of order one there, so the optimiser sees two decorrelated,
    equally scaled directions instead of the nearly collinear k1, k2.
    """

    name = "lens_distortion"
    diagnosis = DiagnosisFacts(
        family="camera",
        evidence=("absorption", "line_target"),
        absorption="geometry",
        confusable=("motion_blur", "defocus_blur", "pose_error"),
        identifiable_when="straight edges or texture reaching the outer image",
    )
    stage = "image"
    per_view = False
    default_learning_rate = 0.01
    default_lock_fraction = 0.3

    def __init__(
        self,
        view_count: int | None = None,
        iterations: int = 4,
        reference_radius: float = 0.5,
        **options,
    ) -> None:
        super().__init__(view_count, **options)
        if int(iterations) < 1:
            raise ReconError(f"effect {self.name}: iterations must be >= 1, got {iterations}")
        if not reference_radius > 0:
            raise ReconError(
                f"effect {self.name}: reference_radius must be positive, got {reference_radius}"
            )
        self.iterations = int(iterations)
        self.reference_radius = float(reference_radius)
        self.coefficients = torch.nn.Parameter(torch.zeros(2))  # (alpha, beta)
        # Corner radius (normalised) and focal length of the last cameras seen, for the
        # summary's pixel shift.
        self._last_geometry: tuple[float, float] | None = None

    def radial_coefficients(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(k1, k2) of x_d = x (1 + k1 r^2 + k2 r^4)."""
        alpha, beta = self.coefficients.unbind()
        reference = self.reference_radius**2
        return (alpha - 0.75 * beta) / reference, beta / (reference * reference)

    def set_radial_coefficients(self, k1: float, k2: float = 0.0) -> None:
        """Set the parameters so that the model is x_d = x (1 + k1 r^2 + k2 r^4)."""
        reference = self.reference_radius**2
        beta = k2 * reference * reference
        with torch.no_grad():
            self.coefficients.copy_(torch.tensor([k1 * reference + 0.75 * beta, beta]))

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
        scale = self._radial_scale(x_distorted, y_distorted, like)
        return fx * x_distorted * (scale - 1), fy * y_distorted * (scale - 1)

    def _radial_scale(
        self, x_distorted: torch.Tensor, y_distorted: torch.Tensor, like: torch.Tensor
    ) -> torch.Tensor:
        """The radial scale t of each distorted position (normalised coordinates, broadcast)."""
        k1, k2 = (value.to(like) for value in self.radial_coefficients())
        squared = x_distorted * x_distorted + y_distorted * y_distorted
        quadratic, quartic = k1 * squared, k2 * squared * squared
        scale = torch.ones_like(squared)
        for _ in range(self.iterations):
            scale_squared = scale * scale
            residual = scale * (1 + scale_squared * (quadratic + quartic * scale_squared)) - 1
            slope = 1 + scale_squared * (3 * quadratic + 5 * quartic * scale_squared)
            # Past the fold of strong barrel distortion the slope would reach 0.
            scale = (scale - residual / slope.clamp(min=0.1)).clamp(0.1, 10.0)
        return scale

    def sample_grids(
        self,
        cameras: Cameras,
        height: int,
        width: int,
        view: torch.Tensor,
        row: torch.Tensor,
        column: torch.Tensor,
        like: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """forward's sampling positions at chosen pixels only: (grid, base grid) [..., 2] in
        grid_sample's coordinates, for pixels of batch entry view, at integer row and column
        (tensors of one shape). Each element is the same arithmetic as in forward's whole
        grids, so grid_sample at these positions gives forward's values there (the
        diagnosis' Gauss-Newton probes count a sixth of the pixels)."""
        intrinsics = cameras.intrinsics.to(device=like.device, dtype=like.dtype)
        fx, fy, cx, cy = (
            intrinsics[:, index_row, index_column][view]
            for index_row, index_column in ((0, 0), (1, 1), (0, 2), (1, 2))
        )
        columns = column.to(like.dtype) + 0.5
        rows = row.to(like.dtype) + 0.5
        x_distorted = (columns - cx) / fx
        y_distorted = (rows - cy) / fy
        scale = self._radial_scale(x_distorted, y_distorted, like)
        du, dv = fx * x_distorted * (scale - 1), fy * y_distorted * (scale - 1)
        base_x = 2 * columns / width - 1
        base_y = 2 * rows / height - 1
        grid = torch.stack([base_x + 2 * du / width, base_y + 2 * dv / height], dim=-1)
        return grid, torch.stack([base_x, base_y], dim=-1)

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
        k1, k2 = (float(value.detach()) for value in self.radial_coefficients())
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
