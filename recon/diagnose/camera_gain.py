"""The camera's per-view gain (an exposure) read apart from a highlight the base model lacks.

A per-view gain fitted to the held-out views (the exposure probe's) takes whatever makes a view
brighter than the model: the camera's exposure, and on a glossy object also the highlight the
diffuse model cannot render, since views differ in how much of it they show. Its ratios are then
off by the highlight's share (a glossy torus: 6-13 % median, 20-29 % at worst; the path tracer's
glossy spot 2 % median, 17 % at worst; docs/decisions/0207-white-balance-exposure.md).

An exposure multiplies everything the camera sees, the highlight included; a highlight adds
light where n.h is high, the same function of n.h in every view. So the observation is modelled

    observed[v, p, c] = gain[v] * (rendered[v, p, c] + sum_k lobe[k, c] * (n.h[v, p])^power[k])

with one gain per view and lobe coefficients per channel shared by the views (n.h against the
fitted light's main direction, as recon.diagnose.pixel_table measures it), fitted by alternating
least squares over the object's pixels (each step is linear). The gains are the camera's,
whatever lobe the views show; with no highlight the lobe coefficients stay near 0 and the gains
are the least-squares per-view gains.

Both models share the mismatch across views; a misfit that one view alone shows (a highlight or a
region the fit got wrong there) moves that view's least-squares gain. diagnose.exposure_gain_estimator
'robust_regions' reads the gains instead from regions (cells of the pixel table's factors, e.g. a
surface region seen at a camera-frame normal): log gain[view, region] = gain[view] + mismatch[region]
+ misfit, the mismatch shared by the views (under a light that turns with the camera, everything
the light does follows the camera-frame normal), fitted by iteratively reweighted least squares
with Tukey's biweight, so a (view, region) cell that disagrees with the rest has no weight; the
regions' gains are read against the render plus the shared highlight lobe fitted above
(docs/decisions/0219-real-exposure.md).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.agreement import surface_angles
from recon.diagnose.data import DiagnosisData
from recon.diagnose.pixel_table import GainModels, pixel_table
from recon.diagnose.records import Evidence

KIND = "gain"


def highlight_free_log_gains(
    data: DiagnosisData, powers: list[int], iterations: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(log gains [B], lobe coefficients [K, 3]) of the model in the module docstring, fitted on
    the region's pixels of data's views."""
    # The region's pixels alone, packed [N, ...] (a sixth to a third of the image).
    inside = data.region[..., 0] > 0
    view = inside.nonzero()[:, 0]
    observed, rendered = data.observed[inside].double(), data.rendered[inside].double()
    n_dot_h, _ = surface_angles(data)
    n_dot_h, coverage = n_dot_h[inside], data.rendered_alpha[..., 0][inside].double()
    lobes = torch.stack([n_dot_h.clamp_min(0.0).pow(power) * coverage for power in powers], -1)
    views = data.view_count
    gains = torch.ones(views, dtype=torch.float64)
    coefficients = torch.zeros(len(powers), 3, dtype=torch.float64)

    def per_view_sum(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros(views, 3, dtype=torch.float64).index_add_(0, view, values).sum(-1)

    for _ in range(iterations):
        predicted = rendered + lobes @ coefficients
        energy = per_view_sum(predicted * predicted).clamp_min(1e-30)
        gains = (per_view_sum(observed * predicted) / energy).clamp_min(1e-12)
        gain = gains.index_select(0, view)[:, None]
        design = gain * lobes  # [N, K]
        target = observed - gain * rendered  # [N, 3]
        if design.shape[0] <= len(powers):
            break
        coefficients = torch.linalg.lstsq(design, target).solution
    return gains.log(), coefficients


def with_highlight(
    data: DiagnosisData, powers: list[int], coefficients: torch.Tensor
) -> DiagnosisData:
    """data whose renders [B, H, W, 3] carry the shared highlight lobe highlight_free_log_gains
    fitted (coefficients [K, 3]): the model the regions' gains are read against."""
    n_dot_h, _ = surface_angles(data)
    coverage = data.rendered_alpha[..., 0].double()
    lobes = torch.stack([n_dot_h.clamp_min(0.0).pow(power) * coverage for power in powers], -1)
    rendered = data.rendered.double() + lobes @ coefficients
    return replace(data, rendered=rendered.to(data.rendered.dtype))


def region_log_gains(
    data: DiagnosisData, factors: list[str], tukey: float, iterations: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(log gains [B], weights [cells]) of the 'robust_regions' model in the module docstring
    (weights NaN on cells without rendered light, which take no part):
    each (view, region) cell's least-squares luminance gain over all its pixels, weighted by its
    rendered energy (the information about it) times Tukey's biweight of its residual in robust
    standard deviations (1.4826 times the cells' median absolute residual)."""
    table = pixel_table(data)
    models = GainModels(table, ["view", *factors], all_pixels=True)
    energy = models.weight.sum(dim=1)
    cross = (models.log_gain.exp() * models.weight).sum(dim=1)
    lit = energy > 0
    target = torch.log(cross[lit].clamp_min(1e-30) / energy[lit])
    view = models.levels["view"][lit]
    region = torch.zeros_like(view)
    for name in factors:
        region = region * (int(models.levels[name].max()) + 1) + models.levels[name][lit]
    region = torch.unique(region, return_inverse=True)[1]
    views = data.view_count
    # One column per view, one per region but the first (the overall scale is the views').
    design = torch.cat(
        [
            torch.nn.functional.one_hot(view, views).double(),
            torch.nn.functional.one_hot(region, int(region.max()) + 1).double()[:, 1:],
        ],
        dim=1,
    )
    information = energy[lit] / energy[lit].max()
    robust = torch.ones_like(target)
    solution = torch.zeros(design.shape[1], dtype=torch.float64)
    for _ in range(iterations):
        root = (information * robust).sqrt()
        solution = torch.linalg.lstsq(
            design * root[:, None], target * root, driver="gelsd"
        ).solution
        residual = target - design @ solution
        scale = 1.4826 * float(residual.abs().median()) + 1e-12
        robust = (1 - (residual / (tukey * scale)) ** 2).clamp_min(0.0) ** 2
    weights = torch.full_like(energy, float("nan"))
    weights[lit] = robust
    return solution[:views], weights


def gain_evidence(data: DiagnosisData, settings: DiagnoseConfig) -> Evidence:
    """The exposure's per-view gains read apart from the highlight (details["parameters"]:
    ratios and stops, each normalised by their geometric mean, as the probe reports them); it
    informs the exposure's recovered parameters, not its significance."""
    log_gains, coefficients = highlight_free_log_gains(
        data, settings.exposure_highlight_powers, settings.exposure_gain_iterations
    )
    how = f"apart from a highlight lobe in n.h (powers {list(settings.exposure_highlight_powers)})"
    estimator, extra = "highlight_free", {}
    if settings.exposure_gain_estimator == "robust_regions":
        factors = list(settings.exposure_region_factors)
        # Against the model with the views' shared highlight: what is left is one view's own.
        lobed = with_highlight(data, settings.exposure_highlight_powers, coefficients)
        log_gains, weights = region_log_gains(
            lobed, factors, settings.exposure_region_tukey, settings.exposure_gain_iterations
        )
        estimator = "robust_regions"
        rejected = float((weights[~weights.isnan()] == 0).double().mean())
        how = (
            f"from regions ({' x '.join(factors)}) with a mismatch shared by the views, "
            f"{100 * rejected:.0f} % of the (view, region) cells rejected as misfit"
        )
        extra = {"region_factors": factors, "rejected_cells": rejected}
    centred = log_gains - log_gains.mean()
    spread = float(centred.pow(2).mean().sqrt())
    reason = (
        f"exposure: per-view gains read {how}, RMS {100 * spread:.1f} % over "
        f"{data.view_count} views"
    )
    return Evidence(
        kind=KIND,
        candidate="exposure",
        statistic=spread,
        threshold=0.0,
        passed=True,
        reason=reason,
        details={
            "parameters": {
                "ratios": [float(value) for value in centred.exp()],
                "stops": [float(value) for value in centred / torch.log(torch.tensor(2.0))],
                "estimator": estimator,
            },
            "lobe_coefficients": coefficients.tolist(),
            "powers": list(settings.exposure_highlight_powers),
            **extra,
        },
    )
