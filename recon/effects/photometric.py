"""Photometric image effects: exposure, white balance, vignetting, response curve.

All act on the rendered linear image, premultiplied against a black background (the render's
colour composited over background 0), pixel by pixel; alpha is unchanged.

Parameterisations (all zero = identity), each simpler than its world counterpart:

- exposure: a per-view log gain g_v, colour *= exp(g_v); view 0 pinned (exposure x light gauge).
- white_balance: per-view log gains for red and blue, green fixed (the channel the exposure
  already scales), colour *= exp([r_v, 0, b_v]); view 0 pinned (white balance x light colour).
- vignetting: an even radial polynomial 1 + a r^2 + b r^4 about the principal point, r the
  distance in pixels over the half image diagonal (r = 1 at the corners of a centred camera),
  optimised in an orthogonal basis of the disc.
- response_curve: observed = y + D(y) with y = x^gamma, gamma = exp(log_gamma), and D a
  piecewise-linear deviation on 16 uniform knots of [0, 1] whose values come from positive
  increments exp(lut): a monotone curve with f(0) = 0 and f(1) = 1 (the scale stays with
  exposure and light), applied to linear values (observed linear ~ true linear^gamma).
"""

from __future__ import annotations

import math

import torch

from recon.camera import Cameras
from recon.effects.base import ModelEffect, check_image, to_float, to_list
from recon.effects.facts import DiagnosisFacts
from recon.errors import ReconError


class Exposure(ModelEffect):
    """Per-view exposure: colour [B, H, W, C] *= exp(log_gain[view])."""

    name = "exposure"
    diagnosis = DiagnosisFacts(
        family="camera",
        confusable=("white_balance", "view_dependent_reflectance"),
        identifiable_when="views whose exposure differs, of surfaces whose reflectance does not change with the view",
        gain_signature=True,
    )
    stage = "image"
    pixelwise = True
    per_view = True
    pins_a_view = True
    default_learning_rate = 0.02
    default_lock_fraction = 0.2

    def __init__(self, view_count: int, **options) -> None:
        super().__init__(view_count, **options)
        self.log_gain = torch.nn.Parameter(torch.zeros(self.view_count))

    def log_gains(self) -> torch.Tensor:
        """[V] effective log gains (the pinned view 0)."""
        return self.masked(self.log_gain)

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch = check_image(color, alpha, self.name)[0]
        gains = self.select_views(self.log_gains(), view_indices, batch).exp()
        return color * gains.to(color)[:, None, None, None], alpha

    def parameters_summary(self) -> dict:
        log_gains = self.log_gains()
        return {
            "ratios": to_list(log_gains.exp()),
            "stops": to_list(log_gains / math.log(2.0)),
            "pinned_view": self.pinned_view,
        }


class WhiteBalance(ModelEffect):
    """Per-view red and blue gains, green fixed: colour [B, H, W, 3] *= exp([r, 0, b])."""

    name = "white_balance"
    diagnosis = DiagnosisFacts(
        family="camera",
        confusable=("exposure", "view_dependent_reflectance"),
        identifiable_when="views whose colour balance differs (one view pins the gauge)",
        gain_signature=True,
    )
    stage = "image"
    pixelwise = True
    per_view = True
    pins_a_view = True
    default_learning_rate = 0.02
    default_lock_fraction = 0.2

    def __init__(self, view_count: int, **options) -> None:
        super().__init__(view_count, **options)
        # Columns: log red gain, log blue gain.
        self.log_red_blue = torch.nn.Parameter(torch.zeros(self.view_count, 2))

    def log_gains(self) -> torch.Tensor:
        """[V, 3] effective log gains (R, G = 0, B), the pinned view all zero."""
        red_blue = self.masked(self.log_red_blue)
        return torch.stack([red_blue[:, 0], torch.zeros_like(red_blue[:, 0]), red_blue[:, 1]], -1)

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch = check_image(color, alpha, self.name)[0]
        if color.shape[-1] != 3:
            raise ReconError(
                f"effect {self.name}: expected 3 colour channels, got {color.shape[-1]}"
            )
        gains = self.select_views(self.log_gains(), view_indices, batch).exp()
        return color * gains.to(color)[:, None, None, :], alpha

    def parameters_summary(self) -> dict:
        return {
            "gains": to_list(self.log_gains().exp()),
            "channels": ["red", "green", "blue"],
            "pinned_view": self.pinned_view,
        }


