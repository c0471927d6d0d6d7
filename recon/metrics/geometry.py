"""Geometry metrics: Chamfer, normal consistency, F1, Hausdorff; mesh statistics; per-vertex error.

All distances are in units of the REFERENCE mesh's bounding-box diagonal: both meshes are
translated by the reference's bounding-box centre and divided by its diagonal (one transform
for both, so relative placement is kept). The bounding box is that of the vertices the faces use.

Two ways to measure the nearest distance of a surface sample to the other mesh:

- approximate (default, exact=False): to the nearest of the other mesh's SAMPLES (a KD-tree,
  scipy cKDTree). Fast, but it has a floor from the sampling density: even a mesh against itself
  scores above 0, because the nearest of N independent uniform samples on area A lies about
  0.5 * sqrt(A / N) away (the mean nearest-neighbour distance of a planar Poisson process of
  density N / A; the mean squared distance is A / (pi N)). For an object with area A ~ 1 in
  diagonal units and N = 100k that floor is ~1.6e-3, the same order as good reconstructions, so
  small differences between good results are not resolved in this mode. The floor is returned
  as `sampling_floor` (the expected chamfer_l1 of a perfect reconstruction).
- exact (exact=True): to the other mesh's SURFACE (point-to-triangle, trimesh.proximity.
  closest_point, an rtree of triangles). No floor: a mesh against itself scores 0. Slower (a few
  seconds per 100k samples against ~20k faces); use it for the numbers that get reported. Per
  sample, the exact distance d and the approximate one are related by approx ~ sqrt(d^2 + rho^2)
  with rho the in-surface distance to the nearest sample, so 0 <= approx - exact <~ floor.

Samples are drawn uniformly by area with a seeded numpy generator (the two meshes get
independent streams spawned from `seed`), each with the unit normal of the face it lies on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from recon.errors import ReconError
from recon.mesh.mesh import Mesh

DEFAULT_THRESHOLDS = (0.005, 0.01, 0.02)
# A face counts as degenerate when its area is at most this times the squared bbox diagonal:
# float32 vertices of an exactly collinear triple round to an area of that order, not to 0.
DEGENERATE_AREA_RATIO = 1e-12
# closest_point works on chunks of query points to bound the memory of its candidate lists.
_CLOSEST_POINT_CHUNK = 10_000


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------


def _check_mesh(mesh: Mesh, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(verts [V, 3] float64, faces [F, 3] int64) numpy arrays of a non-empty Mesh."""
    if not isinstance(mesh, Mesh):
        raise ReconError(f"{name}: expected a recon Mesh, got {type(mesh).__name__}")
    if mesh.faces.shape[0] == 0 or mesh.verts.shape[0] == 0:
        raise ReconError(
            f"{name}: mesh is empty ({mesh.verts.shape[0]} vertices, {mesh.faces.shape[0]} faces)"
        )
    verts = mesh.verts.detach().to("cpu", torch.float64).numpy()
    faces = mesh.faces.detach().to("cpu", torch.int64).numpy()
    return verts, faces


def _check_pair(predicted: Mesh, reference: Mesh) -> None:
    for name, mesh in (("predicted", predicted), ("reference", reference)):
        if not isinstance(mesh, Mesh):
            raise ReconError(f"{name}: expected a recon Mesh, got {type(mesh).__name__}")
    if predicted.device != reference.device:
        raise ReconError(
            f"reference: on device {reference.device}, but predicted is on {predicted.device}"
        )


