"""recon diagnose: where the sim-to-real gap lies, which unmodelled effect causes it, and how far
it shrinks once that effect is in the forward model. Writes diagnosis.json and figures.

diagnosis.json (stable schema, see README "Gap diagnosis"):
  gap:     held-out RMSE/PSNR (linear), noise floor, gap above the floor, relight error,
           visibility fingerprint, geometry error against the ground truth when there is one
  where:   per domain {score, score_in_sample, summary}
  ranking: [{effect, score, heldout_reduction, interval, significant, evidence, parameters,
            absorption, absorption_interval, fingerprint, conditional_on,
            absorption_discounted_by}]
  refits:  [{effects, before, after, floor, closed_fraction, confirmed, relight_before,
            relight_after, relight_floor, relight_closed_fraction, geometry_before,
            geometry_after}]
  checks:  {vetoed, mismatches, not_identifiable, evidence} (recon.diagnose.checks: nulls from
           the run, specificity, capture metadata, identifiability); each ranking entry also
           lists its own Evidence under "checks"
  verdict: the significant effects in order and what the base model cannot represent, or
           "no significant unmodelled effect"
  confirmed_by_refit: the refitted effects whose refit closed at least 5 % of the gap
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import torch

from recon.config.run_config import RunConfig
from recon.diagnose import checks as second_opinion
from recon.diagnose.absorption import (
    GEOMETRY_ABSORBABLE,
    AbsorptionCache,
    absorption_probes,
    heldout_errors,
    heldout_modules,
)
from recon.diagnose.data import DiagnosisData, load_diagnosis_data
from recon.diagnose.domains import where_analysis
from recon.diagnose.fingerprint import FINGERPRINT_EFFECTS, visibility_fingerprint
from recon.diagnose.flat_field import load_flat_field, measure_flat_field
from recon.diagnose.gap import gap_summary, gauge_gain, noise_floor, relight_gap
from recon.diagnose.refit import POSITION_LEARNING_RATE, REFIT_STEPS, refit_with
from recon.diagnose.relight_probe import relight_response_probe
from recon.diagnose.which import (
    CandidateResult,
    EffectProbe,
    conditional_probes,
    conditioning_effect,
    rank_candidates,
)
from recon.effects.forward import render_with_effects
from recon.effects.photometric import normalised_radius
from recon.effects.registry import MODEL_EFFECTS
from recon.errors import ReconError
from recon.io.atomic import atomic_path, atomic_write_json
from recon.io.datasets import FLAT_FIELD_SPLIT, RELIGHT_LIGHTING, held_out_split
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import _plain
from recon.optimize.fit import load_fitted_light
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

matplotlib.use("Agg")

MAX_GREEDY_EFFECTS = 3
# A refit that closes less than this share of the gap above the floor does not confirm its
# effect (and ends a greedy chain).
CONFIRMING_SHARE = 0.05


class _Lap:
    """Seconds since the previous lap, recorded under a stage name (the timings' breakdown)."""

    def __init__(self, record: dict[str, float]) -> None:
        self.record = record
        self.last = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.record[name] = round(now - self.last, 2)
        self.last = now


def heldout_gap(data: DiagnosisData, modules: list) -> float:
    """Held-out MSE on the second half of the pixel blocks, after fitting the per-view
    parameters of the given effect modules on the first half (scene frozen)."""
    squared, count = heldout_errors(data, modules)
    return float(squared.sum() / count.sum())


GAUGE_ITERATIONS = 3


def relight_heldout_gap(relight: DiagnosisData, mesh, modules: list) -> float:
    """The relight split's MSE after a refit, measured like heldout_gap: per-view effect
    parameters fitted on the first half of the pixel blocks, the error on the second half, the
    scene rendered under the split's own light.

    The albedo x light gauge is fixed first, as relight_gap does: the fitted albedo is only
    known up to a per-channel scale that the fitted light carries. A curve after the albedo (a
    response curve, x -> x^gamma) turns a texture gain g into g^gamma, so the texture's gain
    is found by secant steps on log g against the log of the least-squares gain r of the render
    with the global effects on (r = 1 at the answer; the first step takes gamma = 1)."""
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    mesh = mesh.to(relight.observed.device)
    global_effects = [module for module in modules if not module.per_view]
    log_gain = torch.zeros(3, dtype=torch.float64)
    previous: tuple[torch.Tensor, torch.Tensor] | None = None
    gauged = mesh
    for _ in range(GAUGE_ITERATIONS):
        with torch.no_grad():
            color = render_with_effects(
                renderer, gauged, relight.cameras, relight.lighting, global_effects
            ).color
        log_ratio = gauge_gain(relight.observed, color, relight.region).clamp_min(1e-6).log()
        slope = torch.ones(3, dtype=torch.float64)  # d log r / d log g = -slope
        if previous is not None:
            moved = log_gain - previous[0]
            usable = moved.abs() > 1e-9
            secant = (previous[1] - log_ratio) / torch.where(usable, moved, torch.ones_like(moved))
            slope = torch.where(usable, secant.clamp(0.2, 5.0), slope)
        previous = (log_gain, log_ratio)
        log_gain = log_gain + log_ratio / slope
        gauged = replace(mesh, texture=mesh.texture * log_gain.exp().to(mesh.texture.dtype))
    return heldout_gap(replace(relight, mesh=gauged), modules)


@dataclass
class RefitBaseline:
    """What a refit is measured against: the held-out views of the fitted scene and their MSE,
    the noise floor's MSE, and (with a relight split) the same on the relight split."""

    data: DiagnosisData
    before: float
    floor: float
    relight: DiagnosisData | None = None
    relight_before: float | None = None
    relight_floor: float | None = None

    @classmethod
    def measure(
        cls, data: DiagnosisData, floor: float, relight_views: tuple | None
    ) -> RefitBaseline:
        baseline = cls(data, heldout_gap(data, []), floor)
        if relight_views is not None:
            # Where the fit baked an effect into the albedo under its one light (shadows, a
            # response curve), the held-out views show little of it: the relight split does.
            relight = relight_views[0]
            baseline.relight = relight
            baseline.relight_before = relight_heldout_gap(relight, relight.mesh, [])
            baseline.relight_floor = (noise_floor(relight).get("floor_rmse") or 0.0) ** 2
        return baseline

    def after(self, record: dict) -> RefitBaseline:
        """The baseline for the next effect of a greedy chain: this refit's errors."""
        return replace(self, before=record["after"], relight_before=record.get("relight_after"))


def _closed(before: float, after: float, floor: float) -> float:
    return (before - after) / max(before - floor, 1e-20)


def measure_refit(
    names: list[str],
    baseline: RefitBaseline,
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    steps: int = REFIT_STEPS,
    **options,
) -> tuple[dict, object]:
    """Refit with `names` switched on (options go to refit_with) and measure the gap again.
    Returns (the refit record of diagnosis.json without the geometry errors, the refitted
    mesh)."""
    mesh, lighting, fitted_effects = refit_with(names, paths, config, device, steps, **options)
    data = baseline.data
    modules = heldout_modules(names, fitted_effects.modules, len(data.cameras), device)
    after = heldout_gap(replace(data, mesh=mesh, lighting=lighting), modules)
    closed = _closed(baseline.before, after, baseline.floor)
    record = {
        "effects": names,
        "before": baseline.before,
        "after": after,
        "before_rmse": math.sqrt(baseline.before),
        "after_rmse": math.sqrt(max(after, 0.0)),
        "floor": baseline.floor,
        "closed_fraction": closed,
        "confirmed": closed >= CONFIRMING_SHARE,
        "parameters": {m.name: m.parameters_summary() for m in fitted_effects.modules},
    }
    relight = baseline.relight
    if relight is not None:
        relight_modules = heldout_modules(
            names, fitted_effects.modules, len(relight.cameras), relight.observed.device
        )
        relight_after = relight_heldout_gap(relight, mesh, relight_modules)
        record.update(
            relight_before=baseline.relight_before,
            relight_after=relight_after,
            relight_floor=baseline.relight_floor,
            relight_closed_fraction=_closed(
                baseline.relight_before, relight_after, baseline.relight_floor
            ),
        )
    return record, mesh


def _position_learning_rate(names: list[str], config: RunConfig) -> float:
    """The vertices' step size in a how-far refit: the texture stage's own where an effect
    that bends the geometry is switched on (a lens distortion the fit absorbed must be bent
    back: on the benchmark's default lens seed 2, 0.12 of the gap closed at 0.002, 0.39 at
    0.01), else the refit's small default (on default vignetting seed 0 the larger step let the
    vertices chase the residual: 0.34 closed at 0.002, 0.28 at 0.01). `recon-bench refit-settings`
    measures both."""
    if any(name in GEOMETRY_ABSORBABLE for name in names):
        return config.fit.texture.learning_rate
    return POSITION_LEARNING_RATE


def _relight_exponent(ranking: list[CandidateResult]) -> float | None:
    """The relight probe's response exponent (None without a relight split)."""
    for candidate in ranking:
        if candidate.effect == "response_curve" and candidate.relight_parameters:
            return candidate.relight_parameters["gamma"]
    return None


def fingerprint_evidence(ranking, data: DiagnosisData, probe: EffectProbe) -> dict:
    """The visibility fingerprint of the fitted albedo; when significant it makes the effect it
    names (shadows or interreflection) significant. Recorded on those ranking entries."""
    fingerprint = visibility_fingerprint(data, probe.base_output)
    record = fingerprint.to_json()
    for candidate in ranking:
        if candidate.effect in FINGERPRINT_EFFECTS:
            candidate.fingerprint = record
            candidate.decide()
    return record


def load_relight(paths: RunPaths, device: torch.device) -> tuple[dict, tuple | None]:
    """The relight split's gap under its own light (gauge fixed, gap.relight_gap), or why
    it cannot be measured (rendered under the fitted light, a relight view would only measure
    the change of light); and the relight views rendered under both lights (relight data,
    colour under the fitted light, the fitted light) for the response probe, or None."""
    light_path = paths.dataset / RELIGHT_LIGHTING
    if not light_path.exists():
        return {
            "skipped": f"{light_path} not found: the relight split's light is unknown, so its "
            "gap is not measured"
        }, None
    lighting = Lighting.from_json(json.loads(light_path.read_text()), device)
    relight = load_diagnosis_data(paths, "relight", device, lighting=lighting)
    # The same views under the fitted light, rendered as load_diagnosis_data renders.
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    with torch.no_grad():
        fitted_light = load_fitted_light(paths, relight.mesh.verts.device)
        under_fitted = renderer.render(relight.mesh, relight.cameras, fitted_light).color
    return relight_gap(relight), (relight, under_fitted, fitted_light)


def relight_evidence(ranking: list[CandidateResult], relight_views: tuple) -> None:
    """The relight split's response-curve probe, recorded on the response_curve entry (when the
    response curve is a candidate)."""
    for candidate in ranking:
        if candidate.effect == "response_curve":
            record = relight_response_probe(*relight_views)
            candidate.relight_reduction = record["reduction"]
            candidate.relight_interval = tuple(record["interval"])
            candidate.relight_parameters = record["parameters"]
            candidate.decide()


def covered_radius(data: DiagnosisData) -> float:
    """The largest normalised radius (over the half image diagonal from the principal point, as
    the Vignetting module measures it) of a pixel the object covers in any of data's views.

    A falloff is only seen on covered pixels: beyond this radius, and at the corners (radius
    about 1) unless it is near 1, the fitted vignetting is an extrapolation of its polynomial.
    On the benchmark the object reaches 0.57-0.61, and even the best fit of the polynomial to
    the true falloff there misses the corner by 13-24 % (`recon-bench vignetting-extrapolation`).
    """
    _, height, width, _ = data.observed.shape
    radius = normalised_radius(data.cameras, height, width, data.observed)
    covered = data.observed_alpha[..., 0] > 0.5
    return float(radius[covered].max()) if bool(covered.any()) else 0.0


def flat_field_evidence(ranking: list[CandidateResult], frames: torch.Tensor) -> dict:
    """The flat-field frames' falloff (recon.diagnose.flat_field), recorded on the vignetting
    entry, which it makes significant when it clears FLAT_FIELD_ALLOWANCE. A response curve
    found by then (the relight probe) is undone first: a curve bends a falloff like any other
    ratio of intensities."""
    found = any(item.effect == "response_curve" and item.significant for item in ranking)
    exponent = _relight_exponent(ranking) if found else None
    measurement = measure_flat_field(frames, response_exponent=exponent)
    for candidate in ranking:
        if candidate.effect == "vignetting":
            candidate.flat_field = measurement
            candidate.decide()
    return measurement


def dataset_flat_field(ranking: list[CandidateResult], dataset: Path) -> dict:
    """{"flat_field": measurement} when the dataset has usable flat-field frames (recorded on
    the ranking by flat_field_evidence), {"flat_field_error": why} when it has unusable ones,
    {} without any. Unusable calibration frames should not cost the rest of the diagnosis: it
    goes on without them (vignetting decided by the residual evidence) and says why."""
    frames = load_flat_field(dataset)
    if frames is None:
        return {}
    try:
        return {"flat_field": flat_field_evidence(ranking, frames)}
    except ReconError as error:
        return {"flat_field_error": f"{dataset / FLAT_FIELD_SPLIT}: {error}"}


def _mark_vignetting_coverage(
    ranking: list[CandidateResult],
    refits: list[dict],
    radius: float,
    flat_field: dict | None = None,
):
    """Add covered_radius to every vignetting parameter set (ranking and refits), so a corner
    falloff reads as what it is: measured up to that radius, extrapolated beyond.

    With flat-field frames the corner and half-way falloffs are the frames' measurement (the
    fitted polynomial's stay beside them as model_corner_falloff and model_half_radius_falloff),
    the measured radius is the corners' and object_radius keeps the object's."""
    parameter_sets = [
        parameters
        for candidate in ranking
        if candidate.effect == "vignetting"
        for parameters in (candidate.parameters, candidate.absorption_parameters)
        if parameters
    ]
    parameter_sets += [
        record["parameters"]["vignetting"]
        for record in refits
        if "vignetting" in record.get("parameters", {})
    ]
    for parameters in parameter_sets:
        parameters["covered_radius"] = round(radius, 4)
        if flat_field is None:
            continue
        for key in ("corner_falloff", "half_radius_falloff"):
            if key in parameters:
                parameters.setdefault(f"model_{key}", parameters[key])
            parameters[key] = flat_field[key]
        parameters["falloff_source"] = "flat_field"
        parameters["object_radius"] = round(radius, 4)
        parameters["covered_radius"] = 1.0


def _vignetting_model(ranking: list[CandidateResult], refits: list[dict]) -> dict | None:
    """The vignetting polynomial to draw beside the flat field: the first refit's that switched
    it on, else the ranking entry's (absorption regression, else probe)."""
    for record in refits:
        if "vignetting" in record.get("parameters", {}):
            return record["parameters"]["vignetting"]
    for candidate in ranking:
        if candidate.effect == "vignetting":
            return candidate.absorption_parameters or candidate.parameters or None
    return None


def _geometry_errors(mesh, reference) -> dict:
    """Chamfer-L1, normal consistency and F1@1% of a fitted mesh against the reference."""
    from recon.metrics.geometry import geometry_metrics

    metrics = geometry_metrics(mesh.to("cpu"), reference, samples=20000)
    return {key: metrics[key] for key in ("chamfer_l1", "normal_consistency", "f1@1%")}


def waterfall_figure(refits: list[dict], floor_rmse: float, path) -> None:
    labels = ["fitted"] + ["+ " + " + ".join(r["effects"]) for r in refits]
    values = [refits[0]["before_rmse"]] + [r["after_rmse"] for r in refits] if refits else []
    figure, axis = plt.subplots(figsize=(6, 3.5))
    axis.bar(range(len(values)), values, color=["#888"] + ["#3a7"] * (len(values) - 1))
    axis.axhline(floor_rmse, color="#c33", linestyle="--", label="noise floor")
    axis.set_xticks(range(len(values)), labels, rotation=20, ha="right")
    axis.set_ylabel("held-out residual RMSE (linear)")
    axis.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)


