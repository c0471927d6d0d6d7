"""Initial shape from masks: space carving on a voxel grid, then marching cubes."""

from __future__ import annotations

import numpy as np
import torch
from skimage import measure

from recon.camera import Cameras
from recon.errors import ReconError, warn_user
from recon.mesh.mesh import Mesh


def carve(
    cameras: Cameras,
    masks: torch.Tensor,
    resolution: int = 64,
    radius: float | None = None,
    threshold: float = 0.5,
    chunk: int = 1 << 16,
    min_view_share: float = 0.5,
    center: torch.Tensor | None = None,
) -> tuple[torch.Tensor, float]:
    """Occupancy [R, R, R] float (1 = inside every silhouette that sees it) over the cube
    center + [-radius, radius]^3 (center [3], default the origin), and the radius used.

    masks: [B, H, W, 1] coverage. A voxel is removed when any view sees its centre outside the
    mask; views whose image does not contain the centre say nothing about it, but a voxel seen
    by fewer than min_view_share of the views is removed too: otherwise the grid's corners,
    outside most frusta, survive as blobs larger than the object.
    radius: half size of the grid; default 0.6 x the nearest camera's distance from the origin
        (cameras look at the object, so it lies well inside that ball).
    """
    if masks.ndim != 4 or masks.shape[0] != len(cameras):
        raise ReconError(
            f"masks: expected shape [{len(cameras)}, H, W, 1], got {tuple(masks.shape)}"
        )
    if radius is None:
        radius = 0.6 * float(cameras.centers().norm(dim=-1).min())
    height, width = cameras.image_size
    axis = (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * 2 - 1
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) * radius
    grid = grid.to(masks.device)
    if center is not None:
        grid = grid + torch.as_tensor(center, dtype=grid.dtype, device=grid.device)
    occupied = torch.ones(grid.shape[0], dtype=torch.bool, device=masks.device)
    mask_image = masks[..., 0] >= threshold  # [B, H, W]
    for start in range(0, grid.shape[0], chunk):
        points = grid[start : start + chunk]
        pixels = cameras.project_to_pixels(points)  # [B, N, 2]
        depth = cameras.project_to_clip(points)[..., 3]
        column = pixels[..., 0].floor().long()
        row = pixels[..., 1].floor().long()
        visible = (depth > 0) & (column >= 0) & (column < width) & (row >= 0) & (row < height)
        view = torch.arange(len(cameras), device=masks.device)[:, None].expand_as(column)
        inside = mask_image[view, row.clamp(0, height - 1), column.clamp(0, width - 1)]
        seen_enough = visible.sum(0) >= max(1, min_view_share * len(cameras))
        occupied[start : start + chunk] &= ~(visible & ~inside).any(0) & seen_enough
    return occupied.view(resolution, resolution, resolution).float(), radius


def border_share(occupancy: torch.Tensor) -> float:
    """The share of the grid's outer voxels [R, R, R] that are occupied (0 when the carved
    volume stays clear of the border)."""
    border = torch.ones_like(occupancy, dtype=torch.bool)
    border[1:-1, 1:-1, 1:-1] = False
    return float(occupancy[border].mean())


def visual_hull(
    cameras: Cameras, masks: torch.Tensor, resolution: int = 64, radius: float | None = None
) -> Mesh:
    """The carved volume as a watertight triangle mesh (marching cubes, CCW from outside)."""
    occupancy, radius = carve(cameras, masks, resolution, radius)
    volume = occupancy.cpu().numpy()
    if volume.sum() == 0:
        raise ReconError("visual hull: every voxel was carved away; are the masks empty?")
    touching = border_share(occupancy)
    if touching > 0:
        warn_user(
            f"visual hull: {touching:.0%} of the carving grid's border voxels are occupied (grid "
            f"half-size {radius:.3g} around the origin): the object is cut off there. Keep "
            "dataset.normalize.enabled true (it recentres the object), or check the masks "
            "(white = object) and the poses"
        )
    # Pad so the surface closes at the grid border; a light blur gives marching cubes a smooth
    # field instead of a staircase.
    volume = np.pad(volume, 1)
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(volume, sigma=0.8)
    verts, faces, _, _ = measure.marching_cubes(field, level=0.5)
    spacing = 2 * radius / resolution
    verts = (verts - 1 + 0.5) * spacing - radius
    # skimage orders triangles clockwise seen from the higher values (inside): flip to CCW.
    faces = faces[:, [0, 2, 1]]
    import trimesh

    mesh = trimesh.Trimesh(verts, faces, process=True)
    # Keep the largest piece: carving leaves specks where few views constrain the volume.
    pieces = mesh.split(only_watertight=False)
    if len(pieces) > 1:
        mesh = max(pieces, key=lambda piece: piece.area)
    if mesh.volume < 0:
        mesh.invert()
    return Mesh(
        torch.tensor(mesh.vertices, dtype=torch.float32, device=masks.device),
        torch.tensor(mesh.faces, dtype=torch.int64, device=masks.device),
    )
