"""What `recon diagnose` prints: the diagnosis in a few lines a user can read."""

from __future__ import annotations

from recon.diagnose.records import Diagnosis
from recon.report.report import recovered_parameters, summarise_parameters


def _measurement(candidate) -> str:
    """The probe's held-out reduction with its interval, and the other built-in measurements."""
    parts = []
    probe = candidate.evidence_of("probe")
    if probe is not None:
        low, high = probe.interval
        parts.append(
            f"held-out reduction {probe.details['reduction']:7.3f} [{low:.3f}, {high:.3f}]"
        )
    absorption = candidate.evidence_of("absorption")
    if absorption is not None:
        void = f" (void beside {absorption.details['discounted_by']})" if absorption.void else ""
        parts.append(f"absorption {absorption.details['reduction']:6.3f}{void}")
    relight = candidate.evidence_of("relight")
    if relight is not None:
        parts.append(f"relight {relight.details['reduction']:6.3f}")
    return " ".join(parts)


def diagnosis_lines(diagnosis: Diagnosis) -> list[str]:
    """The lines `recon diagnose` prints for a diagnosis."""
    lines = []
    for candidate in diagnosis.candidates:
        flag = f"significant ({candidate.decided_by})" if candidate.significant else ""
        if candidate.status in ("vetoed", "not_identifiable"):
            flag = candidate.status.replace("_", " ")
        elif candidate.status == "ambiguous":
            flag += ", ambiguous"
        lines.append(f"{candidate.name:16} {_measurement(candidate)} {flag}".rstrip())
        lines.append(f"  why: {candidate.why}")
        metadata = candidate.evidence_of("metadata")
        if metadata is not None:
            lines.append(f"  capture metadata: {metadata.reason}")
    record = diagnosis.to_json()
    for effect, source, parameters in recovered_parameters(record):
        lines.append(f"  {effect} ({source}): {summarise_parameters(parameters)}")
    gap = diagnosis.gap
    fingerprint = gap.get("visibility_fingerprint")
    if fingerprint:
        low, high = fingerprint["interval"]
        slope = fingerprint.get("slope", fingerprint["share"])
        placebo = ""
        if fingerprint.get("placebo_lights"):
            placebo = (
                f"; r = {fingerprint['correlation']:.3f}, excess {fingerprint['excess']:.3f} over "
                f"{fingerprint['placebo_lights']} placebo lights (p = {fingerprint['p_value']:.2g})"
            )
        lines.append(
            f"visibility fingerprint: share {fingerprint['share']:.2f} of the predicted "
            f"self-shadowing baked into the albedo (slope {slope:.2f} [{low:.2f}, {high:.2f}]"
            f"{placebo}; names {fingerprint['names'] or 'nothing'})"
        )
    model = diagnosis.model
    if model.get("effects") or model.get("material", "lambert") != "lambert":
        effects = ", ".join(model.get("effects", [])) or "none"
        lines.append(
            f"model: material {model.get('material')}, light frame {model.get('light_frame')}, "
            f"fit effects {effects} (part of the model, not candidates)"
        )
    if gap.get("flat_field_error"):
        lines.append(f"flat field not used: {gap['flat_field_error']}")
    flat = gap.get("flat_field")
    if flat:
        reading = "vignetting" if flat["deviation"] > flat["allowance"] else "flat"
        lines.append(
            f"flat field ({flat['frames']} frames): corner falloff {flat['corner_falloff']:.3f}, "
            f"half-way {flat['half_radius_falloff']:.3f} ({reading}; allowance "
            f"{flat['allowance']:.2f})"
        )
    if gap.get("line_target_error"):
        lines.append(f"line target not used: {gap['line_target_error']}")
    target = gap.get("line_target")
    if target:
        bar = max(target["allowance"], target.get("z", 0.0) * target["standard_error"])
        reading = "lens distortion" if target["corner_shift_pixels"] > bar else "straight"
        lines.append(
            f"line target ({target['frames']} frames, {target['lines']} edges): corners moved "
            f"{target['corner_shift_pixels']:.2f} px (standard error "
            f"{target['standard_error']:.2f} px; {reading}; edges off straight "
            f"{target['straightness_before_pixels']:.3f} -> "
            f"{target['straightness_after_pixels']:.3f} px RMS)"
        )
    for refit in diagnosis.refits:
        relight = (
            f" (relight split: {100 * refit['relight_closed_fraction']:.0f} %)"
            if "relight_closed_fraction" in refit
            else ""
        )
        lines.append(
            f"refit with {' + '.join(refit['effects'])}: RMSE {refit['before_rmse']:.4f} -> "
            f"{refit['after_rmse']:.4f}, closed {100 * refit['closed_fraction']:.0f} % of the gap "
            f"above the floor{relight}"
        )
    lines.append(f"verdict: {diagnosis.verdict}")
    if diagnosis.refits:
        confirmed = diagnosis.confirmed_by_refit
        lines.append(f"confirmed by a refit: {', '.join(confirmed) if confirmed else 'none'}")
    return lines