def _face_areas_and_normals(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas [F] and unit normals [F, 3] (zero for zero-area faces) of a triangle mesh."""
    corners = verts[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    doubled = np.linalg.norm(cross, axis=1)
    normals = np.divide(
        cross, doubled[:, None], out=np.zeros_like(cross), where=doubled[:, None] > 0
    )
    return 0.5 * doubled, normals


def _normalisation(
    reference_verts: np.ndarray, reference_faces: np.ndarray
) -> tuple[np.ndarray, float]:
    """(centre [3], diagonal) of the bounding box of the vertices the reference's faces use."""
    used = reference_verts[np.unique(reference_faces)]
    low, high = used.min(axis=0), used.max(axis=0)
    diagonal = float(np.linalg.norm(high - low))
    if not diagonal > 0:
        raise ReconError("reference: bounding box has zero diagonal (all vertices coincide)")
    return 0.5 * (low + high), diagonal


# --------------------------------------------------------------------------------------------
# Sampling and distances
# --------------------------------------------------------------------------------------------


def sample_surface(
    verts: np.ndarray, faces: np.ndarray, count: int, generator: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, float]:
    """Sample `count` points uniformly by area on a triangle mesh.

    verts: [V, 3] float64; faces: [F, 3] int64; generator: a seeded numpy Generator.
    Returns (points [count, 3], unit normals of the sampled faces [count, 3], total area).
    Zero-area faces are never picked. Raises ReconError when the total area is zero.
    """
    points, picks, _, total = sample_surface_barycentric(verts, faces, count, generator)
    _, normals = _face_areas_and_normals(verts, faces)
    return points, normals[picks], total


def sample_surface_barycentric(
    verts: np.ndarray, faces: np.ndarray, count: int, generator: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """sample_surface's samples with where they lie: (points [count, 3], face index [count],
    barycentric weights [count, 3] of the face's corners, total area). The same generator
    draws give the same points as sample_surface."""
    areas, _ = _face_areas_and_normals(verts, faces)
    cumulative = np.cumsum(areas)
    total = float(cumulative[-1])
    if not total > 0:
        raise ReconError("mesh has zero surface area (every face is degenerate)")
    # Inverse-CDF pick of faces by area (what rng.choice(p=areas / total) does), clipped for the
    # rare uniform draw that rounds up to the total.
    picks = np.searchsorted(cumulative, generator.random(count) * total, side="right")
    picks = np.minimum(picks, len(faces) - 1)
    # Uniform barycentrics: fold the unit square's upper triangle onto the lower one.
    u, v = generator.random((2, count))
    folded = u + v > 1.0
    u[folded], v[folded] = 1.0 - u[folded], 1.0 - v[folded]
    corners = verts[faces[picks]]
    points = (
        corners[:, 0]
        + u[:, None] * (corners[:, 1] - corners[:, 0])
        + v[:, None] * (corners[:, 2] - corners[:, 0])
    )
    weights = np.stack([1.0 - u - v, u, v], axis=1)
    return points, picks, weights, total


def _surface_query(verts: np.ndarray, faces: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A trimesh for exact point-to-surface queries, and its unit face normals [F', 3].

    Degenerate faces are dropped (they add no surface, and their zero normal would spoil normal
    consistency) and so are unreferenced vertices: trimesh bounds its triangle search by the
    nearest VERTEX, so a stray vertex near a query point would leave it no candidate triangle.
    """
    areas, _ = _face_areas_and_normals(verts, faces)
    extent = np.ptp(verts[np.unique(faces)], axis=0)
    keep = areas > DEGENERATE_AREA_RATIO * float(extent @ extent)
    faces = faces[keep]
    used, compact = np.unique(faces, return_inverse=True)
    mesh = trimesh.Trimesh(verts[used], compact.reshape(-1, 3), process=False, validate=False)
    _, normals = _face_areas_and_normals(mesh.vertices, mesh.faces)
    return mesh, normals


def _distances_to_surface(
    points: np.ndarray, surface: trimesh.Trimesh
) -> tuple[np.ndarray, np.ndarray]:
    """Exact distances [N] of points [N, 3] to a triangle surface, and the nearest face [N]."""
    distances = np.empty(len(points))
    triangles = np.empty(len(points), dtype=np.int64)
    for start in range(0, len(points), _CLOSEST_POINT_CHUNK):
        stop = start + _CLOSEST_POINT_CHUNK
        _, distances[start:stop], triangles[start:stop] = trimesh.proximity.closest_point(
            surface, points[start:stop]
        )
    return distances, triangles


def _nearest(
    points: np.ndarray,
    normals: np.ndarray,
    other_points: np.ndarray,
    other_normals: np.ndarray,
    other_surface: tuple[trimesh.Trimesh, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest distances [N] and |cos| [N] between each sample normal and its nearest normal.

    With other_surface (exact mode) the nearest is the closest point on that surface and its
    face's normal; otherwise the nearest of other_points and its normal.
    """
    if other_surface is not None:
        surface, face_normals = other_surface
        distances, triangles = _distances_to_surface(points, surface)
        nearest_normals = face_normals[triangles]
    else:
        distances, indices = cKDTree(other_points).query(points, k=1, workers=-1)
        nearest_normals = other_normals[indices]
    cosines = np.abs(np.einsum("ij,ij->i", normals, nearest_normals))
    return distances, cosines


def _threshold_label(threshold: float) -> str:
    """0.005 -> '0.5%', 0.01 -> '1%' (the threshold as a percentage of the diagonal)."""
    return f"{threshold * 100:g}%"


def geometry_metrics(
    predicted: Mesh,
    reference: Mesh,
    samples: int = 100_000,
    seed: int = 0,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    exact: bool = False,
) -> dict[str, float | int]:
    """Surface-sample metrics of a predicted mesh against a reference, in reference diagonals.

    predicted, reference: Mesh (any device; the work is done on the CPU in float64).
    samples: points sampled per mesh; seed: makes the result deterministic; thresholds: F1
    distances as fractions of the reference diagonal; exact: point-to-surface distances instead
    of point-to-sample (see the module docstring; no sampling floor, slower).

    Keys (distances in units of the reference's bounding-box diagonal):
      chamfer_l1: mean over both directions of the mean nearest distance;
      chamfer_l2: the same with squared distances;
      accuracy / completeness: the mean nearest distance predicted -> reference and
          reference -> predicted (the two halves of chamfer_l1);
      normal_consistency: mean over both directions of the mean |cos| between a sample's face
          normal and its nearest neighbour's (orientation-blind, so flipped winding scores 1);
      precision@T, recall@T, f1@T for each threshold (T printed as a percentage, e.g. '1%'):
          share of predicted samples within T of the reference, share of reference samples
          within T of the prediction, and their harmonic mean (0 when both are 0);
      hausdorff: the largest nearest distance in either direction (approximate mode adds up to
          the largest gap between samples, so prefer exact mode for it);
      hausdorff_p95: the larger of the two directions' 95th percentiles;
      sampling_floor: the expected chamfer_l1 of a perfect reconstruction in this mode
          (0.25 * (sqrt(A_ref / N) + sqrt(A_pred / N)) approximate, 0 exact);
      samples: N; reference_diagonal: the diagonal in the meshes' own units (to convert back).
    """
    _check_pair(predicted, reference)
    predicted_verts, predicted_faces = _check_mesh(predicted, "predicted")
    reference_verts, reference_faces = _check_mesh(reference, "reference")
    if int(samples) < 1:
        raise ReconError(f"samples: expected a positive count, got {samples}")
    samples = int(samples)
    thresholds = tuple(float(threshold) for threshold in thresholds)
    if not all(threshold > 0 for threshold in thresholds):
        raise ReconError(
            f"thresholds: expected positive fractions of the diagonal, got {thresholds}"
        )

    centre, diagonal = _normalisation(reference_verts, reference_faces)
    predicted_verts = (predicted_verts - centre) / diagonal
    reference_verts = (reference_verts - centre) / diagonal

    predicted_stream, reference_stream = np.random.SeedSequence(seed).spawn(2)
    sampled = {}
    for name, verts, faces, stream in (
        ("predicted", predicted_verts, predicted_faces, predicted_stream),
        ("reference", reference_verts, reference_faces, reference_stream),
    ):
        try:
            sampled[name] = sample_surface(verts, faces, samples, np.random.default_rng(stream))
        except ReconError as error:
            raise ReconError(f"{name}: {error}") from error
    predicted_points, predicted_normals, predicted_area = sampled["predicted"]
    reference_points, reference_normals, reference_area = sampled["reference"]

    predicted_surface = reference_surface = None
    if exact:
        predicted_surface = _surface_query(predicted_verts, predicted_faces)
        reference_surface = _surface_query(reference_verts, reference_faces)
    forward, forward_cosines = _nearest(
        predicted_points, predicted_normals, reference_points, reference_normals, reference_surface
    )
    backward, backward_cosines = _nearest(
        reference_points, reference_normals, predicted_points, predicted_normals, predicted_surface
    )

    results: dict[str, float | int] = {
        "chamfer_l1": 0.5 * float(forward.mean() + backward.mean()),
        "chamfer_l2": 0.5 * float((forward**2).mean() + (backward**2).mean()),
        "accuracy": float(forward.mean()),
        "completeness": float(backward.mean()),
        "normal_consistency": 0.5 * float(forward_cosines.mean() + backward_cosines.mean()),
    }
    for threshold in thresholds:
        label = _threshold_label(threshold)
        precision = float((forward < threshold).mean())
        recall = float((backward < threshold).mean())
        total = precision + recall
        results[f"precision@{label}"] = precision
        results[f"recall@{label}"] = recall
        results[f"f1@{label}"] = 2.0 * precision * recall / total if total > 0 else 0.0
    results["hausdorff"] = float(max(forward.max(), backward.max()))
    results["hausdorff_p95"] = float(
        max(np.percentile(forward, 95.0), np.percentile(backward, 95.0))
    )
    results["sampling_floor"] = (
        0.0 if exact else sampling_floor(reference_area, samples, predicted_area)
    )
    results["samples"] = samples
    results["reference_diagonal"] = diagonal
    return results


def sampling_floor(
    reference_area: float, samples: int, predicted_area: float | None = None
) -> float:
    """Expected approximate-mode chamfer_l1 of a perfect reconstruction (areas in diagonal^2).

    Each direction's nearest-sample distance on a surface of area A holding N uniform samples
    averages 0.5 * sqrt(A / N) (planar Poisson process); chamfer_l1 averages the two directions.
    """
    predicted_area = reference_area if predicted_area is None else predicted_area
    return 0.25 * (math.sqrt(reference_area / samples) + math.sqrt(predicted_area / samples))


def per_vertex_error(predicted: Mesh, reference: Mesh) -> torch.Tensor:
    """Distance of each predicted vertex to the reference SURFACE, in reference diagonals.

    Returns [V] float32 on predicted's device (for colouring the predicted mesh in reports).
    Exact point-to-triangle distances (trimesh.proximity.closest_point).
    """
    _check_pair(predicted, reference)
    predicted_verts, _ = _check_mesh(predicted, "predicted")
    reference_verts, reference_faces = _check_mesh(reference, "reference")
    centre, diagonal = _normalisation(reference_verts, reference_faces)
    surface, _ = _surface_query((reference_verts - centre) / diagonal, reference_faces)
    if len(surface.faces) == 0:
        raise ReconError("reference: mesh has zero surface area (every face is degenerate)")
    distances, _ = _distances_to_surface((predicted_verts - centre) / diagonal, surface)
    return torch.from_numpy(distances).to(device=predicted.device, dtype=torch.float32)


# --------------------------------------------------------------------------------------------
# Mesh statistics
# --------------------------------------------------------------------------------------------


def _vertex_fans(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """Number of separate face fans [V] around each vertex (0 unused, 1 manifold, > 1 pinched).

    Nodes are face corners (face f, corner c); two corners of the same vertex are joined when
    their faces share an edge through that vertex. A manifold vertex (interior or on the boundary)
    has all its corners in one fan; a vertex where two surfaces touch at a point has several.
    """
    face_count = len(faces)
    corner_ids = np.arange(3 * face_count).reshape(face_count, 3)
    centres, others, ids = [], [], []
    for corner in range(3):
        for step in (1, 2):  # the two edges of the face through this corner
            centres.append(faces[:, corner])
            others.append(faces[:, (corner + step) % 3])
            ids.append(corner_ids[:, corner])
    centre, other, node = (np.concatenate(parts) for parts in (centres, others, ids))
    order = np.lexsort((other, centre))
    centre, other, node = centre[order], other[order], node[order]
    # After sorting, corners on the same (vertex, edge) are adjacent: chain them together.
    same = (centre[1:] == centre[:-1]) & (other[1:] == other[:-1])
    graph = coo_matrix(
        (np.ones(int(same.sum())), (node[:-1][same], node[1:][same])),
        shape=(3 * face_count, 3 * face_count),
    )
    _, labels = connected_components(graph, directed=False)
    corner_vertex = faces.reshape(-1)
    # One (vertex, fan label) pair per fan: count the distinct pairs per vertex.
    pairs = np.unique(np.stack([corner_vertex, labels]), axis=1)
    return np.bincount(pairs[0], minlength=vertex_count)


def mesh_stats(mesh: Mesh) -> dict[str, int | float | bool | None]:
    """Topology and quality statistics of a mesh.

    Keys: vertices, faces, edges (unique undirected), unreferenced_vertices, boundary_edges
    (in one face), non_manifold_edges (in more than two), edge_manifold, non_manifold_vertices
    (whose faces form more than one fan), vertex_manifold, watertight (every edge in exactly two
    faces), winding_consistent (trimesh: each shared edge traversed in opposite directions),
    degenerate_faces (repeated index or area <= 1e-12 * diagonal^2), components (connected by
    shared vertices), euler_characteristic (V - E + F over referenced vertices), genus (total
    over components, (2 * components - chi) / 2, only for closed manifold meshes, else None;
    assumes orientable surfaces, which every closed surface embedded in 3D is), surface_area,
    bounding_box_diagonal.
    """
    verts, faces = _check_mesh(mesh, "mesh")
    vertex_count, face_count = len(verts), len(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    repeated = (
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    )
    # A face with a repeated index has a zero-length "edge" (v, v): keep it out of the edge counts.
    proper_edges = edges[edges[:, 0] != edges[:, 1]]
    unique_edges, edge_uses = np.unique(proper_edges, axis=0, return_counts=True)
    boundary_edges = int((edge_uses == 1).sum())
    non_manifold_edges = int((edge_uses > 2).sum())

    used = np.unique(faces)
    fans = _vertex_fans(faces, vertex_count)
    non_manifold_vertices = int((fans > 1).sum())

    adjacency = coo_matrix(
        (np.ones(len(unique_edges)), (unique_edges[:, 0], unique_edges[:, 1])),
        shape=(vertex_count, vertex_count),
    )
    _, labels = connected_components(adjacency, directed=False)
    components = len(np.unique(labels[used]))

    areas, _ = _face_areas_and_normals(verts, faces)
    extent = verts[used].max(axis=0) - verts[used].min(axis=0)
    diagonal = float(np.linalg.norm(extent))
    degenerate = repeated | (areas <= DEGENERATE_AREA_RATIO * diagonal**2)

    watertight = boundary_edges == 0 and non_manifold_edges == 0
    closed_manifold = watertight and non_manifold_vertices == 0
    euler = len(used) - len(unique_edges) + face_count
    genus = (2 * components - euler) // 2 if closed_manifold else None
    # trimesh's winding check works on its own edge bookkeeping; process=False keeps our indices.
    winding_consistent = bool(
        trimesh.Trimesh(verts, faces, process=False, validate=False).is_winding_consistent
    )
    return {
        "vertices": vertex_count,
        "faces": face_count,
        "edges": len(unique_edges),
        "unreferenced_vertices": vertex_count - len(used),
        "boundary_edges": boundary_edges,
        "non_manifold_edges": non_manifold_edges,
        "edge_manifold": non_manifold_edges == 0,
        "non_manifold_vertices": non_manifold_vertices,
        "vertex_manifold": non_manifold_vertices == 0,
        "watertight": watertight,
        "winding_consistent": winding_consistent,
        "degenerate_faces": int(degenerate.sum()),
        "components": components,
        "euler_characteristic": int(euler),
        "genus": None if genus is None else int(genus),
        "surface_area": float(areas.sum()),
        "bounding_box_diagonal": diagonal,
    }
