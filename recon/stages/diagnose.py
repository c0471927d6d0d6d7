"""The diagnose stage: reads the fitted run folder, diagnoses it, writes diagnosis.json and the
figures. The only diagnosis module that touches the run folder (every path from RunPaths).

    recon diagnose RUN [--refit none|top|greedy] [--effects all|a,b]

Entry point 'diagnose' of the recon.stages group (pyproject.toml).
"""

from __future__ import annotations

import json

import torch

from recon.config.run_config import RunConfig
from recon.diagnose.allocator import reuse_freed_memory
from recon.diagnose.data import DiagnosisData, FittedModel, render_diagnosis_data
from recon.diagnose.diagnose import DiagnosisInputs, RelightInputs, diagnose_run, radial_model
from recon.diagnose.records import Diagnosis
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.checkpoints import load_checkpoint
from recon.io.dataset_layout import RELIGHT_SPLIT
from recon.io.datasets import (
    FLAT_FIELD_SPLIT,
    LINE_TARGET_SPLIT,
    read_captures,
    read_nerf_synthetic,
)
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import plain_json
from recon.optimize.scene_model import FitEffects
from recon.render.shading import Lighting
from recon.stages.fitted_scene import load_fitted_scene


def load_fitted_model(paths: RunPaths, config: RunConfig, device: torch.device) -> FittedModel:
    """The fitted model of a run: mesh, light, the pbr material (fit.material: pbr) and the
    fit's own effect modules (fit.effects) at the parameters its last checkpoint holds."""
    if not paths.fitted_mesh.exists():
        raise ReconError(f"diagnose: no fitted mesh at {paths.fitted_mesh} (run the fit first)")
    if not paths.fitted_light.exists():
        raise ReconError(f"diagnose: no fitted light at {paths.fitted_light} (run the fit first)")
    scene = load_fitted_scene(paths, device)
    effects = []
    if config.fit.effects:
        checkpoint = load_checkpoint(paths.texture_checkpoint)
        if checkpoint is None or "effects" not in checkpoint:
            raise ReconError(
                f"diagnose: fit.effects {config.fit.effects} but no effect parameters in "
                f"{paths.texture_checkpoint} (run the fit again)"
            )
        view_count = len(read_captures(paths.dataset, "train", config.dataset).cameras)
        fitted = FitEffects(config.fit.effects, view_count, device)
        fitted.load_state_dict(checkpoint["effects"])
        effects = fitted.modules
    return FittedModel(scene.mesh.to(device), scene.lighting, effects, scene.pbr)


def load_diagnosis_data(
    paths: RunPaths, split: str, config: RunConfig, device: torch.device | str = "cpu", effects=None
) -> DiagnosisData:
    """One split of the run's dataset against its fitted model (renders on the CPU)."""
    model = load_fitted_model(paths, config, torch.device(device))
    captures = read_captures(paths.dataset, split, config.dataset)
    return render_diagnosis_data(
        captures, model, device, config.diagnose.band_pixels, effects=effects
    )


