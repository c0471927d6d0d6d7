"""Camera conventions: OpenCV axes, intrinsics, clip space, OpenGL/Blender conversion, and a
golden render of an asymmetric marker."""

from __future__ import annotations

import math

import pytest
import torch

from recon.camera import (
    Cameras,
    intrinsics_from_fov,
    look_at,
    opengl_cam_to_world_to_world_to_cam,
    orbit_cameras,
    world_to_cam_to_opengl_cam_to_world,
)
from recon.errors import ReconError
from recon.render.rasterize import rasterize


def test_look_at_gives_opencv_axes():
    world_to_cam = look_at(torch.tensor([[0.0, 0.0, 5.0]]))[0]
    # Looking from +z toward the origin with y up: camera x = world +x, y = world -y, z = -z.
    torch.testing.assert_close(world_to_cam[:3, :3], torch.diag(torch.tensor([1.0, -1.0, -1.0])))
    origin_cam = world_to_cam @ torch.tensor([0.0, 0.0, 0.0, 1.0])
    torch.testing.assert_close(origin_cam[:3], torch.tensor([0.0, 0.0, 5.0]))


def test_intrinsics_from_horizontal_fov():
    intrinsics = intrinsics_from_fov(90.0, (60, 100))
    assert intrinsics[0, 0] == pytest.approx(50.0)
    assert intrinsics[1, 1] == pytest.approx(50.0)
    assert intrinsics[0, 2] == pytest.approx(50.0) and intrinsics[1, 2] == pytest.approx(30.0)
    with pytest.raises(ReconError, match=r"fov_x_deg: expected a value in \(0, 180\), got 180"):
        intrinsics_from_fov(180.0, (8, 8))


def test_projection_matches_pinhole_pixels():
    cameras = orbit_cameras(3, (48, 64), distance=4.0, fov_x_deg=50.0)
    points = torch.randn(20, 3) * 0.5
    pixels = cameras.project_to_pixels(points)
    points_cam = (
        torch.cat([points, torch.ones(20, 1)], -1) @ cameras.world_to_cam.transpose(1, 2)
    )[..., :3]
    expected = (points_cam @ cameras.intrinsics.transpose(1, 2))[..., :2] / points_cam[..., 2:3]
    torch.testing.assert_close(pixels, expected, atol=1e-3, rtol=1e-5)
    clip = cameras.project_to_clip(points)
    torch.testing.assert_close(clip[..., 3], points_cam[..., 2], atol=1e-5, rtol=1e-5)
    depth = clip[..., 2] / clip[..., 3]
    assert bool(((depth > -1) & (depth < 1)).all())


def test_near_and_far_map_to_ndc_bounds():
    cameras = Cameras(
        look_at(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[0.0, 0.0, 1.0]])),
        intrinsics_from_fov(60.0, (8, 8))[None],
        (8, 8),
        near=0.5,
        far=7.0,
    )
    clip = cameras.project_to_clip(torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 7.0]]))
    torch.testing.assert_close(clip[0, :, 2] / clip[0, :, 3], torch.tensor([-1.0, 1.0]))


def test_opengl_conversion_round_trip_and_nerf_camera():
    cameras = orbit_cameras(5, (32, 32))
    cam_to_world_gl = world_to_cam_to_opengl_cam_to_world(cameras.world_to_cam)
    torch.testing.assert_close(
        opengl_cam_to_world_to_world_to_cam(cam_to_world_gl),
        cameras.world_to_cam,
        atol=1e-5,
        rtol=0,
    )
    # A NeRF-synthetic/Blender camera: identity rotation at (0, 0, 4) looks down -z, y up.
    blender = torch.eye(4)
    blender[2, 3] = 4.0
    nerf_camera = Cameras(
        opengl_cam_to_world_to_world_to_cam(blender[None]),
        intrinsics_from_fov(math.degrees(0.6911), (40, 40))[None],
        (40, 40),
    )
    pixels = nerf_camera.project_to_pixels(
        torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    )[0]
    torch.testing.assert_close(pixels[0], torch.tensor([20.0, 20.0]))
    assert pixels[1, 0] > 20 and pixels[1, 1] == pytest.approx(20.0)  # +x world: right
    assert pixels[2, 1] < 20 and pixels[2, 0] == pytest.approx(20.0)  # +y world: up


def test_non_rigid_matrices_are_rejected():
    scaled = torch.eye(4)[None] * 2
    scaled[0, 3, 3] = 1
    with pytest.raises(ReconError, match="transform_matrix: matrix 0 is not rigid"):
        opengl_cam_to_world_to_world_to_cam(scaled)
    nan_matrix = torch.eye(4)[None].clone()
    nan_matrix[0, 0, 3] = float("nan")
    with pytest.raises(ReconError, match="transform_matrix: contains NaN or inf"):
        opengl_cam_to_world_to_world_to_cam(nan_matrix)


def test_bad_camera_shapes_are_rejected():
    with pytest.raises(ReconError, match=r"cameras.world_to_cam: expected shape \[B, 4, 4\]"):
        Cameras(torch.eye(3)[None], torch.eye(3)[None], (8, 8))
    with pytest.raises(ReconError, match=r"cameras.intrinsics: expected shape \[2, 3, 3\]"):
        Cameras(torch.eye(4).repeat(2, 1, 1), torch.eye(3).repeat(3, 1, 1), (8, 8))
    with pytest.raises(ReconError, match="expected 0 < near < far"):
        Cameras(torch.eye(4)[None], torch.eye(3)[None], (8, 8), near=2.0, far=1.0)


def test_golden_asymmetric_marker(device):
    """An L-shaped marker: a long bar along world +x and a short bar along world +y, seen by a
    Blender-style camera on +z. The long bar must land right of centre, the short bar above it,
    and nothing left of or below the corner."""
    bars = []
    for x0, x1, y0, y1 in [(0.0, 1.0, -0.08, 0.08), (-0.08, 0.08, 0.0, 0.5)]:
        bars.append(torch.tensor([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]]))
    verts = torch.cat(bars).to(device)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], device=device)
    blender = torch.eye(4)
    blender[2, 3] = 3.0
    cameras = Cameras(
        opengl_cam_to_world_to_world_to_cam(blender[None]),
        intrinsics_from_fov(45.0, (64, 64))[None],
        (64, 64),
    ).to(device)
    tri_id = rasterize(cameras.project_to_clip(verts), faces, (64, 64)).tri_id[0].cpu()
    rows, columns = torch.nonzero(tri_id >= 0, as_tuple=True)
    long_bar = tri_id <= 1
    long_rows, long_columns = torch.nonzero(long_bar & (tri_id >= 0), as_tuple=True)
    short_rows, short_columns = torch.nonzero(tri_id >= 2, as_tuple=True)
    assert long_columns.float().mean() > 40  # right of centre (32)
    assert short_rows.float().mean() < 26  # above the centre row (row 0 = top)
    assert columns.min() >= 30 and rows.max() <= 34  # nothing left of / below the corner
    assert long_columns.max() - long_columns.min() > 2 * (short_rows.max() - short_rows.min()) - 4
