"""Tiny end-to-end fits (CPU, seconds each) with metric bounds."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import trimesh
import yaml

from recon.camera import Cameras, intrinsics_from_fov, look_at
from recon.cli import main
from recon.config.run_config import FitConfig, GeometryStageConfig, TextureStageConfig
from recon.io.datasets import CaptureSet
from recon.io.meshes import load_mesh
from recon.mesh.mesh import Mesh
from recon.metrics.geometry import geometry_metrics
from recon.metrics.image import image_metrics
from recon.optimize.checkpoint import History
from recon.optimize.geometry_stage import GeometryResult, run_geometry_stage
from recon.optimize.scene_model import LightModel
from recon.optimize.texture_stage import run_texture_stage
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting, lambertian

REPO_ROOT = Path(__file__).resolve().parents[2]


def _cameras(count: int, size: int, offset: float = 0.0) -> Cameras:
    index = torch.arange(count, dtype=torch.float32) + 0.5
    height = 1 - 2 * index / count
    radius = (1 - height**2).sqrt()
    angle = index * 2.399963 + offset
    eyes = 3.0 * torch.stack([radius * torch.cos(angle), height, radius * torch.sin(angle)], -1)
    intrinsics = intrinsics_from_fov(40.0, (size, size)).expand(count, 3, 3)
    return Cameras(look_at(eyes), intrinsics, (size, size), near=0.5, far=10.0)


def _captures(mesh: Mesh, cameras: Cameras, lighting: Lighting) -> CaptureSet:
    with torch.no_grad():
        output = Renderer().render(mesh, cameras, lighting)
    names = [f"r_{index}" for index in range(len(cameras))]
    return CaptureSet(cameras, output.color, output.alpha, names, "train")


def _ellipsoid() -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=4)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32) * torch.tensor([0.8, 0.55, 0.45])
    return Mesh(
        verts, torch.tensor(sphere.faces), vertex_colors=torch.full((verts.shape[0], 3), 0.6)
    )


def test_sphere_fitted_to_an_ellipsoid(tmp_path):
    target = _ellipsoid()
    captures = _captures(target, _cameras(12, 48), Lighting.constant(1.0))
    config = FitConfig(
        init="icosphere",
        geometry=GeometryStageConfig(
            steps=120,
            resolutions=[48],
            remesh_every=40,
            edge_length_start=0.08,
            edge_length_end=0.04,
            directional_light=False,
        ),
    )
    result = run_geometry_stage(
        captures, config, torch.device("cpu"), 0, tmp_path / "geometry.pt", History(tmp_path / "h")
    )
    fitted = Mesh(result.verts, result.faces)
    metrics = geometry_metrics(fitted, target, samples=20000, seed=0)
    assert metrics["chamfer_l1"] < 6e-3, metrics
    assert metrics["f1@2%"] > 0.95, metrics
    assert metrics["normal_consistency"] > 0.95, metrics


def _checker_sphere() -> Mesh:
    from data_synth.shapes import make_shape
    from data_synth.textures import make_texture

    mesh = make_shape("sphere", resolution=32)
    mesh.verts = mesh.verts * 0.8
    mesh.texture = make_texture("checker", size=64)
    return mesh


def test_texture_recovery_on_a_fixed_mesh(tmp_path):
    truth = _checker_sphere()
    captures = _captures(truth, _cameras(16, 64), Lighting.constant(1.0))
    held_out = _captures(truth, _cameras(4, 64, offset=1.0), Lighting.constant(1.0))
    light = LightModel(ambient=1.0, with_sun=False)
    geometry = GeometryResult(
        truth.verts, truth.faces, torch.full((truth.verts.shape[0], 3), 0.5), light
    )
    config = FitConfig(
        texture=TextureStageConfig(
            steps=150,
            texture_size=128,
            learning_rate=0.0,
            light_learning_rate=0.0,
            texture_learning_rate=0.05,
            smoothness_weight=0.0,
        )
    )
    result = run_texture_stage(
        captures,
        geometry,
        config,
        torch.device("cpu"),
        0,
        tmp_path / "t.pt",
        History(tmp_path / "h"),
    )
    with torch.no_grad():
        output = Renderer(texture_boundary="clamp").render(
            result.mesh, held_out.cameras, light.lighting()
        )
    metrics = image_metrics(output.color, held_out.images, mask=held_out.masks)
    assert metrics["psnr_masked"] > 24.0, metrics
    # Starting from flat grey the checker must have appeared: the texture's contrast grew.
    assert float(result.mesh.texture.std()) > 0.15


def test_light_recovery_with_known_geometry_and_albedo():
    mesh = _ellipsoid()
    truth = Lighting(
        sh_coefficients=torch.zeros(9, 3),
        directional=[
            DirectionalLight(torch.tensor([0.3, 0.9, 0.3]), torch.tensor([2.0, 1.8, 1.5]))
        ],
    )
    truth.sh_coefficients[0] = torch.tensor([0.5, 0.55, 0.6]) * math.sqrt(4 * math.pi)
    truth.sh_coefficients[1] = 0.3
    coarse = trimesh.creation.icosphere(subdivisions=2)
    verts = torch.tensor(coarse.vertices, dtype=torch.float32) * torch.tensor([0.8, 0.55, 0.45])
    mesh = Mesh(
        verts, torch.tensor(coarse.faces), vertex_colors=torch.full((verts.shape[0], 3), 0.6)
    )
    captures = _captures(mesh, _cameras(8, 24), truth)
    light = LightModel(ambient=0.8)
    optimizer = torch.optim.Adam(light.parameters(), lr=0.05)
    renderer = Renderer()
    for _ in range(150):
        output = renderer.render(mesh, captures.cameras, light.lighting())
        loss = (output.color - captures.images).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    # For a Lambertian object only the irradiance E(n) is identifiable (a sun and SH bands 1-2
    # trade off), so compare E over every normal the object shows.
    normals = torch.nn.functional.normalize(mesh.verts, dim=-1)
    ones = torch.ones(normals.shape[0], 3)
    with torch.no_grad():
        recovered = lambertian(ones, normals, light.lighting())
    expected = lambertian(ones, normals, truth)
    relative = ((recovered - expected).abs() / expected.clamp_min(1e-3)).mean()
    assert float(relative) < 0.05, float(relative)
    assert float(loss.detach()) < 5e-3


def _tiny_run_config(tmp_path: Path) -> Path:
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 6, "val_views": 0, "test_views": 1})
    config["scene"]["shape"]["resolution"] = 24
    config["fit"] = {
        "hull_resolution": 32,
        "checkpoint_every": 4,
        "geometry": {"steps": 12, "resolutions": [32], "remesh_every": 6, "views_per_step": 2},
        "simplify": {"target_faces": 2000},
        "texture": {"steps": 6, "texture_size": 64, "views_per_step": 2},
    }
    path = tmp_path / "tiny_fit.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_resume_equals_an_uninterrupted_run(tmp_path, monkeypatch):
    config = _tiny_run_config(tmp_path)
    whole = tmp_path / "whole"
    assert main(["run", str(config), "--out", str(whole), "--device", "cpu"]) == 0

    import recon.optimize.geometry_stage as geometry_stage

    real_sample_views = geometry_stage.sample_views
    calls = {"count": 0}

    def interrupt_after_nine(*args, **kwargs):
        calls["count"] += 1
        if calls["count"] == 10:
            raise KeyboardInterrupt
        return real_sample_views(*args, **kwargs)

    monkeypatch.setattr(geometry_stage, "sample_views", interrupt_after_nine)
    interrupted = tmp_path / "interrupted"
    assert main(["run", str(config), "--out", str(interrupted), "--device", "cpu"]) == 130
    assert (interrupted / "checkpoints" / "geometry.pt").exists()
    monkeypatch.setattr(geometry_stage, "sample_views", real_sample_views)
    assert main(["run", "--resume", str(interrupted), "--device", "cpu"]) == 0

    first = load_mesh(whole / "mesh" / "model.obj")
    second = load_mesh(interrupted / "mesh" / "model.obj")
    assert torch.equal(first.faces, second.faces)
    torch.testing.assert_close(first.verts, second.verts, atol=1e-6, rtol=0)
    torch.testing.assert_close(first.texture, second.texture, atol=1e-6, rtol=0)
    # The history has each logged step once.
    records = History(interrupted / "history.jsonl").records()
    keys = [(record["stage"], record["step"]) for record in records]
    assert len(keys) == len(set(keys))


@pytest.mark.parametrize("bad", ["fit.geometry.stpes=3", "fit.texture.texture_size=big"])
def test_fit_config_errors(tmp_path, capsys, bad):
    assert main(["run", str(_tiny_run_config(tmp_path)), "--set", bad]) == 2
    error = capsys.readouterr().err
    assert "tiny_fit.yaml" in error and bad.split("=")[0] in error
