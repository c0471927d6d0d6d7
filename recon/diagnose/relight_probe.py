"""The response-curve probe on a relight split: the one place a tone curve cannot hide.

Under one light a monotone response f on a Lambertian image is absorbed by the albedo (and the
light): every texel's radiance is one number, whatever curve maps it. A relight split shows the
same surface under a second, known light. If the camera applied f, the fitted scene holds
R1 = f(a s1) per surface point (its render under the fitted light) while the camera records
f(a s2) under the new light. With f(x) = x^gamma that is

    f(f^-1(R1) s2 / s1) = R1 (R2 / R1)^gamma,     R2 = the fitted scene under the new light,

since R2 / R1 = s2 / s1 for the same albedo. gamma = 1 (no curve) gives back R2. The probe fits
the ResponseCurve module's exponent (its LUT stays at zero) and one gain per view and channel
(the albedo x light gauge, and any per-view exposure or white balance), on one half of each
relight view's pixel blocks, and measures the held-out reduction on the other half against the
same fit with gamma held at 1, bootstrapped over 16-pixel tiles of all views.
"""

from __future__ import annotations

import torch

from recon.diagnose.data import DiagnosisData
from recon.diagnose.gauss_newton import GaussNewtonProblem
from recon.diagnose.which import block_halves, bootstrap_reduction
from recon.effects.photometric import ResponseCurve

# Below this rendered value (linear) the shading ratio is not defined: the prediction keeps R2.
DARK = 1e-3
ITERATIONS = 6
# The bootstrap resamples image tiles of this size (across all views), not views: the exponent
# is one number for every view, and a relight split has few views (8 in the benchmark), whose
# own misfit would widen a per-view interval far beyond what the curve changes.
TILE_PIXELS = 16


class RelightResponse(torch.nn.Module):
    """g_vc R1 (R2 / R1)^gamma for B relight views: the ResponseCurve's exponent and a gain per
    view and channel (both the identity at zero). Duck-types what GaussNewtonProblem reads."""

    name = "relight_response"
    per_view = True
    learning_rate = 0.02
    learning_rate_scales: dict[str, float] = {}

    def __init__(self, view_count: int, fit_gamma: bool = True) -> None:
        super().__init__()
        self.view_count = view_count
        self.log_gain = torch.nn.Parameter(torch.zeros(view_count, 3))
        self.response = ResponseCurve()
        self.response.lut.requires_grad_(False)
        self.response.log_gamma.requires_grad_(fit_gamma)

    def forward(self, under_fitted: torch.Tensor, under_relight: torch.Tensor) -> torch.Tensor:
        """[B, H, W, 3] prediction from the fitted scene under its own light (R1) and under the
        relight split's light (R2)."""
        gamma = self.response.log_gamma.exp()
        lit = under_fitted > DARK
        ratio = torch.where(
            lit, under_relight / under_fitted.clamp_min(DARK), torch.ones_like(under_fitted)
        )
        curved = torch.where(lit, under_fitted * ratio.pow(gamma), under_relight)
        return curved * self.log_gain.exp()[:, None, None, :]


def _fit(
    module: RelightResponse,
    under_fitted: torch.Tensor,
    relight: DiagnosisData,
    first: torch.Tensor,
    second: torch.Tensor,
) -> torch.Tensor:
    """Fit on the first half; squared error on the second, per tile [B * tiles]."""
    trainable = [module]
    problem = GaussNewtonProblem(
        trainable,
        lambda: module(under_fitted, relight.rendered),
        relight.observed,
        first * relight.region,
    )
    problem.fit(ITERATIONS)
    with torch.no_grad():
        prediction = module(under_fitted, relight.rendered)
    squared = ((prediction - relight.observed) ** 2 * second * relight.region).sum(-1)
    # Sums per TILE_PIXELS tile of every view [B * tiles]: the bootstrap's units.
    tiles = torch.nn.functional.avg_pool2d(squared[:, None], TILE_PIXELS, ceil_mode=True)
    return tiles.flatten()


def relight_response_probe(
    relight: DiagnosisData, under_fitted: torch.Tensor, seed: int = 0
) -> dict:
    """relight: the relight split rendered under its own light (rendered = R2); under_fitted:
    the same views rendered under the fitted light (R1) [B, H, W, 3]. Returns {"reduction",
    "interval", "parameters": {"gamma", "effective_gamma"}}."""
    batch, height, width, _ = relight.observed.shape
    first, second = block_halves(batch, height, width, relight.observed.device)
    baseline = _fit(RelightResponse(batch, fit_gamma=False), under_fitted, relight, first, second)
    module = RelightResponse(batch)
    curved = _fit(module, under_fitted, relight, first, second)
    reduction, interval = bootstrap_reduction(baseline, curved, seed)
    gamma = float(module.response.log_gamma.detach().exp())
    return {
        "reduction": reduction,
        "interval": list(interval),
        "parameters": {"gamma": gamma, "effective_gamma": gamma},
    }
