"""Scene normalisation (recon.optimize.normalize): the look-at point, the carved box's centre
and size, the up axis, and the fit's invariance to where the dataset puts the object: an
off-centre, rescaled copy of a capture gives the same fitted mesh (in its own frame)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import trimesh
import yaml

from recon.camera import look_at, orbit_cameras, similarity_transformed
from recon.config.run_config import NormalizeConfig, RunConfig
from recon.io.datasets import write_nerf_synthetic
from recon.io.meshes import load_mesh
from recon.mesh.mesh import Mesh
from recon.optimize.normalize import SceneTransform, estimate_scene_transform, look_at_point
from recon.pipeline import run
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

OFFSET = torch.tensor([2.0, -1.5, 0.7])
SCALE = 3.0


def blob() -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32) * torch.tensor([0.8, 0.5, 0.6])
    colours = 0.2 + 0.7 * (verts - verts.amin(0)) / (verts.amax(0) - verts.amin(0))
    return Mesh(verts, torch.tensor(sphere.faces), vertex_colors=colours)


def test_look_at_point_of_an_off_centre_orbit() -> None:
    cameras = orbit_cameras(8, (16, 16), distance=3.0)
    moved = similarity_transformed(cameras, 1.0, -OFFSET)  # the world shifted by OFFSET
    # (the small pull toward the cameras' centroid moves it by about a millimetre)
    assert torch.allclose(look_at_point(moved), OFFSET, atol=5e-3)


def test_transform_centres_and_scales_the_masks_volume() -> None:
    mesh = blob()
    cameras = orbit_cameras(10, (48, 48), distance=3.0, elevation_deg=25.0)
    masks = Renderer().render(mesh, cameras, Lighting.constant()).alpha
    # The same capture with the object at OFFSET and SCALE times larger.
    moved = similarity_transformed(cameras, SCALE, -OFFSET / SCALE)
    transform = estimate_scene_transform(moved, masks, NormalizeConfig(radius=1.0, grid=48))
    assert transform.warnings == []
    voxel = 2 * 0.8 * 3.0 * SCALE / 48  # the coarse grid's voxel in the moved frame
    assert torch.allclose(torch.tensor(transform.centre), OFFSET, atol=voxel)
    # The blob's half-size is 0.8 (x); the carved hull is a little larger, never smaller.
    half_size = 1.0 / transform.scale
    assert 0.8 * SCALE - voxel <= half_size <= 0.8 * SCALE * 1.2
    assert transform.up == pytest.approx([0.0, 1.0, 0.0], abs=1e-3)  # the orbit's y up
    # round trip through the run folder's JSON, and the point maps
    again = SceneTransform.from_json(json.loads(json.dumps(transform.to_json())))
    points = torch.randn(5, 3)
    assert torch.allclose(again.to_dataset(again.to_normalised(points)), points, atol=1e-5)
    normalised = transform.cameras(moved)
    assert torch.allclose(normalised.centers(), transform.to_normalised(moved.centers()), atol=1e-4)
    # cameras 3 x SCALE from the object, now scale times that from the origin
    distances = normalised.centers().norm(dim=-1)
    assert torch.allclose(
        distances, torch.full_like(distances, 3.0 * SCALE * transform.scale), rtol=0.02
    )


def test_configured_up_axis() -> None:
    cameras = orbit_cameras(6, (16, 16))
    masks = torch.ones(6, 16, 16, 1)
    transform = estimate_scene_transform(cameras, masks, NormalizeConfig(up="-z"))
    assert transform.up == [0.0, 0.0, -1.0]


def write_capture(folder: Path, scale: float, offset: torch.Tensor) -> None:
    mesh = blob()
    eyes = torch.tensor(
        [
            [3 * torch.cos(t), 1.0 * (-1) ** i, 3 * torch.sin(t)]
            for i, t in enumerate(torch.arange(8) * 0.785)
        ]
    )
    world_to_cam = look_at(eyes, torch.zeros(8, 3))
    intrinsics = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    from recon.camera import Cameras

    cameras = Cameras(world_to_cam, intrinsics, (32, 32), near=0.1, far=20.0)
    output = Renderer().render(mesh, cameras, Lighting.constant(1.0))
    moved = similarity_transformed(cameras, scale, -offset / scale)
    write_nerf_synthetic(
        folder, "train", moved[:6], output.color[:6], output.alpha[:6], write_exr=False
    )
    write_nerf_synthetic(
        folder, "test", moved[6:], output.color[6:], output.alpha[6:], write_exr=False
    )


def tiny_fit(tmp_path: Path, name: str, scale: float, offset: torch.Tensor) -> Path:
    data = tmp_path / f"{name}_data"
    write_capture(data, scale, offset)
    config = RunConfig(name=name, data=str(data), device="cpu", stages=["fit"])
    settings = yaml.safe_load(
        """
        hull_resolution: 32
        geometry: {steps: 12, resolutions: [32], remesh_every: 0, views_per_step: 2}
        simplify: {target_faces: 600}
        texture: {steps: 2, texture_size: 128}
        """
    )
    from recon.config.loader import load_config

    path = tmp_path / f"{name}.yaml"
    path.write_text(
        yaml.safe_dump(
            {"name": name, "data": str(data), "device": "cpu", "stages": ["fit"], "fit": settings}
        )
    )
    config = load_config(path, RunConfig)
    return run(config, out=tmp_path / name).root


def test_an_off_centre_capture_gives_the_same_fit_as_the_centred_one(tmp_path: Path) -> None:
    centred = tiny_fit(tmp_path, "centred", 1.0, torch.zeros(3))
    moved = tiny_fit(tmp_path, "moved", SCALE, OFFSET)
    first = load_mesh(centred / "mesh" / "model.obj")
    second = load_mesh(moved / "mesh" / "model.obj")
    # The dataset-frame mesh of the moved capture is the centred fit moved the same way.
    expected = first.verts * SCALE + OFFSET
    assert first.faces.shape[0] > 100
    assert torch.allclose(second.verts.amin(0), expected.amin(0), atol=0.03 * SCALE)
    assert torch.allclose(second.verts.amax(0), expected.amax(0), atol=0.03 * SCALE)
    # and the fit's own frames agree directly
    a = load_mesh(centred / "mesh" / "normalized" / "model.obj").verts
    b = load_mesh(moved / "mesh" / "normalized" / "model.obj").verts
    assert torch.allclose(a.amin(0), b.amin(0), atol=0.03) and torch.allclose(
        a.amax(0), b.amax(0), atol=0.03
    )
    record = json.loads((moved / "normalization.json").read_text())
    assert torch.allclose(torch.tensor(record["centre"]), OFFSET, atol=0.15 * SCALE)
    environment = json.loads((moved / "env.json").read_text())
    assert environment["peak_memory_mb"]["fit"] > 10
    # The fitted light is the same in both runs, written in both frames (normalization.json
    # lists what is where).
    lights = [json.loads((root / "light" / "light.json").read_text()) for root in (centred, moved)]
    first_sun, second_sun = (light["directional"][0]["direction_to_light"] for light in lights)
    assert torch.allclose(torch.tensor(first_sun), torch.tensor(second_sun), atol=0.05)
    assert (moved / "light" / "normalized" / "light.json").is_file()
    assert "light/light.json" in record["exports"]["dataset_frame"]


def test_point_lights_move_to_the_dataset_frame_with_the_same_irradiance() -> None:
    transform = SceneTransform(scale=0.5, centre=[1.0, -2.0, 3.0], up=[0.0, 1.0, 0.0])
    light = {
        "sh_coefficients": [[0.1, 0.1, 0.1]] * 9,
        "directional": [{"direction_to_light": [0.0, 1.0, 0.0], "irradiance": [1.0, 1.0, 1.0]}],
        "points": [{"position": [0.5, 1.0, -0.5], "intensity": [2.0, 2.0, 2.0]}],
        "frame": "world",
    }
    converted = transform.light_to_dataset(light)
    assert converted["directional"] == light["directional"]
    assert converted["sh_coefficients"] == light["sh_coefficients"]
    # The irradiance at a surface point is the same in both frames.
    surface = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)  # fit frame
    surface_dataset = transform.to_dataset(surface)
    point, moved = light["points"][0], converted["points"][0]
    near = point["intensity"][0] / float((torch.tensor(point["position"]) - surface).norm()) ** 2
    position = torch.tensor(moved["position"], dtype=torch.float64)
    far = moved["intensity"][0] / float((position - surface_dataset).norm()) ** 2
    assert far == pytest.approx(near, rel=1e-9)
    assert torch.allclose(
        transform.to_normalised(position), torch.tensor(point["position"]).double()
    )


def test_a_hull_cut_off_by_its_grid_is_a_warning(capsys) -> None:
    from recon.optimize.visual_hull import visual_hull

    mesh = blob()
    cameras = orbit_cameras(8, (32, 32), distance=3.0)
    masks = Renderer().render(mesh, cameras, Lighting.constant()).alpha
    visual_hull(cameras, masks, resolution=24, radius=1.2)
    assert "cut off" not in capsys.readouterr().err
    visual_hull(cameras, masks, resolution=24, radius=0.4)  # smaller than the blob
    err = capsys.readouterr().err
    assert "recon: warning: visual hull" in err and "cut off" in err
