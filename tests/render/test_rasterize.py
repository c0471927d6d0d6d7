"""rasterize: agreement with a naive ray caster, coverage, derivatives, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from reference.raycast import raycast

from recon.camera import Cameras, intrinsics_from_fov, look_at, orbit_cameras
from recon.errors import ReconError
from recon.render.interpolate import interpolate
from recon.render.rasterize import rasterize


def _random_scene(seed: int, triangle_count: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    centres = (torch.rand(triangle_count, 1, 3, generator=generator) - 0.5) * 1.6
    offsets = (torch.rand(triangle_count, 3, 3, generator=generator) - 0.5) * 1.2
    verts = (centres + offsets).reshape(-1, 3)
    faces = torch.arange(triangle_count * 3).reshape(-1, 3)
    return verts, faces


def _camera(image_size=(24, 32), eye=(0.3, 0.4, 3.0), fov=50.0, near=0.1, far=20.0) -> Cameras:
    eyes = torch.tensor([eye])
    return Cameras(
        world_to_cam=look_at(eyes),
        intrinsics=intrinsics_from_fov(fov, image_size)[None],
        image_size=image_size,
        near=near,
        far=far,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_naive_raycaster(seed, device):
    verts, faces = _random_scene(seed)
    cameras = _camera()
    fragments = rasterize(
        cameras.to(device).project_to_clip(verts.to(device)), faces.to(device), cameras.image_size
    )
    tri_ref, bary_ref, _ = raycast(verts, faces, cameras)
    tri_id = fragments.tri_id[0].cpu().numpy()
    # Exact agreement except where two surfaces are within float32 noise of each other.
    assert (tri_id == tri_ref).mean() >= 0.998
    same = (tri_id == tri_ref) & (tri_ref >= 0)
    assert same.sum() > 50
    bary = fragments.barycentrics[0].cpu().numpy()
    np.testing.assert_allclose(bary[same], bary_ref[same], atol=2e-4)


def test_triangle_crossing_camera_plane_matches_raycaster(device):
    # A ground quad reaching far behind the camera: vertices with w < 0 must not smear or vanish.
    verts = torch.tensor(
        [[-6.0, -1.0, -8.0], [6.0, -1.0, -8.0], [6.0, -1.0, 9.0], [-6.0, -1.0, 9.0]]
    )
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    cameras = _camera(image_size=(20, 28), eye=(0.0, 0.0, 3.0), fov=70.0, near=0.2)
    clip = cameras.to(device).project_to_clip(verts.to(device))
    assert bool((clip[..., 3] < 0).any()), "the test needs vertices behind the camera"
    fragments = rasterize(clip, faces.to(device), cameras.image_size)
    tri_ref, bary_ref, _ = raycast(verts, faces, cameras)
    tri_id = fragments.tri_id[0].cpu().numpy()
    assert (tri_id == tri_ref).mean() >= 0.995
    assert (tri_ref >= 0).mean() > 0.3
    same = (tri_id == tri_ref) & (tri_ref >= 0)
    np.testing.assert_allclose(
        fragments.barycentrics[0].cpu().numpy()[same], bary_ref[same], atol=1e-3
    )


def test_triangle_coverage_matches_area(device):
    # A big screen-space triangle: covered pixel centres ~ area (error bounded by perimeter).
    height, width = 64, 80
    corners_pixels = torch.tensor([[5.3, 7.1], [71.7, 15.2], [30.4, 60.9]])
    ndc = corners_pixels / torch.tensor([width, height]) * 2 - 1
    clip = torch.cat([ndc, torch.zeros(3, 1), torch.ones(3, 1)], dim=-1).to(device)
    fragments = rasterize(clip, torch.tensor([[0, 1, 2]], device=device), (height, width))
    count = int((fragments.tri_id >= 0).sum())
    a, b, c = corners_pixels
    area = 0.5 * abs(float((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0]))
    perimeter = float((b - a).norm() + (c - b).norm() + (a - c).norm())
    assert abs(count - area) <= 0.5 * perimeter
    assert abs(count - area) / area < 0.03


def test_sphere_coverage_matches_analytic_disc(device):
    mesh = trimesh.creation.icosphere(subdivisions=5)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32, device=device)
    faces = torch.tensor(mesh.faces, device=device)
    cameras = orbit_cameras(3, (96, 96), distance=3.0, fov_x_deg=45.0, device=device)
    fragments = rasterize(cameras.project_to_clip(verts), faces, cameras.image_size)
    coverage = (fragments.tri_id >= 0).float().mean(dim=(1, 2))
    # Silhouette of a unit sphere at distance d: cone of half-angle asin(1/d).
    radius_ndc = math.tan(math.asin(1 / 3.0)) / math.tan(math.radians(22.5))
    expected = math.pi * radius_ndc**2 / 4
    # The icosphere is inscribed, so it covers slightly less than the true sphere.
    assert torch.all(coverage <= expected)
    assert torch.all(coverage >= expected * 0.985)


def test_perspective_correct_interpolation_hits_the_plane(device):
    # Interpolated world positions must equal the ray-plane intersection at each pixel centre.
    verts = torch.tensor([[-1.0, -0.8, -0.5], [1.2, -0.6, 0.8], [-0.2, 1.1, -1.6]])
    faces = torch.tensor([[0, 1, 2]])
    cameras = _camera(image_size=(40, 40), eye=(0.2, 0.1, 3.0), fov=60.0)
    fragments = rasterize(
        cameras.to(device).project_to_clip(verts.to(device)), faces.to(device), cameras.image_size
    )
    positions = interpolate(verts.to(device), fragments, faces.to(device))[0].cpu().double()
    covered = (fragments.tri_id[0] >= 0).cpu()
    origin, directions = _rays(cameras)
    normal = torch.linalg.cross(verts[1] - verts[0], verts[2] - verts[0]).double()
    t = ((verts[0].double() - origin) @ normal) / (directions @ normal)
    expected = origin + t[..., None] * directions
    assert covered.sum() > 200
    torch.testing.assert_close(positions[covered], expected[covered], atol=2e-4, rtol=0)
    # The same interpolation without perspective correction would be visibly off.
    depth_range = float(t[covered].max() / t[covered].min())
    assert depth_range > 1.3


def _rays(cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    from reference.raycast import pixel_rays

    origin, directions = pixel_rays(cameras, 0)
    return torch.from_numpy(origin), torch.from_numpy(directions)


def test_backface_culling(device):
    # Counter-clockwise seen from the camera at +z = front face.
    verts = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]], device=device)
    front = torch.tensor([[0, 1, 2]], device=device)
    back = torch.tensor([[0, 2, 1]], device=device)
    cameras = _camera(image_size=(16, 16), eye=(0.0, 0.0, 3.0)).to(device)
    clip = cameras.project_to_clip(verts)
    assert (rasterize(clip, front, (16, 16), cull_backfaces=True).tri_id >= 0).any()
    assert not (rasterize(clip, back, (16, 16), cull_backfaces=True).tri_id >= 0).any()
    assert (rasterize(clip, back, (16, 16)).tri_id >= 0).any()


def test_barycentric_derivatives_match_finite_differences(device):
    verts = torch.tensor([[-1.0, -0.8, -0.5], [1.2, -0.6, 0.8], [-0.2, 1.1, -1.6]])
    faces = torch.tensor([[0, 1, 2]])
    cameras = _camera(image_size=(32, 32), eye=(0.2, 0.1, 3.0), fov=60.0)
    fragments = rasterize(
        cameras.to(device).project_to_clip(verts.to(device)),
        faces.to(device),
        cameras.image_size,
        with_derivatives=True,
    )
    bary = fragments.barycentrics[0].cpu().double()
    derivatives = fragments.barycentric_derivatives[0].cpu().double()
    covered = (fragments.tri_id[0] >= 0).cpu()
    # Central differences between neighbouring pixels where both neighbours are covered.
    inner_x = covered[:, 2:] & covered[:, :-2] & covered[:, 1:-1]
    fd_x = (bary[:, 2:] - bary[:, :-2]) / 2
    torch.testing.assert_close(
        derivatives[:, 1:-1][..., [0, 1]][inner_x], fd_x[inner_x], atol=5e-4, rtol=0.02
    )
    inner_y = covered[2:] & covered[:-2] & covered[1:-1]
    fd_y = (bary[2:] - bary[:-2]) / 2
    torch.testing.assert_close(
        derivatives[1:-1][..., [2, 3]][inner_y], fd_y[inner_y], atol=5e-4, rtol=0.02
    )


def test_batched_views_equal_single_views(device):
    verts, faces = _random_scene(4)
    cameras = orbit_cameras(3, (20, 24), distance=3.5, device=device)
    clip = cameras.project_to_clip(verts.to(device))
    batched = rasterize(clip, faces.to(device), (20, 24))
    for view in range(3):
        single = rasterize(clip[view], faces.to(device), (20, 24))
        assert torch.equal(single.tri_id[0], batched.tri_id[view])


def test_small_chunks_give_the_same_result(device):
    verts, faces = _random_scene(5, triangle_count=30)
    cameras = _camera().to(device)
    clip = cameras.project_to_clip(verts.to(device))
    whole = rasterize(clip, faces.to(device), cameras.image_size)
    chunked = rasterize(clip, faces.to(device), cameras.image_size, chunk_candidates=97)
    assert torch.equal(whole.tri_id, chunked.tri_id)


def test_barycentric_gradients_flow_to_clip_positions(device):
    clip = torch.tensor(
        [[-0.7, -0.6, 0.3, 1.0], [0.8, -0.4, 0.2, 1.3], [0.0, 0.7, 0.1, 0.9]],
        device=device,
        dtype=torch.float64,
    )

    def barycentric_sum(clip64: torch.Tensor) -> torch.Tensor:
        fragments = rasterize(clip64.float(), torch.tensor([[0, 1, 2]], device=device), (20, 20))
        return fragments.barycentrics.double()

    # Visibility is fixed under tiny perturbations, so autograd must match central differences.
    clip.requires_grad_(True)
    weights = torch.rand(1, 20, 20, 2, device=device, dtype=torch.float64)
    # Only pixels whose 3x3 neighbourhood is covered: tiny steps cannot flip their visibility.
    base = rasterize(clip.detach().float(), torch.tensor([[0, 1, 2]], device=device), (20, 20))
    covered = (base.tri_id >= 0).double()[:, None]
    interior = -torch.nn.functional.max_pool2d(-covered, 3, stride=1, padding=1)
    weights = weights * interior[:, 0, ..., None]
    assert int(interior.sum()) > 20
    (barycentric_sum(clip) * weights).sum().backward()
    numeric = torch.zeros_like(clip)
    step = 1e-3
    for index in np.ndindex(3, 4):
        if index[1] == 2:
            continue
        plus, minus = clip.detach().clone(), clip.detach().clone()
        plus[index] += step
        minus[index] -= step
        numeric[index] = (
            (barycentric_sum(plus) * weights).sum() - (barycentric_sum(minus) * weights).sum()
        ) / (2 * step)
    torch.testing.assert_close(clip.grad, numeric, atol=2e-2, rtol=2e-2)


# ---------------------------------------------------------------------------- bad input


def test_rejects_bad_shapes_and_dtypes():
    faces = torch.tensor([[0, 1, 2]])
    with pytest.raises(ReconError, match=r"clip_pos: expected last dimension 4"):
        rasterize(torch.zeros(3, 3), faces, (8, 8))
    with pytest.raises(ReconError, match=r"clip_pos: expected dtype float32, got torch.float64"):
        rasterize(torch.zeros(3, 4, dtype=torch.float64), faces, (8, 8))
    with pytest.raises(ReconError, match=r"faces: expected shape \[F, 3\], got \(3,\)"):
        rasterize(torch.zeros(3, 4), torch.tensor([0, 1, 2]), (8, 8))
    with pytest.raises(ReconError, match=r"faces: expected dtype int64"):
        rasterize(torch.zeros(3, 4), faces.float(), (8, 8))
    with pytest.raises(ReconError, match=r"resolution: expected positive"):
        rasterize(torch.zeros(3, 4), faces, (0, 8))


def test_rejects_non_finite_positions_and_bad_indices():
    clip = torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 3)
    bad = clip.clone()
    bad[1, 0] = float("nan")
    with pytest.raises(ReconError, match="clip_pos: contains NaN or inf"):
        rasterize(bad, torch.tensor([[0, 1, 2]]), (8, 8))
    bad[1, 0] = float("inf")
    with pytest.raises(ReconError, match="clip_pos: contains NaN or inf"):
        rasterize(bad, torch.tensor([[0, 1, 2]]), (8, 8))
    with pytest.raises(ReconError, match=r"indices must lie in \[0, 2\].*got range \[0, 3\]"):
        rasterize(clip, torch.tensor([[0, 1, 3]]), (8, 8))
    with pytest.raises(ReconError, match=r"got range \[-1, 2\]"):
        rasterize(clip, torch.tensor([[0, -1, 2]]), (8, 8))


def test_empty_mesh_and_zero_area_triangles_are_background():
    empty = rasterize(torch.zeros(0, 4), torch.zeros(0, 3, dtype=torch.int64), (8, 8))
    assert empty.tri_id.shape == (1, 8, 8) and bool((empty.tri_id == -1).all())
    assert empty.barycentrics.shape == (1, 8, 8, 2)
    # Collinear and repeated vertices: no coverage, no NaN, and neighbours unaffected.
    clip = torch.tensor(
        [
            [-0.5, -0.5, 0.0, 1.0],
            [0.5, 0.5, 0.0, 1.0],
            [0.0, 0.0, 0.0, 1.0],  # collinear with the first two
            [-0.9, 0.9, 0.0, 1.0],
            [0.9, 0.9, 0.0, 1.0],
            [0.0, -0.9, 0.0, 1.0],
        ]
    )
    faces = torch.tensor([[0, 1, 2], [0, 0, 1], [3, 4, 5]])
    fragments = rasterize(clip, faces, (16, 16))
    covered = fragments.tri_id[fragments.tri_id >= 0]
    assert bool((covered == 2).all()) and covered.numel() > 50
    assert bool(torch.isfinite(fragments.barycentrics).all())


def test_everything_behind_the_camera_is_background():
    clip = torch.tensor([[-0.5, -0.5, 0.0, -1.0], [0.5, -0.5, 0.0, -1.0], [0.0, 0.5, 0.0, -1.0]])
    fragments = rasterize(clip, torch.tensor([[0, 1, 2]]), (8, 8))
    assert bool((fragments.tri_id == -1).all())


def test_screen_boxes_of_triangles_in_front_match_the_general_path():
    """Triangles wholly in front take the short path (their vertices' box); it gives the box
    the general path (vertices plus near-plane crossings, none here) gives."""
    from recon.render.rasterize import _pixel_ranges, _screen_bounds

    generator = torch.Generator().manual_seed(4)
    triangles = torch.rand(2, 50, 3, 4, generator=generator) * 2.4 - 1.2
    triangles[..., 3] = 0.5 + torch.rand(2, 50, 3, generator=generator)
    triangles[0, :5, :, 0] = 3.0 * triangles[0, :5, :, 3]  # wholly right of the image
    valid = torch.ones(2, 50, 3, dtype=torch.bool)
    general = _pixel_ranges(triangles, valid, 24, 32)
    assert torch.equal(_screen_bounds(triangles, 24, 32), general)
    # Boxes reaching past the image are clamped to it, and some are empty (x1 < x0).
    assert int(general[..., 0].min()) >= 0 and int(general[..., 1].max()) <= 31
    assert bool((general[..., 1] < general[..., 0]).any())
