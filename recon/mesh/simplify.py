"""Mesh simplification (fast-simplification's quadric decimation) and mesh repair.

Quadric decimation can leave a few faces that the rest of recon refuses (remesh, the Laplacians
and the renderer's adjacency want an oriented manifold): zero-area slivers, doubled faces,
edges with three faces, vertices joining two fans, flipped windings. repair removes or fixes
each of these and says how many it found.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import fast_simplification
import numpy as np
import torch

from recon.errors import ReconError
from recon.mesh.topology import (
    as_numpy_faces,
    edge_adjacency,
    face_components,
    orient_faces,
    vertex_fans,
)

# Faces whose doubled area is below this fraction of the squared bounding-box diagonal count as
# zero-area: about float32 rounding of the coordinates, far below any real triangle.
DEFAULT_AREA_TOLERANCE = 1e-12


@dataclass
class RepairReport:
    """What repair found and fixed (counts)."""

    degenerate_faces_removed: int = 0  # faces repeating a vertex index
    zero_area_faces_removed: int = 0  # distinct vertices but (numerically) no area
    duplicate_faces_removed: int = 0  # same three vertices as an earlier face
    non_manifold_faces_removed: int = 0  # the smallest faces beyond two on an edge
    non_manifold_vertices_split: int = 0  # vertex copies added, one per extra fan
    unreferenced_vertices_removed: int = 0
    faces_flipped: int = 0  # to agree with their neighbours, or to face outward
    inconsistent_edges_left: int = 0  # non-orientable parts (a Moebius strip) keep these

    @property
    def changes(self) -> int:
        """Total number of fixes (0 means the mesh came back unchanged)."""
        return sum(value for key, value in asdict(self).items() if key != "inconsistent_edges_left")

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _as_numpy_verts(verts: np.ndarray | torch.Tensor) -> np.ndarray:
    """verts [V, 3] as float64 numpy."""
    if isinstance(verts, torch.Tensor):
        verts = verts.detach().cpu().numpy()
    verts = np.asarray(verts)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ReconError(f"verts: expected shape [V, 3], got {tuple(verts.shape)}")
    if not np.issubdtype(verts.dtype, np.floating):
        raise ReconError(f"verts: expected floats, got {verts.dtype}")
    return verts.astype(np.float64)


def _restore(
    verts: np.ndarray,
    faces: np.ndarray,
    original_verts: np.ndarray | torch.Tensor,
    original_faces: np.ndarray | torch.Tensor,
) -> tuple[np.ndarray | torch.Tensor, np.ndarray | torch.Tensor]:
    """(verts [V, 3], faces [F, 3] int64) in the array type, float dtype and device of the
    originals."""
    if isinstance(original_verts, torch.Tensor):
        out_verts = torch.from_numpy(np.ascontiguousarray(verts)).to(
            dtype=original_verts.dtype, device=original_verts.device
        )
    else:
        out_verts = verts.astype(np.asarray(original_verts).dtype)
    out_faces = np.ascontiguousarray(faces, dtype=np.int64)
    if isinstance(original_faces, torch.Tensor):
        out_faces = torch.from_numpy(out_faces).to(device=original_faces.device)
    return out_verts, out_faces


def simplify(
    verts: np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor,
    target_faces: int | None = None,
    target_reduction: float | None = None,
    aggressiveness: float = 7.0,
    repair_result: bool = True,
) -> tuple[np.ndarray | torch.Tensor, np.ndarray | torch.Tensor]:
    """Quadric-error decimation to about target_faces faces (or by target_reduction in [0, 1),
    the fraction of faces to remove), via fast_simplification.simplify.

    verts: [V, 3] float; faces: [F, 3] integer. Give exactly one target.
    aggressiveness: fast-simplification's `agg` (0 keeps shape best but may stop short of the
        target, 10 is fastest; 7 is its default).
    repair_result: run repair on the output (recommended: decimation can leave slivers and
        non-manifold spots); the face count then may fall a little below the target.
    Returns (verts [V', 3], faces [F', 3] int64) in the input's array type, dtype and device.
    """
    positions = _as_numpy_verts(verts)
    index = as_numpy_faces(faces)
    face_count = index.shape[0]
    if (target_faces is None) == (target_reduction is None):
        raise ReconError("simplify: give exactly one of target_faces and target_reduction")
    if target_reduction is not None:
        if not 0 <= target_reduction < 1:
            raise ReconError(
                f"target_reduction: expected a value in [0, 1), got {target_reduction}"
            )
        target_faces = int(round((1 - target_reduction) * face_count))
    if target_faces <= 0:
        raise ReconError(f"target_faces: expected a positive count, got {target_faces}")
    if target_faces < face_count:
        positions, index = fast_simplification.simplify(
            positions, index, target_count=int(target_faces), agg=float(aggressiveness)
        )
        positions = np.asarray(positions, dtype=np.float64)
        index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
    if repair_result:
        positions, index, _ = repair(positions, index)
    return _restore(positions, index, verts, faces)


def repair(
    verts: np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor,
    area_tolerance: float = DEFAULT_AREA_TOLERANCE,
) -> tuple[np.ndarray | torch.Tensor, np.ndarray | torch.Tensor, RepairReport]:
    """Make a triangle soup into an oriented manifold mesh, reporting each fix.

    In order: drop faces repeating a vertex, faces of (numerically) zero area (doubled area
    below area_tolerance x the squared bounding-box diagonal) and repeated faces (same three
    vertices in any order); on edges with more than two faces keep the two largest; make the
    winding agree across every edge (breadth-first over faces) and point closed parts outward
    (positive signed volume); give every extra fan of faces at a non-manifold vertex its own
    copy of the vertex; drop unreferenced vertices.

    verts: [V, 3] float; faces: [F, 3] integer.
    Returns (verts [V', 3], faces [F', 3] int64, report), arrays in the input's type, dtype and
    device. Removing faces can open holes; nothing here fills them.
    """
    positions = _as_numpy_verts(verts)
    index = as_numpy_faces(faces)
    if index.size and index.max() >= positions.shape[0]:
        raise ReconError(
            f"faces: index {int(index.max())} out of range for {positions.shape[0]} verts"
        )
    report = RepairReport()

    repeats = (
        (index[:, 0] == index[:, 1]) | (index[:, 1] == index[:, 2]) | (index[:, 2] == index[:, 0])
    )
    report.degenerate_faces_removed = int(repeats.sum())
    index = index[~repeats]

    diagonal_squared = float(np.sum(np.ptp(positions, axis=0) ** 2)) if len(positions) else 0.0
    doubled_area = _doubled_areas(positions, index)
    flat = doubled_area <= area_tolerance * diagonal_squared
    report.zero_area_faces_removed = int(flat.sum())
    index, doubled_area = index[~flat], doubled_area[~flat]

    _, first = np.unique(np.sort(index, axis=1), axis=0, return_index=True)
    first = np.sort(first)
    report.duplicate_faces_removed = len(index) - len(first)
    index, doubled_area = index[first], doubled_area[first]

    index, removed = _drop_non_manifold_faces(index, doubled_area, positions.shape[0])
    report.non_manifold_faces_removed = removed

    index, flipped = orient_faces(index)
    index, inverted = _orient_outward(positions, index)
    report.faces_flipped = flipped + inverted

    positions, index, copies = _split_non_manifold_vertices(positions, index)
    report.non_manifold_vertices_split = copies

    used = np.zeros(len(positions), dtype=bool)
    used[index.reshape(-1)] = True
    report.unreferenced_vertices_removed = int((~used).sum())
    new_index = np.cumsum(used) - 1
    positions, index = positions[used], new_index[index]

    report.inconsistent_edges_left = _inconsistent_edge_count(index)
    out_verts, out_faces = _restore(positions, index, verts, faces)
    return out_verts, out_faces, report


def _doubled_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F] twice the area of each face."""
    corners = verts[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.linalg.norm(normal, axis=-1)


def _drop_non_manifold_faces(
    faces: np.ndarray, doubled_area: np.ndarray, vertex_count: int
) -> tuple[np.ndarray, int]:
    """Keep the two largest faces on each edge with more than two; returns (faces, removed)."""
    if not len(faces):
        return faces, 0
    adjacency = edge_adjacency(faces, vertex_count)
    crowded = adjacency.edge_face_count > 2
    if not crowded.any():
        return faces, 0
    face_index = np.repeat(np.arange(len(faces)), 3)
    edge = adjacency.face_edges.reshape(-1)
    on_crowded = crowded[edge]
    edge, face_index = edge[on_crowded], face_index[on_crowded]
    # Within each crowded edge, largest area first (face index breaks ties, for determinism).
    order = np.lexsort((face_index, -doubled_area[face_index], edge))
    edge, face_index = edge[order], face_index[order]
    group_start = np.flatnonzero(np.r_[True, edge[1:] != edge[:-1]])
    rank = np.arange(len(edge)) - np.repeat(group_start, np.diff(np.r_[group_start, len(edge)]))
    drop = np.zeros(len(faces), dtype=bool)
    drop[face_index[rank >= 2]] = True
    return faces[~drop], int(drop.sum())


def _orient_outward(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Flip closed face-components with negative signed volume; returns (faces, flipped)."""
    if not len(faces):
        return faces, 0
    adjacency = edge_adjacency(faces, len(verts))
    component_count, label = face_components(faces, through_edges=True)
    # A component is closed when none of its edges is a boundary edge.
    open_edge = adjacency.edge_face_count != 2
    face_open = open_edge[adjacency.face_edges].any(axis=1)
    component_open = np.bincount(label, weights=face_open, minlength=component_count) > 0
    corners = verts[faces]
    # Signed volume of the tetrahedra with the origin (times 6), summed per component.
    volume = np.einsum("fc,fc->f", corners[:, 0], np.cross(corners[:, 1], corners[:, 2]))
    component_volume = np.bincount(label, weights=volume, minlength=component_count)
    invert = (~component_open) & (component_volume < 0)
    flip = invert[label]
    faces = faces.copy()
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces, int(flip.sum())


def _split_non_manifold_vertices(
    verts: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Give each fan beyond the first at a vertex its own copy of the vertex; returns (verts,
    faces, copies added)."""
    if not len(faces):
        return verts, faces, 0
    corner_fan, fan_count = vertex_fans(faces, len(verts))
    if np.all(fan_count <= 1):
        return verts, faces, 0
    flat = faces.reshape(-1)
    fan = corner_fan.reshape(-1)
    # One row per (vertex, fan), sorted by vertex then fan; the first fan of each vertex keeps it.
    pair_key = flat * (fan.max() + 1) + fan
    unique_key, pair_of_corner = np.unique(pair_key, return_inverse=True)
    pair_vertex = unique_key // (fan.max() + 1)
    keeps = np.r_[True, pair_vertex[1:] != pair_vertex[:-1]]
    new_vertex = np.where(keeps, pair_vertex, 0)
    copies = int((~keeps).sum())
    new_vertex[~keeps] = len(verts) + np.arange(copies)
    verts = np.concatenate([verts, verts[pair_vertex[~keeps]]])
    return verts, new_vertex[pair_of_corner].reshape(-1, 3), copies


def _inconsistent_edge_count(faces: np.ndarray) -> int:
    """Edges whose two faces traverse them in the same direction."""
    if not len(faces):
        return 0
    adjacency = edge_adjacency(faces)
    pair = adjacency.edge_half_edges[adjacency.edge_face_count == 2]
    flat = faces.reshape(-1)
    return int(np.sum(flat[pair[:, 0]] == flat[pair[:, 1]]))
