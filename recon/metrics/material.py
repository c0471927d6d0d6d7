"""Fitted material against the true one over the surface (a `pbr` fit on a synthetic world).

The fitted roughness/metalness maps live on the fitted mesh's own UVs (xatlas), the true maps
on the reference mesh's UVs, so texels cannot be compared directly. The comparison goes through
a surface correspondence instead:

1. points are sampled uniformly by area on the FITTED surface (seeded; each with its face and
   barycentric weights, recon.metrics.geometry.sample_surface_barycentric);
2. each point's closest point on the REFERENCE surface is found exactly (point-to-triangle,
   trimesh.proximity.closest_point), with its face and barycentric weights
   (trimesh.triangles.points_to_barycentric);
3. the fitted maps are read (bilinearly, recon.render.texture) at the sample's UV, the true maps
   at the closest point's UV.

Samples whose closest reference point is farther than max_distance (in reference diagonals)
compare material at the wrong place (a geometry error, not a material one) and are left out;
so, when the training views are given, are samples no training view saw (their material is the
fit's regulariser, not a measurement). metrics.json's `material` section says how many were
kept.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.metrics.geometry import DEGENERATE_AREA_RATIO, sample_surface_barycentric
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import rasterize
from recon.render.texture import texture

# The channels of a material map [h, w, C >= 2] that are compared, in order.
MATERIAL_CHANNELS = ("roughness", "metalness")
# trimesh.proximity.closest_point runs on chunks of queries to bound its candidate lists.
_CLOSEST_POINT_CHUNK = 10_000


def _uv_at(mesh: Mesh, face: np.ndarray, weights: np.ndarray, name: str) -> np.ndarray:
    """UVs [N, 2] (v = 0 at the top of the image) at barycentric weights [N, 3] of faces [N]."""
    if mesh.uvs is None or mesh.uv_faces is None:
        raise ReconError(f"{name}: the mesh has no UVs to read its material maps at")
    uvs = mesh.uvs.detach().to("cpu", torch.float64).numpy()
    uv_faces = mesh.uv_faces.detach().to("cpu", torch.int64).numpy()
    return np.einsum("nk,nkc->nc", weights, uvs[uv_faces[face]])


def sample_maps(maps: torch.Tensor, uv: np.ndarray) -> torch.Tensor:
    """Bilinear lookups [N, C] of a material map [h, w, C] at uv [N, 2] (clamped at the edge)."""
    coordinates = torch.as_tensor(uv, dtype=torch.float32).reshape(1, 1, -1, 2)
    return texture(maps.detach().cpu().float(), coordinates, filter="linear", boundary="clamp")[
        0, 0
    ]


def closest_reference_points(
    points: np.ndarray, reference: Mesh
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For points [N, 3]: (distance [N], reference face [N], barycentric weights [N, 3]) of the
    closest point on the reference's surface. Degenerate faces and unused vertices are left out
    of the search (trimesh bounds its triangle search by the nearest vertex); the faces returned
    index reference.faces."""
    verts = reference.verts.detach().to("cpu", torch.float64).numpy()
    faces = reference.faces.detach().to("cpu", torch.int64).numpy()
    corners = verts[faces]
    doubled = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    extent = np.ptp(verts[np.unique(faces)], axis=0)
    kept = np.flatnonzero(0.5 * doubled > DEGENERATE_AREA_RATIO * float(extent @ extent))
    used, compact = np.unique(faces[kept], return_inverse=True)
    surface = trimesh.Trimesh(verts[used], compact.reshape(-1, 3), process=False, validate=False)
    closest = np.empty_like(points)
    distance = np.empty(len(points))
    triangle = np.empty(len(points), dtype=np.int64)
    for start in range(0, len(points), _CLOSEST_POINT_CHUNK):
        stop = start + _CLOSEST_POINT_CHUNK
        closest[start:stop], distance[start:stop], triangle[start:stop] = (
            trimesh.proximity.closest_point(surface, points[start:stop])
        )
    weights = trimesh.triangles.points_to_barycentric(surface.triangles[triangle], closest)
    # Rounding can put a closest point a hair outside its triangle.
    weights = np.clip(weights, 0.0, 1.0)
    weights /= weights.sum(axis=1, keepdims=True)
    return distance, kept[triangle], weights


