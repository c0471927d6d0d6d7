"""The report stage: figures of whatever the run folder holds (loss, turntable, material,
distance to the reference, held-out views, the diagnosis's figures) and report.html / report.md
(recon.report.report.render_report)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from recon.config.run_config import RunConfig
from recon.io.atomic import atomic_write_text
from recon.io.datasets import read_captures
from recon.io.meshes import load_material_maps, load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import ERROR_PANEL_MAXIMUM
from recon.optimize.checkpoint import History
from recon.report.material_figure import (
    ROUGHNESS_ERROR_MAXIMUM,
    material_figure,
    roughness_comparison_figure,
)
from recon.report.report import (
    geometry_error_figure,
    held_out_figure,
    loss_figure,
    render_report,
    turntable,
)
from recon.stages.fitted_scene import load_fitted_light, load_pbr_fit

# Held-out views shown in the report (the rest are in renders/).
REPORT_VIEWS = 8


def report_stage(config: RunConfig, paths: RunPaths, device: torch.device) -> dict:
    """Stage 'report': whatever the run folder holds, as figures and one page."""
    figures = _fit_figures(paths, device)
    # The comparison with the true material goes right after the fitted material's figure.
    after = [index for index, (_, path) in enumerate(figures) if path == paths.figure("material")]
    at = after[0] + 1 if after else len(figures)
    figures[at:at] = _material_truth_figures(config, paths, device)
    if paths.renders.exists():
        for render in sorted(paths.renders.glob("*.png"))[:REPORT_VIEWS]:
            figure = paths.figure(f"held_out_{render.stem}")
            held_out_figure(render, figure)
            figures.append(
                (
                    f"Held-out view {render.stem}: photo | render | absolute sRGB error "
                    f"(magma, 0 to {ERROR_PANEL_MAXIMUM})",
                    figure,
                )
            )
    metrics = json.loads(paths.metrics.read_text()) if paths.metrics.exists() else {}
    diagnosis = json.loads(paths.diagnosis.read_text()) if paths.diagnosis.exists() else None
    for name, link in (diagnosis or {}).get("figures", {}).items():
        figures.append((f"Diagnosis: {name.replace('_', ' ')}", paths.root / link))
    relative = [(title, figure.relative_to(paths.root).as_posix()) for title, figure in figures]
    markdown, page = render_report(config.name, metrics, diagnosis, relative)
    atomic_write_text(paths.report_markdown, markdown)
    atomic_write_text(paths.report_html, page)
    return {"figures": len(figures)}


def _fit_figures(paths: RunPaths, device: torch.device) -> list[tuple[str, Path]]:
    """(title, file) of the figures drawn from the fit: loss curves, captures, turntable,
    material, distance to the reference."""
    figures: list[tuple[str, Path]] = []
    records = History(paths.history).records()
    if records:
        loss_figure(records, paths.figure("loss"))
        figures.append(("Loss and training PSNR", paths.figure("loss")))
    if paths.contact_sheet.exists():
        figures.append(("Training captures", paths.contact_sheet))
    if not paths.fitted_mesh.exists():
        return figures
    mesh = load_mesh(paths.fitted_mesh)
    # The up axis recorded by the fit's normalisation frames the turntable.
    up = (
        json.loads(paths.normalization.read_text()).get("up")
        if paths.normalization.exists()
        else None
    )
    # A pbr fit turns with its own material and environment, not the Lambertian stand-in.
    pbr = load_pbr_fit(paths, device)
    turntable(mesh, load_fitted_light(paths, device), paths.figure("turntable"), device, up, pbr)
    title = "Fitted mesh, turntable" + (" (pbr material)" if pbr is not None else "")
    figures.append((title, paths.figure("turntable")))
    if pbr is not None:
        material_figure(pbr, paths.figure("material"))
        figures.append(("Fitted material and environment (pbr)", paths.figure("material")))
    if paths.reference_mesh.exists():
        reference = load_mesh(paths.reference_mesh)
        geometry_error_figure(mesh, reference, paths.figure("geometry_error"), device, up)
        figures.append(
            (
                "Distance to the reference (viridis: 0 to 1 % of the diagonal)",
                paths.figure("geometry_error"),
            )
        )
    return figures


# The roughness comparison is drawn at least this many pixels wide, however small the photos.
MATERIAL_VIEW_PIXELS = 256


def _material_truth_figures(
    config: RunConfig, paths: RunPaths, device: torch.device
) -> list[tuple[str, Path]]:
    """A `pbr` fit on a world whose reference mesh carries its true maps: the fitted roughness
    against the true one from the first held-out view (recon.report.material_figure)."""
    if not (paths.reference_mesh.exists() and paths.dataset.exists()):
        return []
    pbr = load_pbr_fit(paths, "cpu")
    true_maps = load_material_maps(paths.reference_mesh)
    if pbr is None or true_maps is None:
        return []
    split = paths.dataset_layout.held_out_split
    camera = read_captures(paths.dataset, split, config.dataset).cameras[:1]
    height, width = camera.image_size
    scale = max(1.0, MATERIAL_VIEW_PIXELS / max(height, width))
    camera = camera.with_image_size((round(height * scale), round(width * scale)))
    reference = load_mesh(paths.reference_mesh)
    path = paths.figure("roughness_truth")
    roughness_comparison_figure(pbr.mesh, pbr.material, reference, true_maps, camera, path)
    title = (
        f"Fitted against true roughness, first {split} view (viridis 0 to 1; error magma 0 to "
        f"{ROUGHNESS_ERROR_MAXIMUM})"
    )
    return [(title, path)]
