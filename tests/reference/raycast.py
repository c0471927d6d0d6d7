"""A naive per-pixel reference rasterizer: one ray per pixel centre, Moller-Trumbore in float64.

Deliberately unlike recon's rasterizer (camera-space rays instead of homogeneous edge functions,
Python-level loop over triangles, numpy float64), so agreement means something.
"""

from __future__ import annotations

import numpy as np
import torch

from recon.camera import Cameras


def pixel_rays(cameras: Cameras, view: int) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origin [3] and unnormalised directions [H, W, 3] through pixel centres,
    scaled so that the camera-space z of origin + t * direction equals t."""
    height, width = cameras.image_size
    intrinsics = cameras.intrinsics[view].double().cpu().numpy()
    world_to_cam = cameras.world_to_cam[view].double().cpu().numpy()
    rows, columns = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    pixels = np.stack([columns, rows, np.ones_like(rows)], -1)
    directions_cam = pixels @ np.linalg.inv(intrinsics).T  # z component = 1
    rotation = world_to_cam[:3, :3]
    origin = -rotation.T @ world_to_cam[:3, 3]
    return origin, directions_cam @ rotation  # rotation.T applied to each row vector


def raycast(
    verts_world: torch.Tensor, faces: torch.Tensor, cameras: Cameras, view: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """tri_id [H, W] (-1 background), barycentrics (u, v) [H, W, 2], camera depth z [H, W].

    Hits are kept between the cameras' near and far planes; ties go to the lower triangle id.
    """
    height, width = cameras.image_size
    origin, directions = pixel_rays(cameras, view)
    verts = verts_world.double().cpu().numpy()
    tri_id = np.full((height, width), -1, dtype=np.int64)
    best_t = np.full((height, width), np.inf)
    bary = np.zeros((height, width, 2))
    for face_index, (a, b, c) in enumerate(faces.cpu().numpy()):
        p0, p1, p2 = verts[a], verts[b], verts[c]
        edge1, edge2 = p1 - p0, p2 - p0
        pvec = np.cross(directions, edge2)
        det = pvec @ edge1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_det = 1.0 / det
            tvec = origin - p0
            # barycentric weights of p1 and p2
            w1 = (pvec @ tvec) * inv_det
            qvec = np.cross(tvec, edge1)
            w2 = (directions @ qvec) * inv_det
            t = (edge2 @ qvec) * inv_det
        hit = (
            (np.abs(det) > 1e-14)
            & (w1 >= 0)
            & (w2 >= 0)
            & (w1 + w2 <= 1)
            & (t >= cameras.near)
            & (t <= cameras.far)
            & (t < best_t)
        )
        tri_id[hit] = face_index
        best_t[hit] = t[hit]
        # recon's (u, v) are the weights of the first two vertices: u = 1 - w1 - w2, v = w1.
        bary[hit, 0] = 1 - w1[hit] - w2[hit]
        bary[hit, 1] = w1[hit]
    depth = np.where(tri_id >= 0, best_t, 0.0)
    return tri_id, bary, depth


def supersampled_render(render_function, resolution: tuple[int, int], factor: int) -> torch.Tensor:
    """Area-integrated image [B, H, W, C]: render at factor x resolution and box-average.

    render_function(resolution) -> [B, H, W, C] point-sampled (no antialias) image.
    """
    height, width = resolution
    fine = render_function((height * factor, width * factor))
    pooled = torch.nn.functional.avg_pool2d(fine.permute(0, 3, 1, 2), factor)
    return pooled.permute(0, 2, 3, 1)
