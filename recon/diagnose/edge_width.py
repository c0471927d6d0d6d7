"""How wide the silhouette's edges are in the data, by direction: defocus or motion blur?

The blur probes (recon.diagnose.which) compare renders of the fitted model, blurred, with the
data. Where the fit's own silhouette is off by a pixel (the path-traced teapot at 48 px) any
blur reduces that misfit, and a per-view line blur imitates it better still: on the clean
teapot the motion probe recovers 2.5-4.5 px lines in every view, longer than the 1-3 px motion
blur injected elsewhere, and a defocus and a motion blur cannot be told apart by what they
remove (decision 0213). The width of the data's edges does not depend on where the fitted
edge lies: a blur widens the data's alpha matte across each edge by the blur's spread along
the edge's normal, a misplaced fitted edge widens nothing.

Per view, each pixel on an edge of the observed alpha (central-difference gradient magnitude
above ``gradient_minimum``) gives a local width ``alpha (1 - alpha) / |grad alpha|`` (px; a
step smoothed by a Gaussian of spread s has width s / sqrt(pi) by this measure) at the angle
theta of its gradient. A weighted least-squares fit ``width(theta) = a + b cos 2 theta +
c sin 2 theta`` (weights |grad alpha|) gives the view's mean width ``a`` and its anisotropy
``(b, c)``: a blur along the direction phi widens the edges whose normal points along phi, so
(b, c) points at 2 phi.

- widening: the observed mean width less the fitted render's (the renderer's antialiasing);
- the isotropic reference: the fitted render's alpha blurred by the isotropic Gaussian whose
  mean width matches the observed (bisection on the variance): what an isotropic blur of these
  very silhouettes shows, pixel grid and curvature included; it is this run's null;
- anisotropy: per view |(b, c)_observed - (b, c)_reference| over the view's widening (median
  over views); the null's the same for the reference against the sharp render
  (|(b, c)_reference - (b, c)_render| over its widening, largest over views). The edges are
  anisotropic when the observed median exceeds ``anisotropy_margin`` times the null.

Evidence (kind "edges", decision row "edges", role inform) on defocus_blur and motion_blur,
passed for the one the edges' shape favours (details["favours"]). It settles a tie of the two
blur probes only (recon.diagnose.geometric_judgement: both clear alone and neither separates
from the other on top of it): there the one the edges favour is named and the other vetoed; a
pair the probes separate is left to them. It needs a matte with soft edges: data whose alpha
is binary (a hand-made mask, or a renderer without antialiasing) or missing carry no width,
and no evidence is produced.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from recon.config.run_config import DiagnoseConfig, GeometricSpecificityConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.records import Candidate, Evidence
from recon.effects.optics import gaussian_blur

if TYPE_CHECKING:  # producers imports this module to register the producer
    from recon.diagnose.producers import EvidenceInputs

KIND = "edges"
DEFOCUS = "defocus_blur"
MOTION = "motion_blur"
# Bisection steps of the reference's variance (px^2): 2^-14 of the bracket, 0.001 px^2.
_BISECTION_STEPS = 14
_LARGEST_VARIANCE = 16.0


def edge_profile(alpha: torch.Tensor, gradient_minimum: float) -> torch.Tensor:
    """[B, 3] per view the coefficients (a, b, c) of width(theta) = a + b cos 2 theta +
    c sin 2 theta, fitted by weighted least squares to the local edge widths of alpha
    [B, H, W, 1] (alpha (1 - alpha) / |grad alpha| at pixels with |grad alpha| above
    gradient_minimum, weights |grad alpha|); NaN rows for views with fewer than 3 edge pixels."""
    matte = alpha[..., 0].double().clamp(0.0, 1.0)
    gradient_y = torch.zeros_like(matte)
    gradient_x = torch.zeros_like(matte)
    gradient_y[:, 1:-1, :] = (matte[:, 2:, :] - matte[:, :-2, :]) / 2
    gradient_x[:, :, 1:-1] = (matte[:, :, 2:] - matte[:, :, :-2]) / 2
    magnitude = torch.sqrt(gradient_x**2 + gradient_y**2)
    angle = torch.atan2(gradient_y, gradient_x)
    width = matte * (1 - matte) / magnitude.clamp_min(1e-12)
    # Weighted normal equations per view, summed over its edge pixels (no loop over views).
    weight = torch.where(magnitude > gradient_minimum, magnitude, torch.zeros_like(magnitude))
    design = torch.stack([torch.ones_like(angle), torch.cos(2 * angle), torch.sin(2 * angle)], -1)
    normal = torch.einsum("bhwi,bhw,bhwj->bij", design, weight, design)
    right = torch.einsum("bhwi,bhw,bhw->bi", design, weight, width)
    counts = (weight > 0).sum(dim=(1, 2))
    ridge = 1e-12 * torch.eye(3, dtype=normal.dtype)
    solution = torch.linalg.solve(normal + ridge, right[..., None])[..., 0]
    return torch.where((counts >= 3)[:, None], solution, torch.full_like(solution, math.nan))


def isotropic_reference(
    rendered_alpha: torch.Tensor, target_width: float, gradient_minimum: float
) -> tuple[torch.Tensor, float]:
    """The edge profile [B, 3] of rendered_alpha [B, H, W, 1] blurred by the isotropic discrete
    Gaussian whose mean width over views matches target_width (bisection on the variance), and
    that variance (px^2; 0 when the render is as wide already)."""
    sharp = rendered_alpha.double()

    def profile(variance: float) -> torch.Tensor:
        if variance <= 0:
            return edge_profile(sharp, gradient_minimum)
        covariance = variance * torch.eye(2, dtype=torch.float64)[None]
        padding = math.ceil(3.5 * math.sqrt(_LARGEST_VARIANCE)) + 1
        return edge_profile(gaussian_blur(sharp, covariance, padding), gradient_minimum)

    def mean_width(rows: torch.Tensor) -> float:
        return float(torch.nanmean(rows[:, 0]))

    low, high = 0.0, _LARGEST_VARIANCE
    if mean_width(profile(low)) >= target_width:
        return profile(low), 0.0
    for _ in range(_BISECTION_STEPS):
        middle = 0.5 * (low + high)
        if mean_width(profile(middle)) < target_width:
            low = middle
        else:
            high = middle
    variance = 0.5 * (low + high)
    return profile(variance), variance


def _anisotropy(rows: torch.Tensor, reference: torch.Tensor, widening: torch.Tensor):
    """Per view |(b, c) - (b, c)_reference| / widening [B]."""
    difference = rows[:, 1:] - reference[:, 1:]
    return torch.linalg.vector_norm(difference, dim=-1) / widening


def soft_edge_profiles(
    data: DiagnosisData, options: GeometricSpecificityConfig, soft_minimum: float
) -> tuple[torch.Tensor, torch.Tensor, float] | None:
    """The edge profiles (edge_profile) [B, 3] of the observed and the fitted render's matte and
    the observed matte's soft share (the share of the render's edge pixels at which it holds a
    value strictly between 0 and 1), or None where that share is below soft_minimum (a binary
    or missing alpha has no edge width)."""
    observed_alpha = data.observed_alpha.double()
    band = (observed_alpha > 0.02) & (observed_alpha < 0.98)
    edge_pixels = (data.rendered_alpha > 0.02) & (data.rendered_alpha < 0.98)
    soft = float(band.sum()) / max(float(edge_pixels.sum()), 1.0)
    if soft < soft_minimum:
        return None
    gradient_minimum = options.edge_gradient_minimum
    observed = edge_profile(observed_alpha, gradient_minimum)
    rendered = edge_profile(data.rendered_alpha.double(), gradient_minimum)
    return observed, rendered, soft


def edge_measurement(
    data: DiagnosisData, options: GeometricSpecificityConfig
) -> dict[str, object] | None:
    """The edge widths of the held-out views (module docstring), or None where the observed
    matte has no soft edges (binary or missing alpha: fewer than
    options.edge_soft_minimum of its edge pixels hold a value strictly between 0 and 1)."""
    profiles = soft_edge_profiles(data, options, options.edge_soft_minimum)
    if profiles is None:
        return None
    observed, rendered, soft = profiles
    gradient_minimum = options.edge_gradient_minimum
    widening = observed[:, 0] - rendered[:, 0]
    valid = torch.isfinite(widening) & torch.isfinite(observed).all(-1)
    if not bool(valid.any()):
        return None
    target = float(observed[valid, 0].mean())
    reference, variance = isotropic_reference(data.rendered_alpha, target, gradient_minimum)
    reference_widening = reference[:, 0] - rendered[:, 0]
    widened = valid & (widening > 0) & (reference_widening > 0)
    measurement: dict[str, object] = {
        "soft_edge_share": soft,
        "widening_px": float(widening[valid].mean()),
        "widening_per_view_px": [float(value) for value in widening],
        "reference_variance_px2": variance,
        "views": int(valid.sum()),
    }
    if not bool(widened.any()):
        measurement["anisotropy"] = math.nan
        measurement["null"] = math.nan
        return measurement
    observed_ratio = _anisotropy(observed, reference, widening)[widened]
    null_ratio = _anisotropy(reference, rendered, reference_widening)[widened]
    difference = observed[:, 1:] - reference[:, 1:]
    angles = (torch.rad2deg(torch.atan2(difference[:, 1], difference[:, 0])) / 2) % 180.0
    measurement["anisotropy"] = float(observed_ratio.median())
    measurement["null"] = float(null_ratio.max())
    measurement["anisotropy_per_view"] = [float(value) for value in observed_ratio]
    measurement["angles_deg"] = [float(value) for value in angles[widened]]
    return measurement


def edge_evidence(data: DiagnosisData, options: GeometricSpecificityConfig) -> list[Evidence]:
    """The "edges" Evidence of defocus_blur and motion_blur (module docstring): passed for the
    one the edges' shape favours (details["favours"]); none where the matte has no soft edges
    or no view's edges are wider than the render's (nothing to attribute)."""
    if not options.edge_widths:
        return []
    measurement = edge_measurement(data, options)
    if measurement is None:
        return []
    anisotropy = float(measurement["anisotropy"])
    if math.isnan(anisotropy):
        return []
    threshold = options.edge_anisotropy_margin * float(measurement["null"])
    favours = MOTION if anisotropy > threshold else DEFOCUS
    shape = (
        "wider across one direction per view: a motion blur's signature"
        if favours == MOTION
        else "as wide in every direction: a defocus's signature"
    )
    reason = (
        f"the data's edges are {float(measurement['widening_px']):.2f} px wider than the fitted "
        f"render's and their width varies with direction by {100 * anisotropy:.0f} % of that "
        f"(median over views) against {100 * threshold:.0f} % "
        f"({options.edge_anisotropy_margin:g} x what an isotropic blur of these silhouettes "
        f"shows): {shape}"
    )
    details = {**measurement, "favours": favours}
    return [
        Evidence(KIND, name, anisotropy, threshold, name == favours, reason, dict(details))
        for name in (DEFOCUS, MOTION)
    ]


def edge_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The edges evidence as a producer (recon.diagnose.producers): measured where both blur
    probes alone could clear under some calibration (lower bound above the decision's
    minimum_share, the floor of every probe allowance): only there can they tie."""
    floor = settings.decision.minimum_share
    lower = {candidate.name: _alone_lower_bound(candidate) for candidate in candidates}
    if not all(lower.get(name, -math.inf) > floor for name in (DEFOCUS, MOTION)):
        return []
    return edge_evidence(inputs.data, settings.geometric_specificity)