def diagnosis_inputs(paths: RunPaths, config: RunConfig, device: torch.device) -> DiagnosisInputs:
    """Everything diagnose_run reads, loaded from the run folder and its dataset (any layout
    recon reads; the layout says which split is held out and whether relight and flat-field
    splits exist)."""
    layout = paths.dataset_layout
    model = load_fitted_model(paths, config, device)
    heldout = read_captures(paths.dataset, layout.held_out_split, config.dataset, keep_frames=True)
    training = read_captures(paths.dataset, "train", config.dataset)
    inputs = DiagnosisInputs(heldout, training, model, config, device, paths.diagnosis_refit)
    if layout.has_relight:
        if layout.relight_lighting.exists():
            record = json.loads(layout.relight_lighting.read_text())
            captures = read_captures(paths.dataset, RELIGHT_SPLIT, config.dataset)
            inputs.relight = RelightInputs(captures, Lighting.from_json(record, device))
        else:
            inputs.relight_skipped = (
                f"{layout.relight_lighting} not found: the relight split's light is unknown, "
                "so its gap is not measured"
            )
    if layout.has_flat_field:
        try:
            frames = read_nerf_synthetic(
                paths.dataset, FLAT_FIELD_SPLIT, background=None, prefer_exr=True
            )
            inputs.flat_field = frames.images.double()
        except ReconError as error:
            inputs.flat_field_error = f"{layout.flat_field}: {error}"
    if layout.has_line_target:
        try:
            frames = read_nerf_synthetic(
                paths.dataset, LINE_TARGET_SPLIT, background=None, prefer_exr=True
            )
            inputs.line_target = (frames.images.double(), frames.cameras.intrinsics)
        except ReconError as error:
            inputs.line_target_error = f"{layout.line_target}: {error}"
    if paths.reference_mesh.exists():
        reference = load_mesh(paths.reference_mesh)

        def geometry_errors(mesh) -> dict:
            from recon.metrics.geometry import geometry_metrics

            metrics = geometry_metrics(mesh.to("cpu"), reference, samples=20000)
            return {key: metrics[key] for key in ("chamfer_l1", "normal_consistency", "f1@1%")}

        inputs.geometry_errors = geometry_errors
    return inputs


def write_figures(diagnosis: Diagnosis, data: DiagnosisData, paths: RunPaths) -> None:
    """The diagnosis' figures under RUN/diagnosis/, recorded relative to the run folder."""
    from recon.diagnose.figures import (
        backdrop_figure,
        flat_field_figure,
        line_target_figure,
        waterfall_figure,
        where_figures,
    )

    folder = paths.diagnosis_folder
    folder.mkdir(parents=True, exist_ok=True)
    figures = where_figures(data, diagnosis.where, folder)
    diagnosis.figures = {key: str(path.relative_to(paths.root)) for key, path in figures.items()}
    if diagnosis.refits:
        floor = diagnosis.gap["noise_floor"].get("floor_rmse") or 0.0
        path = waterfall_figure(diagnosis.refits, floor, folder / "waterfall.png")
        diagnosis.figures["waterfall"] = str(path.relative_to(paths.root))
    if "flat_field" in diagnosis.gap:
        path = flat_field_figure(
            diagnosis.gap["flat_field"], radial_model(diagnosis), folder / "flat_field.png"
        )
        diagnosis.figures["flat_field"] = str(path.relative_to(paths.root))
    if "line_target" in diagnosis.gap:
        path = line_target_figure(diagnosis.gap["line_target"], folder / "line_target.png")
        diagnosis.figures["line_target"] = str(path.relative_to(paths.root))
    backdrop = [
        item.to_json()
        for candidate in diagnosis.candidates
        for item in candidate.evidence
        if item.kind == "backdrop"
    ]
    if backdrop:
        path = backdrop_figure(backdrop, folder / "backdrop.png")
        diagnosis.figures["backdrop"] = str(path.relative_to(paths.root))


def run_diagnosis(
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    refit: str | None = None,
    candidates: list[str] | None = None,
) -> Diagnosis:
    """Diagnose a fitted run folder; writes RUN/diagnosis.json and RUN/diagnosis/*.png."""
    inputs = diagnosis_inputs(paths, config, device)
    with reuse_freed_memory():  # large tensors come and go: no page faults for each
        diagnosis, data = diagnose_run(inputs, refit, candidates)
        write_figures(diagnosis, data, paths)
    atomic_write_json(paths.diagnosis, plain_json(diagnosis.to_json()))
    return diagnosis


def diagnose_stage(config: RunConfig, paths: RunPaths, device: torch.device, **options) -> dict:
    """Entry point 'diagnose' of the recon.stages group."""
    diagnosis = run_diagnosis(paths, config, device, **options)
    return {"verdict": diagnosis.verdict}