def fit_effects_note(names: list[str]) -> dict:
    """What the diagnosis says of effects the fit itself modelled (fit.effects): it renders
    the fitted mesh, texture and light without them (their per-view parameters belong to the
    training views, and the global ones stay in the fit's checkpoint), so their share of the
    residual is measured as if unmodelled and they can be ranked as candidates."""
    return {
        "names": sorted(names),
        "note": "modelled by the fit but not by the diagnosis: it renders the fitted scene "
        "without them, so their share of the residual counts as unmodelled",
    }


def diagnose_run(
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    refit: str = "top",
    candidates: list[str] | None = None,
    refit_steps: int = REFIT_STEPS,
    absorption: bool = True,
) -> dict:
    """Gap, where, which (probes, conditioning on a per-view top effect, the visibility
    fingerprint, absorption refits) and how far (refit: none, the top effect, or greedily each
    significant one) for a fitted run; writes RUN/diagnosis.json and RUN/diagnosis/*.png and
    returns the same dict. candidates: effect names to consider (None = all eleven)."""
    if not paths.fitted_mesh.exists():
        raise ReconError(f"diagnose: no fitted mesh at {paths.fitted_mesh} (run the fit first)")
    if refit not in ("none", "top", "greedy"):
        raise ReconError(f"--refit: expected none, top or greedy, got {refit!r}")
    unknown = sorted(set(candidates or []) - set(MODEL_EFFECTS))
    if unknown:
        raise ReconError(f"--effects: unknown {unknown}; known: {', '.join(sorted(MODEL_EFFECTS))}")
    started = time.perf_counter()
    stage_seconds: dict[str, float] = {}
    lap = _Lap(stage_seconds)
    split = held_out_split(paths.dataset)
    data = load_diagnosis_data(paths, split, device, dataset_options=config.dataset)
    gap = gap_summary(data)
    if config.fit.effects:
        gap["fit_effects_not_in_model"] = fit_effects_note(config.fit.effects)
    floor = noise_floor(data)
    floor_rmse = floor.get("floor_rmse") or 0.0
    gap["noise_floor"] = floor
    lap("gap")
    relight_views = None
    if (paths.dataset / "transforms_relight.json").exists():
        gap["relight"], relight_views = load_relight(paths, device)
    lap("relight_gap")
    where = where_analysis(data)
    lap("where")
    probe = EffectProbe(data)
    ranking = rank_candidates(data, candidates, probe=probe)
    lap("probes")
    gap["visibility_fingerprint"] = fingerprint_evidence(ranking, data, probe)
    lap("fingerprint")
    if relight_views is not None:
        relight_evidence(ranking, relight_views)
    lap("relight_probe")
    gap.update(dataset_flat_field(ranking, paths.dataset))
    lap("flat_field")
    cache = AbsorptionCache()
    if absorption:
        absorption_probes(ranking, data, paths, config, device, cache=cache)
    lap("absorption")
    ranking.sort(key=CandidateResult.rank_key, reverse=True)
    # A per-view effect at the top (exposure, pose, ...) is measured first; everything else is
    # then measured again on top of it, so a pair is not hidden behind its louder half. (The
    # absorption evidence is gathered before this choice: a lens distortion that the fit bent
    # into the geometry looks like per-view misalignment to the probes alone.)
    given = conditioning_effect(ranking)
    if given:
        conditional_probes(ranking, probe, given)
        lap("conditional_probes")
        if absorption:
            absorption_probes(ranking, data, paths, config, device, given=given, cache=cache)
        lap("conditional_absorption")
    ranking.sort(key=CandidateResult.rank_key, reverse=True)
    # Issue 20's checks (nulls from the run, specificity, metadata, identifiability): vetoes
    # applied in place, the Evidence stored beside each candidate (recon.diagnose.checks).
    conditions, known_exposure = second_opinion.capture_facts(
        paths.dataset, split, config.dataset, relight_views is not None, "flat_field" in gap
    )
    checks = second_opinion.apply_checks(ranking, data, conditions, known_exposure)
    ranking.sort(key=CandidateResult.rank_key, reverse=True)
    lap("checks")
    timings = {"diagnose_seconds": round(time.perf_counter() - started, 2), "stages": stage_seconds}
    # Against the ground truth when the run has one (synthetic data only; not part of the
    # diagnosis method, so outside its timing).
    reference = load_mesh(paths.reference_mesh) if paths.reference_mesh.exists() else None
    if reference is not None:
        gap["parameters"] = {"geometry": _geometry_errors(data.mesh, reference)}

    refits = []
    if refit != "none":
        chosen: list[str] = []
        baseline = RefitBaseline.measure(data, floor_rmse**2, relight_views)
        for candidate in ranking:
            if not candidate.significant or (refit == "top" and chosen):
                continue
            if len(chosen) >= MAX_GREEDY_EFFECTS:
                break
            names = chosen + [candidate.effect]
            record, mesh = measure_refit(
                names,
                baseline,
                paths,
                config,
                device,
                refit_steps,
                response_exponent=_relight_exponent(ranking) if "response_curve" in names else None,
                position_learning_rate=_position_learning_rate(names, config),
            )
            if reference is not None:
                record["geometry_before"] = gap["parameters"]["geometry"]["chamfer_l1"]
                record["geometry_after"] = _geometry_errors(mesh, reference)["chamfer_l1"]
            refits.append(record)
            if refit == "greedy" and not record["confirmed"]:
                break
            chosen = names
            if refit == "greedy":
                baseline = baseline.after(record)
        timings["refit_seconds"] = round(
            time.perf_counter() - started - timings["diagnose_seconds"], 2
        )
    _mark_vignetting_coverage(ranking, refits, covered_radius(data), gap.get("flat_field"))
    verdict = checks.verdict([candidate.effect for candidate in ranking if candidate.significant])
    result = {
        "gap": gap,
        "where": where,
        "ranking": [
            {**candidate.to_json(), "checks": checks.for_candidate(candidate.effect)}
            for candidate in ranking
        ],
        "checks": checks.to_json(),
        "refits": refits,
        "verdict": verdict,
        # The effects whose refit closed at least CONFIRMING_SHARE of the gap: a significant
        # effect whose refit does not close the gap is more likely a probe's false alarm.
        "confirmed_by_refit": [record["effects"][-1] for record in refits if record["confirmed"]],
        "timings": timings,
    }
    folder = paths.root / "diagnosis"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        from recon.diagnose.figures import where_figures

        result["figures"] = {
            key: str(value.relative_to(paths.root)) if hasattr(value, "relative_to") else str(value)
            for key, value in where_figures(data, where, folder).items()
        }
    except ImportError:
        result["figures"] = {}
    if refits:
        waterfall_figure(refits, floor_rmse, folder / "waterfall.png")
        result["figures"]["waterfall"] = "diagnosis/waterfall.png"
    if "flat_field" in gap:
        from recon.diagnose.figures import flat_field_figure

        model = _vignetting_model(ranking, refits)
        flat_field_figure(gap["flat_field"], model, folder / "flat_field.png")
        result["figures"]["flat_field"] = "diagnosis/flat_field.png"
    atomic_write_json(paths.root / "diagnosis.json", _plain(result))
    return result


def diagnose_stage(config: RunConfig, paths: RunPaths, device: torch.device, **options) -> dict:
    """Entry point 'diagnose' of the recon.stages group."""
    result = diagnose_run(paths, config, device, **options)
    return {"verdict": result["verdict"]}