def _probe_alone(candidate: Candidate) -> tuple[float | None, dict] | None:
    """The (statistic, details) of the candidate's probe alone (a probe measured on top of
    another effect keeps its probe alone in details["alone"]); None without a counted probe."""
    probe = candidate.evidence_of("probe")
    if probe is None or not probe.counts:
        return None
    alone = probe.details.get("alone") if probe.details.get("conditional_on") else None
    if alone:
        return alone.get("statistic"), alone.get("details", {})
    return probe.statistic, probe.details


def _alone_lower_bound(candidate: Candidate) -> float:
    """The lower bound of the candidate's probe alone; -inf without a probe."""
    alone = _probe_alone(candidate)
    statistic = None if alone is None else alone[0]
    return float(statistic) if statistic is not None else -math.inf


NULL_KIND = "edge_blur"


def probe_blur_covariances(candidate: Candidate, view_count: int) -> torch.Tensor | None:
    """[B, 2, 2] the blur covariance (px^2, x along columns) of a blur candidate's probe in each
    held-out view (the probe alone where it was measured on top of another effect), rebuilt
    from its reported parameters: a defocus's variance times I; a motion blur's line of length
    L at its angle (variance L^2 / 12 along it, its minor variance across). None without a
    probe or its parameters."""
    alone = _probe_alone(candidate)
    if alone is None:
        return None
    parameters = alone[1].get("parameters") or {}
    if candidate.name == DEFOCUS and "variance_px2" in parameters:
        variance = max(float(parameters["variance_px2"]), 0.0)
        return variance * torch.eye(2, dtype=torch.float64).expand(view_count, 2, 2)
    lengths = parameters.get("lengths_px") or []
    if candidate.name != MOTION or len(lengths) != view_count:
        return None
    major = torch.tensor(lengths, dtype=torch.float64) ** 2 / 12
    minor = torch.tensor(parameters.get("minor_sigma_px") or [0.0] * view_count).double() ** 2
    angle = torch.deg2rad(torch.tensor(parameters["angles_deg"], dtype=torch.float64))
    along = torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)  # [B, 2] (column, row)
    across = torch.stack([-torch.sin(angle), torch.cos(angle)], dim=-1)
    return (
        major[:, None, None] * along[:, :, None] * along[:, None, :]
        + minor[:, None, None] * across[:, :, None] * across[:, None, :]
    )


