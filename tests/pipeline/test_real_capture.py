"""Regression on real photos: a 6-view subset of ../shared/captures/ethiopian_head (LLFF layout,
off-centre, masks, EXIF) at 48 px, fitted in a few steps with configs/real_capture.yaml as it
is (only the step counts and size lowered), then evaluate, report and diagnose (which crashed on
LLFF runs). Skipped where ../shared/captures is absent. The subset lives in tmp_path."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from recon.cli import main
from recon.config.run_config import DatasetConfig
from recon.io.datasets import read_captures
from recon.io.meshes import load_mesh
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

REPO_ROOT = Path(__file__).resolve().parents[2]
VIEWS = [0, 11, 22, 33, 44, 55]  # spread around the turntable; view 0 is held out


def subset(source: Path, target: Path) -> Path:
    """An LLFF folder with VIEWS of source (images, masks and their poses rows)."""
    table = np.load(source / "poses_bounds.npy")
    names = sorted(path.name for path in (source / "images").iterdir())
    masks = sorted(path.name for path in (source / "masks").iterdir())
    (target / "images").mkdir(parents=True)
    (target / "masks").mkdir()
    for index in VIEWS:
        shutil.copy(source / "images" / names[index], target / "images" / names[index])
        shutil.copy(source / "masks" / masks[index], target / "masks" / masks[index])
    np.save(target / "poses_bounds.npy", table[VIEWS])
    return target


@pytest.mark.slow
@pytest.mark.shared
def test_real_capture_fits_evaluates_reports_and_diagnoses(
    tmp_path: Path, shared_captures: Path, capsys
) -> None:
    data = subset(shared_captures / "ethiopian_head", tmp_path / "data")
    run = tmp_path / "run"
    settings = [
        "dataset.max_resolution=48",
        "fit.hull_resolution=40",
        "fit.geometry.steps=24",
        "fit.geometry.resolutions=[32,48]",
        "fit.geometry.remesh_every=12",
        "fit.simplify.target_faces=2000",
        "fit.texture.steps=4",
        "fit.texture.texture_size=128",
    ]
    overrides = [item for setting in settings for item in ("--set", setting)]
    config = str(REPO_ROOT / "configs" / "real_capture.yaml")
    code = main(
        ["fit", config, "--data", str(data), "--out", str(run), "--device", "cpu", *overrides]
    )
    assert code == 0, capsys.readouterr().err
    # the photos (384 px) were read at 48 px, with a message saying so
    assert "reading them at 48 x 48" in capsys.readouterr().err

    normalization = json.loads((run / "normalization.json").read_text())
    # the published poses put the object well away from the origin
    assert float(np.linalg.norm(normalization["centre"])) > 1.0
    # and the cameras' up is the turntable's axis (LLFF poses here have -y up)
    assert abs(normalization["up"][1]) > 0.8

    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["split"] == "test" and metrics["views"] == 1
    assert metrics["image"]["psnr_masked"] > 14.0
    assert metrics["mesh"]["faces"] <= 2000
    light = json.loads((run / "light" / "light.json").read_text())
    assert light["frame"] == "camera"

    # The fitted mesh (dataset frame) covers the held-out view's mask.
    captures = read_captures(data, "test", DatasetConfig(max_resolution=48))
    mesh = load_mesh(run / "mesh" / "model.obj")
    with torch.no_grad():
        alpha = Renderer().render(mesh, captures.cameras, Lighting.constant()).alpha
    predicted, observed = alpha[..., 0] > 0.5, captures.masks[..., 0] > 0.5
    iou = float((predicted & observed).sum() / (predicted | observed).sum())
    assert iou > 0.75

    assert main(["report", str(run)]) == 0
    assert (run / "figures" / "turntable.png").stat().st_size > 0
    assert main(["diagnose", str(run), "--refit", "none", "--device", "cpu"]) == 0
    diagnosis = json.loads((run / "diagnosis.json").read_text())
    assert diagnosis["verdict"]
