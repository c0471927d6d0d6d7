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

Two things besides a tone curve bend the ratio between the two renders, and both are left out:

- The fitted light's own error. Where the fit got the first light's balance wrong (too weak a
  sun and too much ambient, say), the albedo absorbed S_true1 / S_fit1 = 1 + (dA + dB c) / S_fit1
  (c the sun's cosine), a function of the normal, and it shows under the second light as a
  ratio that also grows with the shading (without this factor, clean spot fits read it as an
  exponent of 1.08-1.11).
  The test's two fits (gamma free and gamma at 1) both divide that factor out with dA and dB
  fitted: whatever function of the first light's shading the albedo absorbed, a tone curve
  also makes the ratio depend on the *second* light's shading s2, and that is what the test
  credits. (The reported exponent comes from a third fit without the factor; see below.)
- Cast shadows. A shadow the model lacks moves with the light, and its edge changes the ratio
  as well as any curve. Pixels where the fitted mesh blocks more than diagnose.relight_shadowed_share of either
  light (recon.effects.light_transport.vertex_light_visibility, worst vertex of the pixel's
  triangle) are left out.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.gauss_newton import GaussNewtonProblem
from recon.diagnose.which import block_halves, bootstrap_reduction
from recon.effects.light_transport import dominant_light, vertex_light_visibility
from recon.effects.photometric import ResponseCurve
from recon.render.shading import Lighting, lambertian

# Below this rendered value (linear, under either light) the shading ratio is not defined: the
# prediction keeps R2.
DARK = 1e-3


class RelightResponse(torch.nn.Module):
    """g_vc R1 (R2 / R1)^gamma / (1 + t . b(n)) for B relight views: the ResponseCurve's
    exponent, a gain per view and channel, and the first light's error t (all the identity at
    zero).
    light_basis: [B, H, W, K] the first light's error shapes over its shading (light_error_basis).
    Duck-types what GaussNewtonProblem reads."""

    name = "relight_response"
    per_view = True
    learning_rate = 0.02
    learning_rate_scales: dict[str, float] = {}

    def __init__(
        self,
        light_basis: torch.Tensor,
        fit_gamma: bool = True,
        image_basis: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        self.view_count = light_basis.shape[0]
        self.log_gain = torch.nn.Parameter(torch.zeros(self.view_count, 3))
        self.light_basis = light_basis
        # [B, H, W, 3, K] first-order changes of the relight render (render_laplacian: a
        # blur's), K strengths per view; None: none.
        self.image_basis = image_basis
        count = 0 if image_basis is None else image_basis.shape[-1]
        self.image_strength = torch.nn.Parameter(
            torch.zeros(self.view_count, count), requires_grad=image_basis is not None
        )
        self.light_error = torch.nn.Parameter(torch.zeros(light_basis.shape[-1]))
        self.response = ResponseCurve()
        self.response.lut.requires_grad_(False)
        self.response.log_gamma.requires_grad_(fit_gamma)

    def forward(self, under_fitted: torch.Tensor, under_relight: torch.Tensor) -> torch.Tensor:
        """[B, H, W, 3] prediction from the fitted scene under its own light (R1) and under the
        relight split's light (R2)."""
        gamma = self.response.log_gamma.exp()
        # Both renders must be lit: a fitted SH light can go slightly negative on a few normals,
        # and a negative ratio has no real power.
        lit = (under_fitted > DARK) & (under_relight > DARK)
        ratio = torch.where(
            lit, under_relight / under_fitted.clamp_min(DARK), torch.ones_like(under_fitted)
        )
        curved = torch.where(lit, under_fitted * ratio.pow(gamma), under_relight)
        # The fitted albedo holds S_true1 / S_fit1 = 1 + t . b: divided out (kept positive).
        light_error = (self.light_basis.to(curved) * self.light_error.to(curved)).sum(-1)
        absorbed = (1 + light_error[..., None]).clamp_min(0.1)
        prediction = curved * self.log_gain.exp()[:, None, None, :] / absorbed
        if self.image_basis is not None:
            strength = self.image_strength[:, None, None, None, :].to(curved)
            prediction = prediction + (strength * self.image_basis.to(curved)).sum(-1)
        return prediction


def render_laplacian(rendered: torch.Tensor) -> torch.Tensor:
    """[B, H, W, 3, 1] the 5-point Laplacian of a render [B, H, W, 3] (edges replicated): a
    blur by a kernel of variance s^2 adds s^2 / 2 times it, to first order. (A shift's first
    order, the render's gradients, was tried beside it: on the blind check's stored fits it
    raised the clean fits' compression, docs/decisions/0212-response-curve-relight.md.)"""
    batch, height, width, channels = rendered.shape
    planes = rendered.permute(0, 3, 1, 2).reshape(batch * channels, 1, height, width)
    padded = torch.nn.functional.pad(planes, (1, 1, 1, 1), mode="replicate")
    kernel = torch.tensor(
        [[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]], dtype=rendered.dtype
    ).to(rendered.device)
    laplacian = torch.nn.functional.conv2d(padded, kernel[None, None])
    return laplacian.reshape(batch, channels, height, width).permute(0, 2, 3, 1)[..., None]


def _fit(
    module: RelightResponse,
    under_fitted: torch.Tensor,
    relight: DiagnosisData,
    first: torch.Tensor,
    second: torch.Tensor,
    settings: DiagnoseConfig,
) -> torch.Tensor:
    """Fit on the first half (diagnose.relight_iterations); squared error on the second, per
    tile of diagnose.relight_tile_pixels [B * tiles]. The bootstrap resamples tiles (across all
    views), not views: the exponent is one number for every view, and a relight split has few
    views, whose own misfit would widen a per-view interval far beyond what the curve changes."""
    trainable = [module]
    problem = GaussNewtonProblem(
        trainable,
        lambda: module(under_fitted, relight.rendered),
        relight.observed,
        first * relight.region,
    )
    problem.fit(settings.relight_iterations)
    with torch.no_grad():
        prediction = module(under_fitted, relight.rendered)
    squared = ((prediction - relight.observed) ** 2 * second * relight.region).sum(-1)
    # Sums per tile of every view [B * tiles]: the bootstrap's units.
    tile = settings.relight_tile_pixels
    tiles = torch.nn.functional.avg_pool2d(squared[:, None], tile, ceil_mode=True)
    return tiles.flatten()


def light_error_basis(normals: torch.Tensor, lighting: Lighting) -> torch.Tensor:
    """[B, H, W, 2] the shapes of an error in `lighting`'s balance: its ambient level and its
    dominant light's strength (recon.effects.light_transport.dominant_light: the brightest sun's
    clamped cosine, or the SH linear band's cosine), each over the light's luminance irradiance
    E(n). normals: [B, H, W, 3] (0 on background, where the basis is 0).

    Only the light's own components: a new direction (a free linear band, say) would contain the
    second light's shading too, and with it most of what a curve changes."""
    lighting = lighting.detached()
    weights = torch.tensor([0.2126, 0.7152, 0.0722], dtype=normals.dtype, device=normals.device)
    # E(n): the lambertian shading of a white albedo, times pi.
    irradiance = (lambertian(torch.ones_like(normals), normals, lighting) * math.pi * weights).sum(
        -1
    )
    direction, _ = dominant_light(lighting)
    cosine = (normals * direction.to(normals)).sum(-1)
    if lighting.directional:
        cosine = cosine.clamp_min(0.0)
    covered = normals.abs().sum(-1) > 0
    # Normals that only a weak ambient reaches would blow the ratio up; a tenth of the mean
    # irradiance bounds it.
    floor = 0.1 * irradiance[covered].mean() if bool(covered.any()) else torch.ones(())
    scale = torch.where(covered, 1.0 / irradiance.clamp_min(floor), torch.zeros_like(irradiance))
    return torch.stack([torch.ones_like(cosine), cosine], dim=-1) * scale[..., None]


def unshadowed(
    relight: DiagnosisData, fitted_lighting: Lighting, shadowed_share: float
) -> torch.Tensor:
    """[B, H, W, 1] 1 where the fitted mesh blocks at most shadowed_share (config
    diagnose.relight_shadowed_share) of the fitted light
    and of the relight split's light at every vertex of the pixel's triangle (background: 1)."""
    mesh = relight.mesh
    visible = torch.minimum(
        vertex_light_visibility(mesh.verts, mesh.faces, fitted_lighting),
        vertex_light_visibility(mesh.verts, mesh.faces, relight.lighting),
    )
    triangle = relight.triangle_id
    corners = visible[mesh.faces[triangle.clamp(min=0)]].min(dim=-1).values  # [B, H, W]
    keep = (triangle < 0) | (corners >= 1 - shadowed_share)
    return keep.to(relight.region)[..., None]


def off_terminator(relight: DiagnosisData, cosines: list[float]) -> torch.Tensor:
    """[B, H, W, 1] 0 where the fitted normal's cosine to the relight light's dominant direction
    (recon.effects.light_transport.dominant_light) lies strictly between cosines[0] and
    cosines[1] (config diagnose.relight_grazing_cosines), 1 elsewhere (background: 1).

    Near that light's terminator the predicted shading under it moves fastest with the normal
    (under a sun of irradiance I over an ambient A, d log s / d n reaches I / A there, against
    I / (A + I) facing the sun): the fitted normals' error scatters the predicted ratio most
    there, and a regression on a scattered predictor comes out flatter than the truth
    (regression dilution), which reads as a compressive exponent on clean fits."""
    direction, _ = dominant_light(relight.lighting)
    cosine = (relight.normals * direction.to(relight.normals)).sum(-1)
    low, high = cosines
    grazing = (relight.triangle_id >= 0) & (cosine > low) & (cosine < high)
    return (~grazing).to(relight.region)[..., None]


def _tile_sums(values: torch.Tensor, tile: int) -> torch.Tensor:
    """[B, H, W, C, K] summed over tiles of tile x tile pixels -> [B, T, C, K] (the image is
    padded with zeros to whole tiles)."""
    batch, height, width, channels, count = values.shape
    rows, columns = -(-height // tile), -(-width // tile)
    padded = torch.nn.functional.pad(
        values, (0, 0, 0, 0, 0, columns * tile - width, 0, rows * tile - height)
    )
    tiled = padded.reshape(batch, rows, tile, columns, tile, channels, count)
    return tiled.sum(dim=(2, 4)).reshape(batch, rows * columns, channels, count)


def exponent_interval(
    module: RelightResponse,
    under_fitted: torch.Tensor,
    relight: DiagnosisData,
    settings: DiagnoseConfig,
    seed: int = 0,
) -> tuple[float, float]:
    """90 % bootstrap interval of a fitted RelightResponse's exponent (its light error held),
    over tiles of diagnose.relight_tile_pixels of all views (as the reduction's), by one
    linearised Gauss-Newton step per resample with each view's nuisances (its three gains and
    its blur strength) profiled out: each tile adds its sums of J_n J_n^T, J_n J_e, J_e^2,
    J_n r and J_e r (n the view's nuisances, e the log exponent), and a resample's step is
    -sum_v (g_e - m^T N^-1 g_n) / sum_v (C - m^T N^-1 m). Cheap (no refit per resample) and
    exact to first order about the fit."""
    with torch.no_grad():
        prediction = module(under_fitted, relight.rendered).double()
        lit = (under_fitted > DARK) & (relight.rendered > DARK)
        ratio = torch.where(
            lit, relight.rendered / under_fitted.clamp_min(DARK), torch.ones_like(under_fitted)
        ).double()
        gamma = float(module.response.log_gamma.exp())
        if module.image_basis is None:
            image_slope = torch.zeros(*prediction.shape, 0, dtype=torch.float64)
        else:
            image_slope = module.image_basis.double()
        strength = module.image_strength.detach().double()[:, None, None, None, :]
        scaled = prediction - (strength * image_slope).sum(-1)  # the gained, curved render
        # d prediction / d (log gain of channel c, image strengths) per pixel and channel:
        # [B, H, W, 3, 3 + K].
        nuisance = torch.cat([torch.diag_embed(scaled), image_slope], dim=-1)
        exponent_slope = scaled * gamma * ratio.log()  # d prediction / d log gamma
        residual = (prediction - relight.observed.double()) * relight.region.double()
        nuisance = nuisance * relight.region.double()[..., None]
        exponent_slope = exponent_slope * relight.region.double()
        stacked = torch.cat(
            [
                (nuisance[..., :, None] * nuisance[..., None, :]).flatten(-2),
                nuisance * exponent_slope[..., None],
                nuisance * residual[..., None],
                torch.stack([exponent_slope**2, exponent_slope * residual], dim=-1),
            ],
            dim=-1,
        ).sum(dim=-2, keepdim=True)  # summed over channels: [B, H, W, 1, N^2 + 2 N + 2]
        sums = _tile_sums(stacked, settings.relight_tile_pixels)[:, :, 0]  # [B, T, ...]
        size = nuisance.shape[-1]
        batch, tiles = sums.shape[:2]
        generator = torch.Generator().manual_seed(seed)
        picks = torch.randint(
            0, batch * tiles, (settings.bootstrap_samples, batch * tiles), generator=generator
        )
        counts = torch.zeros(settings.bootstrap_samples, batch * tiles, dtype=torch.float64)
        counts.scatter_add_(1, picks, torch.ones_like(picks, dtype=torch.float64))
        grouped = torch.einsum("sbt,btk->sbk", counts.reshape(-1, batch, tiles), sums)
        square = size * size
        normal = grouped[..., :square].reshape(*grouped.shape[:2], size, size)
        # An unused nuisance (a channel nowhere lit) keeps its row solvable.
        normal = normal + 1e-12 * torch.eye(size, dtype=torch.float64)
        mixed = grouped[..., square : square + size]
        nuisance_gradient = grouped[..., square + size : square + 2 * size]
        curvature_own, gradient_own = grouped[..., -2], grouped[..., -1]
        solved = torch.linalg.solve(normal, torch.stack([mixed, nuisance_gradient], dim=-1))
        curvature = (curvature_own - (mixed * solved[..., 0]).sum(-1)).sum(-1)
        gradient = (gradient_own - (mixed * solved[..., 1]).sum(-1)).sum(-1)
        exponents = gamma * torch.exp(-gradient / curvature.clamp_min(1e-20))
        return float(torch.quantile(exponents, 0.05)), float(torch.quantile(exponents, 0.95))


def relight_response_probe(
    relight: DiagnosisData,
    under_fitted: torch.Tensor,
    fitted_lighting: Lighting,
    settings: DiagnoseConfig,
    seed: int = 0,
) -> dict:
    """relight: the relight split rendered under its own light (rendered = R2); under_fitted:
    the same views rendered under the fitted light (R1) [B, H, W, 3]; fitted_lighting: the
    fit's light (its error shapes, and the cast shadows of both lights). Returns
    {"lower_bound": the evidence's statistic, the compression 1 - gamma's 90 % lower bound
    (with diagnose.relight_compressive_only False, the larger of it and the expansion's),
    "compression", "compression_interval", "reduction", "interval" (the held-out error the
    exponent removes, with the light-error factor), "parameters": {"gamma", "effective_gamma",
    "gamma_with_light_error"}, "expanding": whether the exponent exceeds 1, "specific": whether
    the reduction's lower bound is positive (else the lower bound is at most 0)}."""
    batch, height, width, _ = relight.observed.shape
    first, second = block_halves(
        batch, height, width, relight.observed.device, settings.block_pixels
    )
    shadowed_share = settings.relight_shadowed_share
    relight = replace(
        relight,
        region=relight.region
        * unshadowed(relight, fitted_lighting, shadowed_share)
        * off_terminator(relight, settings.relight_grazing_cosines),
    )
    light_basis = light_error_basis(relight.normals, fitted_lighting)
    fixed = RelightResponse(light_basis, fit_gamma=False)
    baseline = _fit(fixed, under_fitted, relight, first, second, settings)
    tested = RelightResponse(light_basis)
    curved = _fit(tested, under_fitted, relight, first, second, settings)
    # A camera's response compresses (exponent below 1 on the shading ratio); an expanding fit
    # is light the diffuse model lacks where the relight render is bright (a highlight under
    # the relight sun), not a curve: the one-sided fit then sits at gamma = 1 and removes
    # nothing (diagnose.relight_compressive_only).
    if bool(tested.response.log_gamma.detach() > 0) and settings.relight_compressive_only:
        curved = baseline
    reduction, interval = bootstrap_reduction(baseline, curved, settings.bootstrap_samples, seed)
    # The evidence is the exponent itself, fitted on every kept pixel without the light-error
    # factor (a power law of s2 / s1 is in part a function of s1: with the factor free the
    # exponent is pinned by s2 alone and comes out low even on clean fits; recorded as
    # gamma_with_light_error) and beside a blur strength per view (a defocus smooths the
    # observed ratio: diagnose.relight_blur_nuisance). Its interval is the run's own null.
    image_basis = render_laplacian(relight.rendered) if settings.relight_blur_nuisance else None
    estimate = RelightResponse(light_basis[..., :0], image_basis=image_basis)
    _fit(estimate, under_fitted, relight, first + second, torch.zeros_like(first), settings)
    gamma = float(estimate.response.log_gamma.detach().exp())
    low, high = exponent_interval(estimate, under_fitted, relight, settings, seed)
    lower_bound = 1.0 - high
    if not settings.relight_compressive_only:
        lower_bound = max(lower_bound, low - 1.0)
    # Specific to the camera: the first light's balance, which the training views cannot pin
    # (each texel is seen under one light), bends the ratio too, and a fit with too strong a
    # sun reads as an exponent below 1. Only an exponent that removes held-out error beyond
    # that balance (the reduction above, fitted with the light-error factor free) is credited.
    specific = interval[0] > 0
    if not specific:
        lower_bound = min(lower_bound, 0.0)
    return {
        "lower_bound": lower_bound,
        "compression": 1.0 - gamma,
        "compression_interval": [1.0 - high, 1.0 - low],
        "reduction": reduction,
        "interval": list(interval),
        "parameters": {
            "gamma": gamma,
            "effective_gamma": gamma,
            "gamma_with_light_error": float(tested.response.log_gamma.detach().exp()),
        },
        "expanding": gamma > 1.0,
        "specific": specific,
    }