def blurred_edge_width(
    rendered_alpha: torch.Tensor, covariances: torch.Tensor, gradient_minimum: float
) -> torch.Tensor:
    """[B] the mean edge width (px; edge_profile) of the fitted render's matte
    (rendered_alpha [B, H, W, 1]) blurred by the covariances [B, 2, 2]."""
    largest = float(torch.linalg.eigvalsh(covariances).max().clamp_min(0.0))
    padding = math.ceil(3.5 * math.sqrt(largest)) + 1
    blurred = gaussian_blur(rendered_alpha.double(), covariances, padding)
    return edge_profile(blurred, gradient_minimum)[:, 0]


def edge_blur_evidence(
    data: DiagnosisData, candidates: list[Candidate], options: GeometricSpecificityConfig
) -> list[Evidence]:
    """The "edge_blur" null of each blur candidate (defocus_blur, motion_blur) whose probe
    found a blur: how much the data's silhouette edges are wider than the fitted render's
    (soft_edge_profiles), over how much the probe's own blur widens the render's edges
    (blurred_edge_width), both averaged over the held-out views. A blur in the data widens its
    edges as the probe's blur does; a probe that reduces the fit's silhouette misfit (a pose or
    shape error: edges in the wrong place, not wider) recovers a blur the data's edges do not
    show. The threshold is the decision's (diagnose.decision.edge_blur_minimum_ratio). None
    where the matte has no soft edges (no width to measure: binary or missing alpha; the bar is
    options.edge_blur_soft_minimum) or the probe's blur widens nothing."""
    profiles = soft_edge_profiles(data, options, options.edge_blur_soft_minimum)
    if profiles is None:
        return []
    observed, rendered, _ = profiles
    per_view = observed[:, 0] - rendered[:, 0]
    evidence = []
    for candidate in candidates:
        if candidate.name not in (DEFOCUS, MOTION):
            continue
        covariances = probe_blur_covariances(candidate, data.view_count)
        if covariances is None:
            continue
        widths = blurred_edge_width(data.rendered_alpha, covariances, options.edge_gradient_minimum)
        expected = widths - rendered[:, 0]
        valid = torch.isfinite(per_view) & torch.isfinite(expected)
        if not bool(valid.any()) or float(expected[valid].mean()) <= 0:
            continue
        observed_mean = float(per_view[valid].mean())
        expected_mean = float(expected[valid].mean())
        ratio = observed_mean / expected_mean
        reason = (
            f"the data's silhouette edges are {observed_mean:.2f} px wider than the fitted "
            f"render's: {100 * ratio:.0f} % of the {expected_mean:.2f} px {candidate.name}'s "
            "probe blur would widen them by (a blur the edges do not show is the fit's "
            "silhouette misfit)"
        )
        details = {
            "data_widening_px": observed_mean,
            "probe_widening_px": expected_mean,
            "probe_widening_per_view_px": [float(value) for value in expected],
            "views": int(valid.sum()),
        }
        evidence.append(
            Evidence(NULL_KIND, candidate.name, ratio, math.nan, False, reason, details)
        )
    return evidence


def edge_blur_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """The edge_blur null as a producer (recon.diagnose.producers), on the held-out views."""
    if not settings.geometric_specificity.edge_widths:
        return []
    return edge_blur_evidence(inputs.data, candidates, settings.geometric_specificity)