def seen_points(
    points: np.ndarray,
    mesh: Mesh,
    cameras,
    depth_tolerance: float = 0.02,
    views_per_batch: int = 4,
) -> np.ndarray:
    """[N] bool: which points [N, 3] (on mesh's surface) some view of cameras (a recon Cameras
    batch) sees: the point projects inside the image, in front of the camera, and no farther
    than the mesh's depth at that pixel (camera z, the rasterizer's nearest surface) plus
    depth_tolerance times that depth. Per point, not per face: faces smaller than a pixel, which
    may cover no pixel centre, are still seen where they are in view."""
    seen = np.zeros(len(points), dtype=bool)
    verts = mesh.verts.detach().to(cameras.device, torch.float32)
    faces = mesh.faces.to(cameras.device)
    queries = torch.as_tensor(points, dtype=torch.float32, device=cameras.device)
    height, width = cameras.image_size
    with torch.no_grad():
        for start in range(0, len(cameras), views_per_batch):
            batch = cameras[start : start + views_per_batch]
            clip = batch.project_to_clip(verts)
            fragments = rasterize(clip, faces, (height, width))
            # Clip w is the camera z (OpenCV: +z forward); the nearest surface's, per pixel.
            surface = interpolate_packed(clip[..., 3:4], fragments, faces)[:, 0]
            depth = torch.full((len(batch) * height * width,), -1.0, device=cameras.device)
            depth[fragments.covered_index] = surface
            projected = batch.project_to_clip(queries)  # [B, N, 4]
            z = projected[..., 3]
            pixels = batch.project_to_pixels(queries).floor().long()
            column, row = pixels[..., 0], pixels[..., 1]
            inside = (z > 0) & (column >= 0) & (column < width) & (row >= 0) & (row < height)
            view = torch.arange(len(batch), device=cameras.device)[:, None].expand_as(z)
            flat = (view * height + row.clamp(0, height - 1)) * width + column.clamp(0, width - 1)
            nearest = depth[flat]
            visible = inside & (nearest > 0) & (z <= nearest * (1 + depth_tolerance))
            seen |= visible.any(0).cpu().numpy()
    return seen


def _channel_errors(fitted: torch.Tensor, true: torch.Tensor, tolerance: float) -> dict:
    error = (fitted - true).abs()
    return {
        "mae": float(error.mean()),
        "median_error": float(error.median()),
        "within_tolerance": float((error <= tolerance).double().mean()),
        "bias": float((fitted - true).mean()),
        "fitted_median": float(fitted.median()),
        "true_median": float(true.median()),
        # What the best uniform map (the true median) would score: the bar a fit that
        # resolves the variation must beat.
        "uniform_mae": float((true - true.median()).abs().mean()),
    }


def material_metrics(
    fitted: Mesh,
    fitted_maps: torch.Tensor,
    reference: Mesh,
    reference_maps: torch.Tensor,
    samples: int = 50_000,
    seed: int = 0,
    tolerance: float = 0.05,
    max_distance: float = 0.01,
    seen_from=None,
    depth_tolerance: float = 0.02,
) -> dict:
    """The fitted roughness and metalness against the true ones over the surface (module
    docstring): per channel the mean and median absolute error, the fraction of samples within
    tolerance, the mean signed error (bias), both medians and the MAE a uniform map at the true
    median would have (uniform_mae), as flat keys
    (`roughness_mae`, `metalness_within_tolerance`, ...); plus the samples drawn, the fraction
    kept and why others were not.

    fitted / reference: meshes with UVs in one frame; fitted_maps [h, w, >= 2] and
    reference_maps [h', w', >= 2]: roughness, metalness on their mesh's UVs. max_distance is in
    units of the reference's bounding-box diagonal. seen_from: the training views' Cameras
    (samples none of them sees are left out, seen_points with depth_tolerance) or None to keep
    unseen surface. Raises ReconError when no sample is left to compare.
    """
    for name, maps in (("fitted_maps", fitted_maps), ("reference_maps", reference_maps)):
        if maps.ndim != 3 or maps.shape[-1] < 2:
            raise ReconError(
                f"material_metrics: {name}: expected [h, w, >= 2] (roughness, metalness), got "
                f"{tuple(maps.shape)}"
            )
    verts = fitted.verts.detach().to("cpu", torch.float64).numpy()
    faces = fitted.faces.detach().to("cpu", torch.int64).numpy()
    generator = np.random.default_rng(seed)
    points, face, weights, _ = sample_surface_barycentric(verts, faces, samples, generator)
    distance, reference_face, reference_weights = closest_reference_points(points, reference)
    reference_verts = reference.verts.detach().to("cpu", torch.float64).numpy()
    used = reference_verts[np.unique(reference.faces.cpu().numpy())]
    diagonal = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    matched = distance <= max_distance * diagonal
    keep = matched.copy()
    seen = None
    if seen_from is not None:
        seen = seen_points(points, fitted, seen_from, depth_tolerance)
        keep &= seen
    if not keep.any():
        raise ReconError(
            f"material_metrics: none of {samples} samples is both within {max_distance} "
            "diagonals of the reference and on a seen face; the meshes do not overlap"
        )
    fitted_values = sample_maps(fitted_maps, _uv_at(fitted, face[keep], weights[keep], "fitted"))
    true_values = sample_maps(
        reference_maps,
        _uv_at(reference, reference_face[keep], reference_weights[keep], "reference"),
    )
    metrics: dict = {
        "samples": int(samples),
        "compared_fraction": float(keep.mean()),
        "matched_fraction": float(matched.mean()),
        "seen_fraction": None if seen is None else float(seen.mean()),
        "max_distance": float(max_distance),
        "tolerance": float(tolerance),
    }
    for channel, name in enumerate(MATERIAL_CHANNELS):
        errors = _channel_errors(fitted_values[:, channel], true_values[:, channel], tolerance)
        metrics.update({f"{name}_{key}": value for key, value in errors.items()})
    return metrics
