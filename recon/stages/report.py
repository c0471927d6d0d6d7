"""The report stage: figures of whatever the run folder holds (loss, turntable, material,
distance to the reference, held-out views, the diagnosis's figures) and report.html / report.md
(recon.report.report.render_report)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from recon.config.run_config import RunConfig
from recon.io.atomic import atomic_write_text
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import ERROR_PANEL_MAXIMUM
from recon.optimize.checkpoint import History
from recon.report.material_figure import material_figure
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
