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
"""

from __future__ import annotations

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.agreement import surface_angles
from recon.diagnose.data import DiagnosisData
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


def gain_evidence(data: DiagnosisData, settings: DiagnoseConfig) -> Evidence:
    """The exposure's per-view gains read apart from the highlight (details["parameters"]:
    ratios and stops, each normalised by their geometric mean, as the probe reports them); it
    informs the exposure's recovered parameters, not its significance."""
    log_gains, coefficients = highlight_free_log_gains(
        data, settings.exposure_highlight_powers, settings.exposure_gain_iterations
    )
    centred = log_gains - log_gains.mean()
    spread = float(centred.pow(2).mean().sqrt())
    reason = (
        f"exposure: per-view gains read apart from a highlight lobe in n.h (powers "
        f"{list(settings.exposure_highlight_powers)}), RMS {100 * spread:.1f} % over "
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
                "estimator": "highlight_free",
            },
            "lobe_coefficients": coefficients.tolist(),
            "powers": list(settings.exposure_highlight_powers),
        },
    )
