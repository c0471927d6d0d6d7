"""The report's text pieces: one-line parameter summaries.
Held-out views as large figures with the error colour bar; views framed by bounds and up."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image

from recon.mesh.mesh import Mesh
from recon.metrics.evaluate import ERROR_PANEL_MAXIMUM, error_image
from recon.render.renderer import Renderer
from recon.render.shading import Lighting
from recon.report.report import (
    HELD_OUT_PANEL_PIXELS,
    framing_cameras,
    held_out_figure,
    summarise_parameters,
)


def test_parameter_summaries_keep_numbers_and_ranges():
    line = summarise_parameters(
        {
            "ratios": [1.0, 0.5, 2.0],
            "gamma": 0.81234,
            "pinned_view": None,
            "model": "x_distorted = x (1 + k1 r^2 + k2 r^4), normalised coordinates",
            "rows": [[1.0, 2.0]],
            "unit": "stops",
            "held": True,
        }
    )
    assert line == "ratios 0.5..2 (3), gamma 0.812, unit stops"


def test_a_small_held_out_view_becomes_a_large_figure_with_a_colour_bar(tmp_path: Path) -> None:
    # A 48 px held-out panel as evaluate writes it: photo | render | error (magma).
    photo = torch.rand(48, 48, 3, generator=torch.Generator().manual_seed(0))
    render = (photo + 0.1).clamp(0, 1)
    error = error_image(render, photo)
    strip = torch.cat([photo, render, error], dim=1)
    panel = tmp_path / "test_view.png"
    Image.fromarray((strip.numpy() * 255).astype(np.uint8)).save(panel)
    figure = tmp_path / "held_out.png"
    held_out_figure(panel, figure)
    with Image.open(figure) as image:
        width, height = image.size
        pixels = np.asarray(image.convert("RGB")).astype(float)
    # three panels of about HELD_OUT_PANEL_PIXELS each (the tight crop trims the margins)
    assert width >= 2.5 * HELD_OUT_PANEL_PIXELS and height >= 0.8 * HELD_OUT_PANEL_PIXELS
    # the colour bar: a column running from black (0) to magma's pale end (the maximum)
    right = pixels[:, int(0.85 * width) :]
    brightness = right.mean(-1)
    assert brightness.min() < 30 and (right[..., 0] > 240).any()
    assert ERROR_PANEL_MAXIMUM == 0.25


def test_framing_keeps_an_off_centre_z_up_object_in_view() -> None:
    box = trimesh.creation.box(extents=(0.4, 0.6, 1.6))  # tall along z
    verts = torch.tensor(box.vertices, dtype=torch.float32) + torch.tensor([5.0, -3.0, 2.0])
    mesh = Mesh(verts, torch.tensor(box.faces), vertex_colors=torch.full_like(verts, 0.7))
    cameras = framing_cameras(mesh, 4, 64, up=[0.0, 0.0, 1.0])
    with torch.no_grad():
        alpha = Renderer().render(mesh, cameras, Lighting.constant()).alpha[..., 0]
    for view in alpha:
        covered = view > 0.5
        assert 0.05 < float(covered.float().mean()) < 0.8  # in view, not cut off
        rows = covered.any(dim=1).nonzero()
        columns = covered.any(dim=0).nonzero()
        # upright: the tall z axis runs down the image (taller than wide)
        assert int(rows.max() - rows.min()) > int(columns.max() - columns.min())
        assert int(rows.min()) > 0 and int(rows.max()) < 63
