"""The gap diagnosis of a fitted model: where the sim-to-real gap lies, which unmodelled effect
(or base-model mismatch) causes it, and how far it shrinks once that effect is in the forward
model. ``diagnose_run`` calls the parts in order on objects (captures, the fitted model, the
run config); the stage (recon.stages.diagnose) reads the run folder and writes diagnosis.json
(its schema: docs/diagnosis/schema.md, generated from recon.diagnose.records).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from recon.config import to_dict
from recon.config.run_config import DiagnoseConfig, LineTargetConfig, RunConfig
from recon.diagnose.absorption import AbsorptionCache, AbsorptionInputs, absorption_probes
from recon.diagnose.data import (
    DiagnosisData,
    FittedModel,
    render_diagnosis_data,
    render_views_once,
)
from recon.diagnose.decision import decide, decide_all, verdict_of
from recon.diagnose.domains import where_analysis
from recon.diagnose.fingerprint import visibility_fingerprint
from recon.diagnose.flat_field import measure_flat_field
from recon.diagnose.gap import gap_summary, noise_floor, relight_gap
from recon.diagnose.how_far import RefitBaseline, RefitInputs, how_far, relight_exponent
from recon.diagnose.line_target import card_exponent_allowance, measure_line_target
from recon.diagnose.producers import PRODUCERS, EvidenceInputs, gather
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.diagnose.relight_probe import relight_response_probe
from recon.diagnose.which import (
    EffectProbe,
    conditional_probes,
    conditioning_effect,
    rank_candidates,
)
from recon.effects.photometric import normalised_radius
from recon.effects.registry import MODEL_EFFECTS, diagnosis_facts
from recon.errors import ReconError
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer
from recon.render.shading import Lighting


@dataclass
class RelightInputs:
    """A relight split: its captures and the light they were taken under."""

    captures: CaptureSet
    lighting: Lighting


@dataclass
class DiagnosisInputs:
    """Everything the diagnosis reads, as objects (the stage loads them from the run folder).

    heldout, training: the held-out and training captures. model: the fitted model.
    config: the run config (its diagnose section; fit recipe and seed for the refits).
    device: where refits and renders run. scratch: a folder for the refits' checkpoints.
    relight: the relight split, or None; relight_skipped: why it is not used, if it exists.
    flat_field: flat-field frames [N, H, W, 3] or None; flat_field_error: why unusable frames
        are not used. geometry_errors: mesh -> {chamfer_l1, ...} against a ground truth (None
        without one; not part of the method, so outside its timing).
    """

    heldout: CaptureSet
    training: CaptureSet
    model: FittedModel
    config: RunConfig
    device: torch.device
    scratch: Path
    relight: RelightInputs | None = None
    relight_skipped: str | None = None
    flat_field: torch.Tensor | None = None
    flat_field_error: str | None = None
    line_target: tuple[torch.Tensor, torch.Tensor] | None = None
    line_target_error: str | None = None
    geometry_errors: Callable[[Mesh], dict] | None = None


class _Lap:
    """Seconds since the previous lap, recorded under a stage name (the timings' breakdown)."""

    def __init__(self, record: dict[str, float]) -> None:
        self.record = record
        self.last = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.record[name] = round(now - self.last, 2)
        self.last = now


def candidate_names(
    requested: list[str] | None, model: FittedModel, settings: DiagnoseConfig
) -> list[str]:
    """The effects to consider: the requested ones (else diagnose.candidates, else all), less
    those the model already has (the fit's own effects; what its material models)."""
    names = list(requested or settings.candidates or sorted(MODEL_EFFECTS))
    unknown = sorted(set(names) - set(MODEL_EFFECTS))
    if unknown:
        raise ReconError(f"--effects: unknown {unknown}; known: {', '.join(sorted(MODEL_EFFECTS))}")
    modelled = set(model.effect_names)
    return [
        name
        for name in names
        if name not in modelled and model.material not in diagnosis_facts(name).modelled_by
    ]


def covered_radius(data: DiagnosisData) -> float:
    """The largest normalised radius (over the half image diagonal from the principal point, as
    the Vignetting module measures it) of a pixel the object covers in any of data's views.

    A falloff is only seen on covered pixels: beyond this radius, and at the corners (radius
    about 1) unless it is near 1, the fitted falloff is an extrapolation of its polynomial
    (`recon-bench vignetting-extrapolation` measures how far off).
    """
    _, height, width, _ = data.observed.shape
    radius = normalised_radius(data.cameras, height, width, data.observed)
    covered = data.observed_alpha[..., 0] > 0.5
    return float(radius[covered].max()) if bool(covered.any()) else 0.0


def fingerprint_evidence(
    candidates: list[Candidate], data: DiagnosisData, probe: EffectProbe, settings: DiagnoseConfig
) -> dict:
    """The visibility fingerprint of the fitted albedo, recorded on every candidate it can name
    (its facts list 'fingerprint'); returns the gap's record of it."""
    fingerprint = visibility_fingerprint(data, probe.base_output, settings)
    for candidate in candidates:
        if "fingerprint" in diagnosis_facts(candidate.name).evidence:
            candidate.add(fingerprint.evidence(candidate.name).record())
            condition = fingerprint.identifiability(candidate.name, settings.decision)
            if condition is not None:
                candidate.add(condition)
            decide(candidate, settings.decision)
    return fingerprint.to_json(settings.decision)


def relight_evidence(
    candidates: list[Candidate],
    relight: DiagnosisData,
    under_fitted: torch.Tensor,
    fitted_lighting: Lighting,
    settings: DiagnoseConfig,
) -> None:
    """The relight split's response probe, recorded on the candidates its facts apply to."""
    for candidate in candidates:
        if "relight" not in diagnosis_facts(candidate.name).evidence:
            continue
        record = relight_response_probe(relight, under_fitted, fitted_lighting, settings)
        gamma = record["parameters"]["gamma"]
        low, high = record["compression_interval"]
        reason = (
            f"relight split's shading ratio to the power {gamma:.2f} (90 % interval "
            f"{1 - high:.2f}-{1 - low:.2f}); compression's lower bound (1 - its upper end)"
        )
        if record["expanding"] and settings.relight_compressive_only:
            reason = (
                f"relight split's shading ratio is expanded (exponent {gamma:.2f} > 1: light "
                "the diffuse model lacks where it is bright, e.g. a highlight, not a camera's "
                "compressive curve); compression's lower bound"
            )
        if not record["specific"]:
            reason = (
                f"relight split's shading ratio to the power {gamma:.2f}, but the exponent "
                "removes no held-out error beyond the fitted light's own balance (reduction's "
                f"lower bound {record['interval'][0]:.3f} <= 0): not specific to a tone curve; "
                "compression's lower bound, capped at 0"
            )
        candidate.add(
            Evidence(
                kind="relight",
                candidate=candidate.name,
                statistic=record["lower_bound"],
                threshold=float("nan"),
                passed=False,
                reason=reason,
                details={
                    "reduction": record["reduction"],
                    "interval": record["interval"],
                    "compression": record["compression"],
                    "compression_interval": [low, high],
                    "parameters": record["parameters"],
                    "expanding": record["expanding"],
                    "specific": record["specific"],
                },
            )
        )
        decide(candidate, settings.decision)


def record_measurement(
    candidates: list[Candidate],
    kind: str,
    statistic: float,
    reason: str,
    details: dict,
    settings: DiagnoseConfig,
) -> None:
    """One measurement on calibration frames as evidence of kind on every candidate whose facts
    list that kind, each decided again (threshold and verdict come from the decision table)."""
    for candidate in candidates:
        if kind not in diagnosis_facts(candidate.name).evidence:
            continue
        candidate.add(
            Evidence(
                kind=kind,
                candidate=candidate.name,
                statistic=statistic,
                threshold=float("nan"),
                passed=False,
                reason=reason,
                details=dict(details),
            )
        )
        decide(candidate, settings.decision)


def flat_field_evidence(
    candidates: list[Candidate], frames: torch.Tensor, settings: DiagnoseConfig
) -> dict:
    """The flat-field frames' falloff (recon.diagnose.flat_field), recorded on the candidates
    its facts apply to; it overrules their residual evidence either way. A response curve
    found by then (the relight probe) is undone first: a curve bends a falloff like any other
    ratio of intensities."""
    found = [
        item
        for item in candidates
        if item.significant and "relight" in diagnosis_facts(item.name).evidence
    ]
    exponent = relight_exponent(found) if found else None
    measurement = measure_flat_field(frames, exponent, settings)
    measurement["allowance"] = settings.decision.flat_field_allowance
    record_measurement(
        candidates,
        "flat_field",
        measurement["deviation"],
        "flat-field frames: deviation of the corner or half-way falloff from 1",
        {key: measurement[key] for key in ("corner_falloff", "half_radius_falloff", "frames")},
        settings,
    )
    return measurement


def line_target_evidence(
    candidates: list[Candidate],
    frames: torch.Tensor,
    intrinsics: torch.Tensor,
    settings: DiagnoseConfig,
    card: LineTargetConfig | None = None,
) -> dict:
    """The line-target frames' lens distortion (recon.diagnose.line_target), recorded on the
    candidates its facts apply to (it overrules their residual evidence either way), and, with
    the card's specification (its dark_share and contrast_tolerance), the response's exponent
    over its two levels (evidence line_target_levels: it clears a response curve like a relight
    split does, and its allowance grows with what the card's contrast leaves unknown)."""
    dark_share = None if card is None else card.dark_share
    measurement = measure_line_target(frames, intrinsics, dark_share)
    measurement["allowance"] = settings.decision.line_target_allowance
    z = settings.decision.line_target_z
    measurement["z"] = z
    record_measurement(
        candidates,
        "line_target",
        measurement["corner_shift_pixels"],
        f"line-target frames ({measurement['lines']} straight edges in "
        f"{measurement['frames']} frames): the distortion that straightens them moves the "
        f"image corners by (pixels, against the larger of the allowance and {z:g} standard "
        f"errors of {measurement['standard_error']:.3f} px)",
        {
            key: measurement[key]
            for key in (
                "standard_error",
                "parameters",
                "straightness_before_pixels",
                "straightness_after_pixels",
                "lines",
                "frames",
            )
        },
        settings,
    )
    levels = measurement.get("levels")
    if card is not None and levels and levels["exponent"] is not None:
        card_allowance = card_exponent_allowance(card.dark_share, card.contrast_tolerance)
        record_measurement(
            candidates,
            "line_target_levels",
            round(abs(1.0 - levels["exponent"]), 5),
            f"line-target frames' two levels (black {card.dark_share:g} of white, known to "
            f"{100 * card.contrast_tolerance:g} %): the response's exponent over them is "
            f"{levels['exponent']:.3f}; its distance from 1 (against the largest of the "
            f"allowance, the card's {card_allowance:.4f} and {z:g} standard errors of "
            f"{math.inf if levels['standard_error'] is None else levels['standard_error']:.4f})",
            {
                "standard_error": levels["standard_error"],
                "per_frame": levels["per_frame"],
                "dark_share": card.dark_share,
                "contrast_tolerance": card.contrast_tolerance,
                "parameters": {"effective_gamma": levels["exponent"]},
            },
            settings,
        )
    return measurement


def mark_radial_coverage(
    candidates: list[Candidate],
    refits: list[dict],
    radius: float,
    flat_field: dict | None,
    corner_radius: float = 0.0,
) -> None:
    """Add covered_radius to every radial falloff's parameters (candidates' evidence and
    refits), so a corner falloff reads as what it is: measured up to that radius, extrapolated
    beyond. With flat-field frames the corner and half-way falloffs are the frames'
    measurement (the fitted polynomial's stay beside them as model_*), the measured radius is
    the corners' and object_radius keeps the object's.

    Without frames, where the object reaches less than corner_radius (the identifiability
    condition, diagnose.identifiability.corner_radius), the polynomial's corner value is an
    extrapolation, not a measurement (on the real capture, covered to 0.60, it read -5.1 for a
    true 0.60): it is reported as extrapolated_corner_falloff only, and the falloff at the
    covered radius (covered_falloff, from the polynomial's a and b) beside it."""
    radial = {name for name in MODEL_EFFECTS if diagnosis_facts(name).radial_falloff}
    parameter_sets = [
        evidence.details["parameters"]
        for candidate in candidates
        if candidate.name in radial
        for evidence in candidate.evidence
        if evidence.details.get("parameters")
    ]
    parameter_sets += [
        parameters
        for record in refits
        for name, parameters in record.get("parameters", {}).items()
        if name in radial
    ]
    seen: set[int] = set()
    for parameters in parameter_sets:
        if id(parameters) in seen:
            continue
        seen.add(id(parameters))
        parameters["covered_radius"] = round(radius, 4)
        if flat_field is None:
            if radius < corner_radius:
                _withhold_extrapolation(parameters, radius)
            continue
        for key in ("corner_falloff", "half_radius_falloff"):
            if key in parameters:
                parameters.setdefault(f"model_{key}", parameters[key])
            parameters[key] = flat_field[key]
        parameters["falloff_source"] = "flat_field"
        parameters["object_radius"] = round(radius, 4)
        parameters["covered_radius"] = 1.0


def _withhold_extrapolation(parameters: dict, radius: float) -> None:
    """Move an extrapolated corner falloff aside and add the falloff at the covered radius
    (the Vignetting polynomial 1 + r^2 (a + b (r^2 - 0.75)))."""
    if "corner_falloff" in parameters:
        parameters["extrapolated_corner_falloff"] = parameters.pop("corner_falloff")
    if "a" in parameters and "b" in parameters:
        squared = radius * radius
        value = 1 + squared * (parameters["a"] + parameters["b"] * (squared - 0.75))
        parameters["covered_falloff"] = round(float(value), 6)


def radial_model(diagnosis: Diagnosis) -> dict | None:
    """The falloff polynomial to draw beside the flat field: the first refit's that switched a
    radial falloff on, else the candidate's (absorption regression, else probe)."""
    radial = {name for name in MODEL_EFFECTS if diagnosis_facts(name).radial_falloff}
    for record in diagnosis.refits:
        for name, parameters in record.get("parameters", {}).items():
            if name in radial:
                return parameters
    for candidate in diagnosis.candidates:
        if candidate.name in radial:
            for kind in ("absorption", "probe"):
                evidence = candidate.evidence_of(kind)
                if evidence is not None and evidence.details.get("parameters"):
                    return evidence.details["parameters"]
    return None


def heldout_views(inputs: DiagnosisInputs) -> tuple[DiagnosisData, EffectProbe]:
    """The held-out views against the model (its own effects on, per-view ones fitted on each
    view's first half of blocks) and the EffectProbe that renders them."""
    settings = inputs.config.diagnose
    data, output = render_views_once(inputs.heldout, inputs.model, settings.band_pixels)
    probe = EffectProbe(data, settings, scene_output=output)
    if probe.model_effects:
        data = replace(data, rendered=probe.base_output.color.detach())
        probe.data = data
    return data, probe


def relight_views(
    inputs: DiagnosisInputs,
) -> tuple[dict, tuple[DiagnosisData, torch.Tensor, Lighting] | None]:
    """The relight split's gap under its own light (gauge fixed, gap.relight_gap) and the views
    rendered under both lights, or why it is not measured."""
    if inputs.relight is None:
        return ({"skipped": inputs.relight_skipped} if inputs.relight_skipped else {}), None
    settings = inputs.config.diagnose
    relight = render_diagnosis_data(
        inputs.relight.captures,
        inputs.model,
        inputs.device,
        settings.band_pixels,
        lighting=inputs.relight.lighting,
    )
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    with torch.no_grad():
        under_fitted = inputs.model.to("cpu").render(renderer, relight.cameras).color
    return relight_gap(relight), (relight, under_fitted, inputs.model.lighting.to("cpu"))


def which(
    inputs: DiagnosisInputs,
    data: DiagnosisData,
    probe: EffectProbe,
    relight: tuple | None,
    gap: dict,
    lap: _Lap,
    candidates: list[str] | None = None,
) -> list[Candidate]:
    """Which: the probes, the fingerprint, the relight probe, the flat field and the absorption
    refits; then, when a per-view effect tops the ranking, the others again on top of it; then
    the registered producers; every candidate decided and ranked. Records the fingerprint and
    flat field in gap."""
    settings = inputs.config.diagnose
    names = candidate_names(candidates, inputs.model, settings)
    ranked = rank_candidates(data, names, probe=probe, settings=settings)
    lap("probes")
    gap["visibility_fingerprint"] = fingerprint_evidence(ranked, data, probe, settings)
    lap("fingerprint")
    if relight is not None:
        relight_evidence(ranked, *relight, settings)
    lap("relight_probe")
    if inputs.flat_field is not None:
        gap["flat_field"] = flat_field_evidence(ranked, inputs.flat_field, settings)
    if inputs.flat_field_error:
        gap["flat_field_error"] = inputs.flat_field_error
    lap("flat_field")
    if inputs.line_target is not None:
        try:
            gap["line_target"] = line_target_evidence(
                ranked,
                *inputs.line_target,
                settings,
                inputs.config.capture.line_target,
            )
        except ReconError as error:
            gap["line_target_error"] = str(error)
    if inputs.line_target_error:
        gap["line_target_error"] = inputs.line_target_error
    lap("line_target")
    absorption = AbsorptionInputs(
        inputs.training, inputs.model, inputs.config, inputs.device, inputs.scratch
    )
    cache = AbsorptionCache()
    if settings.absorption:
        absorption_probes(ranked, data, absorption, cache=cache)
    lap("absorption")
    decide_all(ranked, settings.decision)
    # A per-view effect at the top (exposure, pose, ...) is measured first; everything else is
    # then measured again on top of it, so a pair is not hidden behind its louder half. (The
    # absorption evidence is gathered before this choice: a lens distortion that the fit bent
    # into the geometry looks like per-view misalignment to the probes alone.)
    given = conditioning_effect(ranked)
    if given:
        conditional_probes(ranked, probe, given)
        lap("conditional_probes")
        if settings.absorption:
            absorption_probes(ranked, data, absorption, given=given, cache=cache)
        lap("conditional_absorption")
    evidence_inputs = EvidenceInputs(
        data,
        probe,
        inputs.heldout,
        inputs.training,
        inputs.model,
        relight and relight[0],
        cache.training,
    )
    gather(PRODUCERS, evidence_inputs, ranked, settings)
    lap("producers")
    return decide_all(ranked, settings.decision)


def how_far_refits(
    inputs: DiagnosisInputs,
    ranked: list[Candidate],
    data: DiagnosisData,
    relight: tuple | None,
    gap: dict,
    refit: str,
) -> list[dict]:
    """How far: the refit ladder against the held-out gap and its noise floor. The refits use
    the fit's own material model (recon.diagnose.refit); a pbr model's refits are measured on
    the held-out views only (the relight split's gap is the Lambertian model's, said in gap)."""
    if refit == "none":
        return []
    settings = inputs.config.diagnose
    floor = (gap["noise_floor"].get("floor_rmse") or 0.0) ** 2
    if inputs.model.pbr is not None and relight is not None:
        gap["how_far_relight_skipped"] = (
            "the relight split renders the Lambertian model under its light; the refits of a "
            "fit.material pbr model are measured on the held-out views only"
        )
        relight = None
    baseline = RefitBaseline.measure(data, floor, relight and relight[0], settings)
    # The refits' baseline, recorded even where nothing is refitted: a benchmark compares a
    # refit's error with a clean fit's on this measure (second half of the pixel blocks).
    gap["heldout_mse"] = baseline.before
    refit_inputs = RefitInputs(
        inputs.training, inputs.model, inputs.config, inputs.device, inputs.scratch
    )
    chamfer, before = None, None
    if inputs.geometry_errors is not None:
        before = gap["parameters"]["geometry"]["chamfer_l1"]

        def chamfer(mesh: Mesh) -> float:
            return inputs.geometry_errors(mesh)["chamfer_l1"]

    return how_far(ranked, baseline, refit_inputs, refit, chamfer, before)


def diagnose_run(
    inputs: DiagnosisInputs, refit: str | None = None, candidates: list[str] | None = None
) -> tuple[Diagnosis, DiagnosisData]:
    """Gap, where, which and how far (refit: none, top or greedy; default diagnose.refit), in
    that order. Returns the Diagnosis and the held-out views (for the figures)."""
    settings = inputs.config.diagnose
    refit = refit or settings.refit
    if refit not in ("none", "top", "greedy"):
        raise ReconError(f"--refit: expected none, top or greedy, got {refit!r}")
    started = time.perf_counter()
    stage_seconds: dict[str, float] = {}
    lap = _Lap(stage_seconds)
    data, probe = heldout_views(inputs)
    gap = {**gap_summary(data), "noise_floor": noise_floor(data)}
    lap("gap")
    gap_relight, relight = relight_views(inputs)
    gap.update({"relight": gap_relight} if gap_relight else {})
    lap("relight_gap")
    where = where_analysis(data)
    lap("where")
    ranked = which(inputs, data, probe, relight, gap, lap, candidates)
    timings = {"diagnose_seconds": round(time.perf_counter() - started, 2), "stages": stage_seconds}
    if inputs.geometry_errors is not None:  # a ground truth: not part of the method's timing
        gap["parameters"] = {"geometry": inputs.geometry_errors(data.mesh)}
    refits = how_far_refits(inputs, ranked, data, relight, gap, refit)
    if refit != "none":
        timings["refit_seconds"] = round(
            time.perf_counter() - started - timings["diagnose_seconds"], 2
        )
    mark_radial_coverage(
        ranked,
        refits,
        covered_radius(data),
        gap.get("flat_field"),
        settings.identifiability.corner_radius,
    )
    decide_all(ranked, settings.decision)  # parameters are the deciding evidence's: again
    diagnosis = Diagnosis(
        gap=gap,
        where=where,
        candidates=ranked,
        refits=refits,
        verdict=verdict_of(ranked),
        # A significant effect whose refit does not close the gap is more likely a false alarm.
        confirmed_by_refit=[record["effects"][-1] for record in refits if record["confirmed"]],
        model=inputs.model.describe(),
        settings=to_dict(settings),
        timings=timings,
    )
    return diagnosis, data