def normalised_radius(
    cameras: Cameras, height: int, width: int, like: torch.Tensor
) -> torch.Tensor:
    """Distance of each pixel centre from the principal point over the half diagonal [B, H, W]."""
    intrinsics = cameras.intrinsics.to(device=like.device, dtype=like.dtype)
    cx = intrinsics[:, 0, 2][:, None, None]
    cy = intrinsics[:, 1, 2][:, None, None]
    rows = torch.arange(height, device=like.device, dtype=like.dtype) + 0.5
    columns = torch.arange(width, device=like.device, dtype=like.dtype) + 0.5
    half_diagonal = 0.5 * math.hypot(height, width)
    dx = (columns[None, None, :] - cx) / half_diagonal
    dy = (rows[None, :, None] - cy) / half_diagonal
    return torch.sqrt(dx * dx + dy * dy)


class Vignetting(ModelEffect):
    """Radial falloff shared by all views: colour *= 1 + a r^2 + b r^4.

    r: pixel distance from the principal point over the half image diagonal. Needs cameras
    (principal point, image size). The parameters are (alpha, beta) with
    a = alpha - 0.75 beta, b = beta: r^2 and r^4 - 0.75 r^2 are orthogonal over the unit disc,
    which decorrelates the two for the optimiser (r^2 and r^4 alone are nearly collinear).
    """

    name = "vignetting"
    diagnosis = DiagnosisFacts(
        family="camera",
        evidence=("absorption", "flat_field"),
        absorption="closed_form",
        radial_falloff=True,
        confusable=("response_curve", "view_dependent_reflectance"),
        identifiable_when="the object reaching the image corners, or flat-field frames",
        gain_signature=True,
    )
    stage = "image"
    per_view = False
    default_learning_rate = 0.02
    default_lock_fraction = 0.2

    def __init__(self, view_count: int | None = None, **options) -> None:
        super().__init__(view_count, **options)
        self.coefficients = torch.nn.Parameter(torch.zeros(2))  # (alpha, beta)

    def set_polynomial(self, a: float, b: float = 0.0) -> None:
        """Set the parameters so that the gain is 1 + a r^2 + b r^4."""
        with torch.no_grad():
            self.coefficients.copy_(torch.tensor([a + 0.75 * b, b]))

    def polynomial(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(a, b) of 1 + a r^2 + b r^4."""
        alpha, beta = self.coefficients.unbind()
        return alpha - 0.75 * beta, beta

    def falloff(self, radius: torch.Tensor) -> torch.Tensor:
        """The gain 1 + a r^2 + b r^4 at normalised radii [...]."""
        squared = radius * radius
        alpha, beta = self.coefficients.to(radius).unbind()
        return 1 + squared * (alpha + beta * (squared - 0.75))

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch, height, width = check_image(color, alpha, self.name)
        if cameras is None or len(cameras) != batch:
            raise ReconError(
                f"effect {self.name}: needs the {batch} cameras of the batch (principal points)"
            )
        gain = self.falloff(normalised_radius(cameras, height, width, color))
        return color * gain[..., None], alpha

    def parameters_summary(self) -> dict:
        a, b = (float(value.detach()) for value in self.polynomial())
        return {
            "corner_falloff": to_float(1 + a + b),
            "half_radius_falloff": to_float(1 + a / 4 + b / 16),
            "a": to_float(a),
            "b": to_float(b),
            "radius_unit": "half image diagonal from the principal point",
        }


_LUT_KNOTS = 16
_EFFECTIVE_EXPONENT_RANGE = (0.05, 0.9)


class ResponseCurve(ModelEffect):
    """A monotone tone curve on linear values: observed = y + D(y), y = x^gamma.

    gamma = exp(log_gamma); D: piecewise linear on knots k / K (K = 16) with values
    cumsum(exp(lut))[k] / sum(exp(lut)) - k / K, so y + D(y) is monotone from 0 to 1 on
    [0, 1] (D = 0 above 1 and below 0). Shared by all views and channels. Writing the curve as
    y + D(y) keeps it bit-exact at zero parameters (D is exactly 0 there).
    """

    name = "response_curve"
    diagnosis = DiagnosisFacts(
        family="camera",
        evidence=("relight", "line_target_levels"),
        relight_exponent=True,
        confusable=("lens_distortion", "exposure"),
        identifiable_when="views under a second light (a relight split) or with varying exposure",
        gain_signature=True,
    )
    stage = "image"
    pixelwise = True
    per_view = False
    default_learning_rate = 0.03
    default_lock_fraction = 0.2
    # The LUT moves slower so the single exponent takes the bulk of a power-law response first.
    learning_rate_scales = {"lut": 0.1}

    def __init__(self, view_count: int | None = None, knots: int = _LUT_KNOTS, **options) -> None:
        super().__init__(view_count, **options)
        if int(knots) < 2:
            raise ReconError(f"effect {self.name}: knots must be >= 2, got {knots}")
        self.log_gamma = torch.nn.Parameter(torch.zeros(()))
        self.lut = torch.nn.Parameter(torch.zeros(int(knots)))
        # (values, gamma, powered, index, fraction) of the last curve() without autograd: the
        # diagnosis' Gauss-Newton Jacobian moves one LUT entry at a time over the same image,
        # and x^gamma and its segments are most of a curve's cost.
        self._segments: tuple | None = None

    def deviation_values(self) -> torch.Tensor:
        """D at the knots 0, 1/K, ..., 1 [K + 1] (zero at both ends)."""
        increments = self.lut.exp()
        cumulative = torch.cumsum(increments, 0) / increments.sum()
        count = self.lut.shape[0]
        knots = torch.arange(1, count + 1, dtype=self.lut.dtype, device=self.lut.device) / count
        # Equal increments give cumsum k and k / K exactly, so the deviation is exactly zero.
        return torch.cat([self.lut.new_zeros(1), cumulative - knots])

    def curve(self, values: torch.Tensor) -> torch.Tensor:
        """observed linear for true linear values [...] (negatives map to 0)."""
        gamma = self.log_gamma.exp().to(values)
        deviation = self.deviation_values().to(values)
        count = deviation.shape[0] - 1
        powered, index, fraction = self._segments_of(values, gamma, count)
        # The segment slopes at the knots, then one flat gather each per pixel (the same values
        # as indexing both ends per pixel, at half the cost: the diagnosis' probe renders this
        # curve about a hundred times).
        slopes = deviation[1:] - deviation[:-1]
        return powered + deviation.take(index) + slopes.take(index) * fraction

    def _segments_of(
        self, values: torch.Tensor, gamma: torch.Tensor, count: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x^gamma of values [...], its LUT segment index and the fraction along it; reused
        without autograd when values and gamma equal the last call's (an exact reuse: the same
        inputs give the same numbers)."""
        cached = self._segments
        reuse = (
            not torch.is_grad_enabled()
            and cached is not None
            and cached[0].shape == values.shape
            and cached[0].dtype == values.dtype
            and cached[0].device == values.device
            and bool(cached[1] == gamma)
            and torch.equal(cached[0], values)
        )
        if reuse:
            return cached[2], cached[3], cached[4]
        positive = values > 0
        safe = torch.where(positive, values, torch.ones_like(values))
        # The double where keeps the gradient finite at 0 (0^gamma's slope and log 0).
        powered = torch.where(positive, safe.pow(gamma), torch.zeros_like(values))
        scaled = powered.clamp(0.0, 1.0) * count
        index = scaled.detach().floor().clamp(max=count - 1).long()
        fraction = scaled - index.to(values)
        if torch.is_grad_enabled():
            self._segments = None
        else:
            self._segments = (values.clone(), gamma.clone(), powered, index, fraction)
        return powered, index, fraction

    def forward(
        self,
        color: torch.Tensor,
        alpha: torch.Tensor,
        cameras: Cameras | None = None,
        view_indices: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        check_image(color, alpha, self.name)
        return self.curve(color), alpha

    def hold_exponent(self, gamma: float) -> None:
        """Set the exponent to gamma and keep it there (its gradient stops; the LUT stays free):
        for a refit whose training views, all under one light, cannot pin the exponent while
        another measurement (the relight probe) has."""
        if not gamma > 0:
            raise ReconError(f"effect {self.name}: held exponent must be > 0, got {gamma}")
        with torch.no_grad():
            self.log_gamma.fill_(math.log(gamma))
        self.log_gamma.requires_grad_(False)

    def effective_exponent(self) -> float:
        """k of the least-squares fit log f(E) = k log E over E in [0.05, 0.9]: comparable with
        the world's effective_exponent (1 for the identity)."""
        with torch.no_grad():
            exposure = torch.linspace(*_EFFECTIVE_EXPONENT_RANGE, 200, dtype=torch.float64)
            observed = self.double_curve(exposure).clamp(min=1e-12)
            log_exposure, log_observed = exposure.log(), observed.log()
            return float((log_exposure * log_observed).sum() / (log_exposure**2).sum())

    def double_curve(self, values: torch.Tensor) -> torch.Tensor:
        """curve() evaluated in float64 on the CPU (for summaries)."""
        values = values.to(device=self.lut.device, dtype=torch.float64)
        return self.curve(values).cpu()

    def parameters_summary(self) -> dict:
        true_linear = torch.linspace(0.0, 1.0, 33, dtype=torch.float64)
        with torch.no_grad():
            observed = self.double_curve(true_linear)
            mid_grey = self.double_curve(torch.tensor([0.18], dtype=torch.float64))
        return {
            "gamma": to_float(self.log_gamma.detach().exp()),
            "effective_gamma": to_float(self.effective_exponent()),
            "mid_grey_observed": to_float(mid_grey[0]),
            "table": {"true_linear": to_list(true_linear), "observed_linear": to_list(observed)},
        }
