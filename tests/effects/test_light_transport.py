"""Shading effects under a light fixed to the camera (recon.effects.light_transport with
Lighting.frame 'camera'): an object and its camera turned together give the same highlight and
the same shadow, as on a turntable; with a world-frame light they do not. Two views in one
batch each get their own light direction."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from recon.camera import Cameras, look_at
from recon.effects.forward import render_with_effects
from recon.effects.light_transport import view_light_directions
from recon.effects.registry import make_effect
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting


def rotation_matrix(axis: list[float], angle: float) -> torch.Tensor:
    axis = torch.nn.functional.normalize(torch.tensor(axis), dim=0)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def scene() -> tuple[Mesh, Cameras]:
    """A lumpy sphere with a small sphere beside it (to cast a shadow), one 48 px camera."""
    big = trimesh.creation.icosphere(subdivisions=3)
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.35)
    # Between the big sphere and the light (toward (-0.2, 0.67, 0.71) in the world).
    small.apply_translation([-0.35, 1.15, 1.2])
    both = trimesh.util.concatenate([big, small])
    verts = torch.tensor(both.vertices, dtype=torch.float32) * torch.tensor([1.0, 0.8, 0.9])
    mesh = Mesh(verts, torch.tensor(both.faces), vertex_colors=torch.full_like(verts, 0.6))
    world_to_cam = look_at(torch.tensor([[0.5, 0.8, 3.5]]), torch.zeros(1, 3))
    intrinsics = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]])
    return mesh, Cameras(world_to_cam, intrinsics, (48, 48), near=0.1, far=10.0)


def turned(mesh: Mesh, cameras: Cameras, rotation: torch.Tensor) -> tuple[Mesh, Cameras]:
    """Object and camera rotated together: x -> R x, world_to_cam -> world_to_cam R^T."""
    rigid = torch.eye(4)
    rigid[:3, :3] = rotation.T
    moved = Mesh(mesh.verts @ rotation.T, mesh.faces, vertex_colors=mesh.vertex_colors)
    return moved, Cameras(
        cameras.world_to_cam @ rigid, cameras.intrinsics, cameras.image_size, 0.1, 10.0
    )


def lighting(frame: str) -> Lighting:
    sh = torch.zeros(9, 3)
    sh[0] = 0.2 * math.sqrt(4 * math.pi)
    # Toward the light in camera axes (OpenCV: y down): up-left of the camera, toward it.
    sun = DirectionalLight(torch.tensor([-0.3, -0.5, -0.8]), torch.full((3,), 2.0))
    return Lighting(sh_coefficients=sh, directional=[sun], frame=frame)


def effects() -> list:
    specular = make_effect("specular")
    shadows = make_effect("shadows", map_resolution=256)
    with torch.no_grad():
        specular.strength.fill_(0.8)
        shadows.strength.fill_(1.0)
    return [specular, shadows]


def render(mesh: Mesh, cameras: Cameras, light: Lighting, chosen: list) -> torch.Tensor:
    with torch.no_grad():
        return render_with_effects(Renderer(), mesh, cameras, light, chosen).color


@pytest.mark.parametrize("angle", [0.9, 2.5])
def test_camera_frame_highlight_and_shadow_turn_with_the_camera(angle: float) -> None:
    mesh, cameras = scene()
    moved_mesh, moved_cameras = turned(mesh, cameras, rotation_matrix([0.1, 1.0, 0.3], angle))
    chosen = effects()
    light = lighting("camera")
    plain = render(mesh, cameras, light, [])
    before = render(mesh, cameras, light, chosen)
    after = render(moved_mesh, moved_cameras, light, chosen)
    # The effects change the image (a highlight brightens, a shadow darkens) ...
    assert float((before - plain).max()) > 0.05
    assert float((before - plain).min()) < -0.02
    # ... and turn with the pair: the same highlight, the same shadowed pixels (up to the
    # shadow map's texel grid, which is laid out in world axes).
    assert float((before - after).abs().mean()) < 1e-3
    shadowed_before = (plain - before).amax(-1) > 0.02
    plain_after = render(moved_mesh, moved_cameras, light, [])
    shadowed_after = (plain_after - after).amax(-1) > 0.02
    overlap = (shadowed_before & shadowed_after).sum() / (shadowed_before | shadowed_after).sum()
    assert int(shadowed_before.sum()) > 20 and float(overlap) > 0.9
    highlight = (before - plain).amax(-1) > 0.05
    highlight_after = (after - plain_after).amax(-1) > 0.05
    overlap = (highlight & highlight_after).sum() / (highlight | highlight_after).sum()
    assert int(highlight.sum()) > 5 and float(overlap) > 0.9
    # A world-frame light's highlight stays in the world: the turned pair looks different.
    world = lighting("world")
    world_before = render(mesh, cameras, world, chosen)
    world_after = render(moved_mesh, moved_cameras, world, chosen)
    assert float((world_before - world_after).abs().max()) > 0.05


def test_views_of_one_batch_get_their_own_light_direction() -> None:
    mesh, cameras = scene()
    rotation = rotation_matrix([0.0, 1.0, 0.0], 1.3)
    _, other = turned(mesh, cameras, rotation)
    pair = Cameras(
        torch.cat([cameras.world_to_cam, other.world_to_cam]),
        cameras.intrinsics.expand(2, 3, 3),
        cameras.image_size,
        0.1,
        10.0,
    )
    directions, _ = view_light_directions(lighting("camera"), pair, torch.zeros(()))
    expected = torch.nn.functional.normalize(torch.tensor([-0.3, -0.5, -0.8]), dim=0)
    for view in range(2):
        rotation_view = pair.world_to_cam[view, :3, :3]
        assert torch.allclose(rotation_view @ directions[view], expected, atol=1e-5)
    # A batch renders each view as it renders alone.
    chosen = effects()
    together = render(mesh, pair, lighting("camera"), chosen)
    alone = render(mesh, other, lighting("camera"), chosen)
    assert float((together[1:] - alone).abs().max()) < 1e-4
