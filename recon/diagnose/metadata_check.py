"""Capture metadata as a check on the diagnosis: recovered exposure against EXIF exposure, and
a white balance against the camera's recorded white-balance mode.

Real photos often carry their exposure (exposure time x ISO / f-number^2, recon.io.exif). When
they do, a recovered per-view exposure is a claim that can be checked: up to one common scale
(the exposure x light gauge), the recovered gains should equal the EXIF ones. The check reports
the median ratio error (|recovered / EXIF - 1| after the common scale), the correlation of the
log gains over views, and the same error of the baseline that predicts the same exposure for
every view: a recovered exposure that does no better than "all equal" has not found the
camera's exposure, whatever it absorbed.

The EXIF WhiteBalance tag says whether the camera set its colour gains itself (auto) or held
them (manual). Under a manual white balance in every held-out view, a colour change from view to
view is not the camera's, whatever the probe removes: on a glossy real object it is the
reflected surroundings, which a diffuse model cannot render (the check vetoes the candidate).
Under auto, the record leaves it possible and the other evidence decides.

The producer returns recon.diagnose.records.Evidence of kind "metadata".
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from recon.config.run_config import MetadataConfig
from recon.diagnose.nulls import permuted_correlations
from recon.diagnose.records import Evidence
from recon.errors import ReconError
from recon.io.exif import exposure_value

KIND = "metadata"


def exif_exposure_gains(metadata: Sequence[dict[str, Any]] | None) -> torch.Tensor | None:
    """Per-view EXIF exposure [B] (time x ISO / f-number^2) over its median, or None when any
    view lacks one of the three values (the check then does not apply)."""
    if not metadata:
        return None
    values = [exposure_value(record or {}) for record in metadata]
    if any(value is None for value in values):
        return None
    gains = torch.tensor(values, dtype=torch.float64)
    return gains / gains.median()


def ratio_error(predicted: torch.Tensor, known: torch.Tensor) -> torch.Tensor:
    """|predicted / known - 1| per view [B], after the common scale that the gauge leaves free
    (the median ratio, so one wrong view does not move it)."""
    ratio = predicted.double() / known.double()
    return (ratio / ratio.median() - 1).abs()


def log_correlation(one: torch.Tensor, other: torch.Tensor) -> float:
    a = one.double().log()
    b = other.double().log()
    a, b = a - a.mean(), b - b.mean()
    denominator = ((a * a).sum() * (b * b).sum()).sqrt()
    return float((a * b).sum() / denominator) if float(denominator) > 0 else 0.0


def metadata_evidence(
    recovered: Sequence[float] | torch.Tensor,
    known: Sequence[float] | torch.Tensor,
    candidate: str = "exposure",
    options: MetadataConfig | None = None,
    divided: bool = False,
) -> Evidence:
    """Recovered per-view exposure gains [B] (e.g. the exposure probe's "ratios") against the
    known ones [B] (EXIF, in the same view order): median ratio error, log correlation with a
    permutation p-value, and the all-equal baseline's error. Passes when the recovered gains
    beat the baseline and correlate with the EXIF gains; when the known gains are all equal, when
    their median ratio error is at most options.equal_tolerance.

    divided: the images were divided by their EXIF exposure on load (dataset.exposure 'exif'),
    so known is all ones (the exposure left to recover) and the reason says why."""
    options = options or MetadataConfig()
    recovered = torch.as_tensor(recovered, dtype=torch.float64).flatten()
    known = torch.as_tensor(known, dtype=torch.float64).flatten()
    if recovered.shape != known.shape:
        raise ReconError(
            f"metadata check: recovered gains for {recovered.numel()} views, known (EXIF) "
            f"gains for {known.numel()}"
        )
    too_few = recovered.numel() < options.minimum_views
    if too_few or bool((recovered <= 0).any()) or bool((known <= 0).any()):
        raise ReconError(
            f"metadata check: expected at least {options.minimum_views} positive gains per "
            "side (diagnose.metadata.minimum_views), got recovered "
            f"{recovered.tolist()} and known {known.tolist()}"
        )
    error = float(ratio_error(recovered, known).median())
    baseline = float(ratio_error(torch.ones_like(known), known).median())
    correlation = log_correlation(recovered, known)
    centred = [values.log() - values.log().mean() for values in (recovered, known)]
    permuted = permuted_correlations(
        centred[0][:, None], centred[1][:, None], options.permutations, options.seed
    )
    p_value = float((1 + (permuted >= correlation).sum()) / (1 + permuted.numel()))
    spread = float(known.max() / known.min())
    if divided:
        agreement = (
            f"the images were divided by their EXIF exposure on load (dataset.exposure: exif), "
            f"so the recovered exposure is compared with equal gains in all {known.numel()} views"
        )
    else:
        agreement = f"EXIF exposure is the same in all {known.numel()} views"
    if spread == 1.0:
        # Known equal exposures: the baseline is exact, so only a spread within the tolerance
        # (pixel quantisation and noise) agrees.
        passed = error <= baseline + options.equal_tolerance
    else:
        passed = error < baseline and p_value < options.alpha
        agreement = (
            f"r = {correlation:.2f} with the known exposure (p = {p_value:.2g}, spanning "
            f"x{spread:.2f} over {known.numel()} views)"
        )
    verdict = "agrees with" if passed else "does not agree with"
    reason = (
        f"recovered {candidate} {verdict} the capture's metadata: median ratio error "
        f"{100 * error:.1f} % against {100 * baseline:.1f} % for equal exposure in every view; "
        f"{agreement}"
    )
    return Evidence(
        kind=KIND,
        candidate=candidate,
        statistic=error,
        threshold=baseline,
        passed=passed,
        reason=reason,
        details={
            "median_ratio_error": error,
            "baseline_error": baseline,
            "correlation": correlation,
            "p_value": p_value,
            "known_spread": spread,
            "views": int(known.numel()),
            "compared_with": "equal gains (images divided by EXIF exposure)"
            if divided
            else "EXIF exposure",
        },
    )


def white_balance_record_evidence(
    metadata: Sequence[dict[str, Any]] | None, candidate: str = "white_balance"
) -> Evidence | None:
    """The held-out views' EXIF white-balance modes (recon.io.exif: "auto" or "manual") as
    evidence on a per-view white balance: failed (a veto) when every view records a manual
    white balance, passed when any records auto; None when a view has no record (a photo
    without the tag, or rendered data), which is no evidence either way."""
    if not metadata:
        return None
    modes = [(record or {}).get("white_balance") for record in metadata]
    if any(mode is None for mode in modes):
        return None
    manual = sum(mode == "manual" for mode in modes)
    share = manual / len(modes)
    passed = manual < len(modes)
    if passed:
        reason = (
            f"the capture's EXIF records an automatic white balance in {len(modes) - manual} of "
            f"{len(modes)} held-out views: the camera may have changed its colour gains"
        )
    else:
        reason = (
            f"the capture's EXIF records a manual white balance in all {len(modes)} held-out "
            "views: the camera held its colour gains, so a colour change from view to view is "
            "not the camera's"
        )
    details = {"views": len(modes), "manual_views": manual, "compared_with": "EXIF WhiteBalance"}
    return Evidence(KIND, candidate, share, 1.0, passed, reason, details)
