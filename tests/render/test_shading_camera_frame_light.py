"""A light fixed to the camera (Lighting.frame 'camera', config fit.light.frame): an object and
its camera turned together by any rotation render the same image, as on a turntable, while a
world-frame light shades them differently; light.json round-trips the frame."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from recon.camera import Cameras, look_at
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.optimize.scene_model import LightModel
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting, PointLight


def rotation_matrix(axis: list[float], angle: float) -> torch.Tensor:
    axis = torch.nn.functional.normalize(torch.tensor(axis), dim=0)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def scene() -> tuple[Mesh, Cameras]:
    # A lumpy shape (not a sphere) so that shading depends on orientation.
    sphere = trimesh.creation.icosphere(subdivisions=2)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32) * torch.tensor([1.0, 0.6, 0.8])
    colours = 0.3 + 0.6 * (verts - verts.amin(0)) / (verts.amax(0) - verts.amin(0))
    mesh = Mesh(verts, torch.tensor(sphere.faces), vertex_colors=colours)
    world_to_cam = look_at(torch.tensor([[0.5, 0.8, 3.0]]), torch.zeros(1, 3))
    intrinsics = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]])
    return mesh, Cameras(world_to_cam, intrinsics, (48, 48), near=0.1, far=10.0)


def turned(mesh: Mesh, cameras: Cameras, rotation: torch.Tensor) -> tuple[Mesh, Cameras]:
    """Object and camera rotated together: x -> R x, world_to_cam -> world_to_cam R^T."""
    verts = mesh.verts @ rotation.T
    rigid = torch.eye(4)
    rigid[:3, :3] = rotation.T
    moved = Mesh(verts, mesh.faces, vertex_colors=mesh.vertex_colors)
    return moved, Cameras(
        cameras.world_to_cam @ rigid,
        cameras.intrinsics,
        cameras.image_size,
        cameras.near,
        cameras.far,
    )


def lighting(frame: str) -> Lighting:
    sh = torch.zeros(9, 3)
    sh[0] = 0.3 * math.sqrt(4 * math.pi)
    sh[1] = 0.2  # a y gradient: the environment itself is directional
    sh[3] = -0.1
    return Lighting(
        sh_coefficients=sh,
        directional=[DirectionalLight(torch.tensor([0.3, -0.7, -0.6]), torch.full((3,), 1.5))],
        points=[PointLight(torch.tensor([0.5, -0.5, 0.5]), torch.full((3,), 0.6))],
        frame=frame,
    )


@pytest.mark.parametrize("angle", [0.7, 2.4])
def test_camera_frame_light_shades_a_turned_pair_the_same(angle: float) -> None:
    mesh, cameras = scene()
    rotation = rotation_matrix([0.2, 1.0, 0.3], angle)
    moved_mesh, moved_cameras = turned(mesh, cameras, rotation)
    renderer = Renderer()
    camera_light = lighting("camera")
    before = renderer.render(mesh, cameras, camera_light)
    after = renderer.render(moved_mesh, moved_cameras, camera_light)
    assert float(before.mask.sum()) > 200  # the object fills part of the frame
    assert float((before.alpha - after.alpha).abs().max()) < 1e-3
    assert float((before.color - after.color).abs().max()) < 2e-3
    # A world-frame light does not turn with the pair: the shading changes.
    world_before = renderer.render(mesh, cameras, lighting("world"))
    world_after = renderer.render(moved_mesh, moved_cameras, lighting("world"))
    assert float((world_before.color - world_after.color).abs().max()) > 0.05


def test_camera_frame_light_is_the_world_light_of_an_identity_camera() -> None:
    mesh, cameras = scene()
    # A camera whose axes are the world's (at a translation): camera frame = world frame up to
    # the translation, which a directional light and an SH environment do not see.
    world_to_cam = torch.eye(4)
    world_to_cam[2, 3] = 3.0
    identity = Cameras(world_to_cam[None], cameras.intrinsics, cameras.image_size, 0.1, 10.0)
    light = lighting("world")
    light.points = []
    camera_light = Lighting(light.sh_coefficients, light.directional, frame="camera")
    renderer = Renderer()
    world = renderer.render(mesh, identity, light).color
    camera = renderer.render(mesh, identity, camera_light).color
    assert float((world - camera).abs().max()) < 1e-5


def test_light_model_writes_and_reads_its_frame() -> None:
    model = LightModel(frame="camera")
    data = model.to_json()
    assert data["frame"] == "camera"
    assert Lighting.from_json(data).frame == "camera"
    assert LightModel.from_lighting(Lighting.from_json(data)).frame == "camera"
    assert Lighting.from_json({"sh_coefficients": data["sh_coefficients"]}).frame == "world"
    with pytest.raises(ReconError, match="lighting.frame: expected 'world' or 'camera'"):
        Lighting(torch.zeros(9, 3), frame="object")
