"""Isotropic remeshing toward a target edge length, vectorised with numpy.

The loop is Botsch & Kobbelt's (2004), the one continuous remeshing (Palfinger 2022) runs
between optimisation steps: split edges longer than 4/3 of the target, collapse edges shorter
than 4/5 of it, flip edges to bring valences toward 6 (4 on the boundary), then relax vertices
tangentially toward the centroid of their one-ring (optionally projecting them back onto the
input surface).

Every operation is applied to many edges at once. Splits touch only their own faces, so all
long edges split in one pass. Collapses and flips are applied to an independent set per pass:
candidates are validated against the current mesh, then chosen by priority so that no two chosen
operations touch the same face (local maxima of the priority over the edge graph, repeated a
few rounds toward a maximal set). Because chosen operations never share a face, the checks made
on the unmodified mesh stay true when they are all applied together. Random tie-breaks come from
a seeded generator, so the output is deterministic.

Per-vertex data (albedo, optimiser moments, ...) follows the vertices through a sparse transfer
matrix [V_new, V_old]: a split midpoint gets the mean of its edge's ends, a collapsed pair gets
the weights of its merged position (mean, or the boundary end's), a relaxed vertex keeps its
own values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.spatial
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh.topology import (
    EdgeAdjacency,
    as_numpy_faces,
    csr_from_pairs,
    edge_adjacency,
    edges_one_ring,
    expand_csr,
    is_consistently_oriented,
    is_edge_manifold,
    is_vertex_manifold,
)

# Botsch & Kobbelt's thresholds: edges end within about [4/5, 4/3] x target, and because a
# collapse is refused when it would make an edge longer than the split threshold, splits and
# collapses cannot keep undoing each other.
SPLIT_RATIO = 4.0 / 3.0
COLLAPSE_RATIO = 4.0 / 5.0
# A collapse, flip or vertex move is refused when it turns any face's normal by more than
# about 72 degrees (cosine 0.3): enough to allow work on coarse curved meshes, far from a
# fold-over (cosine < 0).
_MIN_NORMAL_COSINE = 0.3
# New faces must keep twice their area above this fraction of target_length^2 (an equilateral
# triangle has 0.87), unless they were already smaller and do not shrink: no slivers are made.
_MIN_AREA_RATIO = 1e-3
# Boundary vertices where the boundary turns by more than this stay fixed in relaxation, so
# the corners of an open patch survive.
_BOUNDARY_CORNER_DEGREES = 40.0
# Rounds of local-maximum selection per pass; each round adds operations away from the ones
# already chosen.
_SELECTION_ROUNDS = 8
# Candidate triangles per point for the projection onto the input surface.
_PROJECTION_CANDIDATES = 12


@dataclass
class RemeshResult:
    """Output of remesh.

    verts: [V', 3] positions, same array type, dtype and device as the input verts.
    faces: [F', 3] int64 (torch.int64 when the input faces were a tensor), counter-clockwise.
    attributes: each input attribute [V, ...] carried to [V', ...], same type, dtype, device.
    vertex_transfer: [V', V] scipy CSR, rows summing to 1: any per-vertex quantity of the
        input (e.g. an optimiser state not passed in attributes) maps as transfer @ values.
    """

    verts: np.ndarray | torch.Tensor
    faces: np.ndarray | torch.Tensor
    attributes: dict[str, np.ndarray | torch.Tensor]
    vertex_transfer: scipy.sparse.csr_matrix


@dataclass
class _Working:
    """The mesh being remeshed: verts [V, 3] float64, faces [F, 3] int64, transfer [V, V0]."""

    verts: np.ndarray
    faces: np.ndarray
    transfer: scipy.sparse.csr_matrix


def remesh(
    verts: np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor,
    target_length: float,
    iterations: int = 3,
    attributes: dict[str, np.ndarray | torch.Tensor] | None = None,
    project_to_input: bool = False,
    *,
    relaxation_weight: float = 0.5,
    area_weighted: bool = True,
    collapse_passes: int = 4,
    flip_passes: int = 3,
    seed: int = 0,
) -> RemeshResult:
    """Remesh a manifold, consistently oriented triangle mesh toward uniform edge length.

    verts: [V, 3] float positions (numpy or torch; gradients are not tracked).
    faces: [F, 3] integer indices; edge- and vertex-manifold, consistently oriented (run
        recon.mesh.simplify.repair first otherwise). Open boundaries are allowed and kept.
    target_length: desired edge length (same units as verts).
    iterations: rounds of split, collapse, flip, relax. Each round halves edges at most once, so
        shrinking the target by 2^k needs about k + 2 rounds.
    attributes: per-vertex data {name: [V, ...] float} carried to the new vertices.
    project_to_input: after each relaxation, move vertices to the nearest point of the input
        surface (otherwise they move in their tangent plane only, which drifts slightly
        inward on convex parts).
    relaxation_weight: step toward the one-ring centroid, in (0, 1].
    area_weighted: centroid of the one-ring's face centroids weighted by area (Botsch &
        Kobbelt) instead of the plain mean of the neighbours.
    collapse_passes, flip_passes: independent-set passes per round.
    seed: for the random tie-breaks between equal priorities (output is deterministic).
    Guarantees: manifold in, manifold out; closed stays closed, genus and boundary count are
    kept; no operation turns a face by more than about 72 degrees or makes it a sliver.
    Unreferenced input vertices are dropped.
    """
    if not np.isfinite(target_length) or target_length <= 0:
        raise ReconError(f"target_length: expected a positive finite number, got {target_length}")
    if iterations < 0:
        raise ReconError(f"iterations: expected >= 0, got {iterations}")
    if not 0 < relaxation_weight <= 1:
        raise ReconError(f"relaxation_weight: expected a value in (0, 1], got {relaxation_weight}")
    input_verts = verts
    input_faces = faces
    positions = _as_numpy_positions(verts)
    index = as_numpy_faces(faces)
    vertex_count = positions.shape[0]
    if index.size and index.max() >= vertex_count:
        raise ReconError(f"faces: index {int(index.max())} out of range for {vertex_count} verts")
    _check_manifold(index, vertex_count)
    attribute_values = _prepare_attributes(attributes, vertex_count)

    working = _Working(
        positions.copy(), index.copy(), scipy.sparse.identity(vertex_count, format="csr")
    )
    _drop_unreferenced(working)
    projector = _SurfaceProjector(positions, index) if project_to_input else None
    generator = np.random.default_rng(seed)
    max_length = SPLIT_RATIO * target_length
    min_length = COLLAPSE_RATIO * target_length
    area_floor = _MIN_AREA_RATIO * target_length**2
    for _ in range(iterations):
        _split_long_edges(working, max_length)
        for _ in range(collapse_passes):
            if _collapse_pass(working, min_length, max_length, area_floor, generator) == 0:
                break
        for _ in range(flip_passes):
            if _flip_pass(working, area_floor, generator) == 0:
                break
        _relax(working, relaxation_weight, area_weighted, area_floor, projector)

    transfer = working.transfer.tocsr()
    transfer.eliminate_zeros()
    carried = {
        name: _restore_attribute(transfer @ values, original)
        for name, (values, original) in attribute_values.items()
    }
    return RemeshResult(
        verts=_restore_positions(working.verts, input_verts),
        faces=_restore_faces(working.faces, input_faces),
        attributes=carried,
        vertex_transfer=transfer,
    )


# --------------------------------------------------------------------------------------------
# Conversions and checks


def _as_numpy_positions(verts: np.ndarray | torch.Tensor) -> np.ndarray:
    """verts [V, 3] as float64 numpy, checked finite."""
    if isinstance(verts, torch.Tensor):
        verts = verts.detach().cpu().numpy()
    verts = np.asarray(verts)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ReconError(f"verts: expected shape [V, 3], got {tuple(verts.shape)}")
    if not np.issubdtype(verts.dtype, np.floating):
        raise ReconError(f"verts: expected floats, got {verts.dtype}")
    verts = verts.astype(np.float64)
    if not np.all(np.isfinite(verts)):
        raise ReconError("verts: contains NaN or inf")
    return verts


def _check_manifold(faces: np.ndarray, vertex_count: int) -> None:
    """Raise ReconError unless faces are edge- and vertex-manifold and consistently oriented."""
    if not is_edge_manifold(faces):
        raise ReconError(
            "faces: not edge-manifold (an edge has more than two faces or a face repeats a "
            "vertex); run recon.mesh.simplify.repair first"
        )
    if not is_vertex_manifold(faces, vertex_count):
        raise ReconError(
            "faces: not vertex-manifold (a vertex joins separate fans of faces); run "
            "recon.mesh.simplify.repair first"
        )
    if not is_consistently_oriented(faces):
        raise ReconError(
            "faces: inconsistent winding between neighbouring faces; run "
            "recon.mesh.simplify.repair first"
        )


def _prepare_attributes(
    attributes: dict[str, np.ndarray | torch.Tensor] | None, vertex_count: int
) -> dict[str, tuple[np.ndarray, np.ndarray | torch.Tensor]]:
    """Each attribute as float64 [V, K] next to its original (for type, shape and device)."""
    prepared = {}
    for name, value in (attributes or {}).items():
        array = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
        array = np.asarray(array)
        if array.ndim == 0 or array.shape[0] != vertex_count:
            raise ReconError(
                f"attributes[{name!r}]: expected shape [{vertex_count}, ...] (one row per "
                f"vertex), got {tuple(array.shape)}"
            )
        if not np.issubdtype(array.dtype, np.floating):
            raise ReconError(
                f"attributes[{name!r}]: expected floats (values are averaged), got {array.dtype}"
            )
        prepared[name] = (array.reshape(vertex_count, -1).astype(np.float64), value)
    return prepared


def _restore_attribute(
    values: np.ndarray, original: np.ndarray | torch.Tensor
) -> np.ndarray | torch.Tensor:
    """values [V', K] float64 back to the original's trailing shape, type, dtype and device."""
    shape = (values.shape[0], *tuple(original.shape[1:]))
    if isinstance(original, torch.Tensor):
        return torch.from_numpy(np.ascontiguousarray(values).reshape(shape)).to(
            dtype=original.dtype, device=original.device
        )
    return values.reshape(shape).astype(np.asarray(original).dtype)


def _restore_positions(
    verts: np.ndarray, original: np.ndarray | torch.Tensor
) -> np.ndarray | torch.Tensor:
    """verts [V', 3] float64 in the original's type, dtype and device."""
    if isinstance(original, torch.Tensor):
        return torch.from_numpy(verts).to(dtype=original.dtype, device=original.device)
    return verts.astype(np.asarray(original).dtype)


def _restore_faces(
    faces: np.ndarray, original: np.ndarray | torch.Tensor
) -> np.ndarray | torch.Tensor:
    """faces [F', 3] int64, as a torch.int64 tensor on the original's device when it was one."""
    if isinstance(original, torch.Tensor):
        return torch.from_numpy(faces).to(device=original.device)
    return faces


def _drop_unreferenced(working: _Working) -> None:
    """Remove vertices no face uses (renumbering faces and transfer rows)."""
    used = np.zeros(len(working.verts), dtype=bool)
    used[working.faces.reshape(-1)] = True
    if used.all():
        return
    new_index = np.cumsum(used) - 1
    working.faces = new_index[working.faces]
    working.verts = working.verts[used]
    working.transfer = working.transfer[used]


def _cross(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Cross product of [..., 3] arrays (written out: several times faster than np.cross)."""
    x1, y1, z1 = first[..., 0], first[..., 1], first[..., 2]
    x2, y2, z2 = second[..., 0], second[..., 1], second[..., 2]
    return np.stack([y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2], axis=-1)


def _length(vectors: np.ndarray) -> np.ndarray:
    """Euclidean length [N] of vectors [N, 3]."""
    return np.sqrt(np.einsum("nc,nc->n", vectors, vectors))


def _doubled_normals(corners: np.ndarray) -> np.ndarray:
    """Unnormalised normals [..., 3] (length = twice the area) of corners [..., 3, 3]."""
    return _cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])


def _normal_kept(old_normal: np.ndarray, new_normal: np.ndarray, area_floor: float) -> np.ndarray:
    """[N] bool: the new face turned by less than the allowed angle and did not become a sliver
    (twice its area stays above the floor, or at least does not shrink below an already
    smaller old area). old_normal, new_normal: [N, 3] doubled-area normals."""
    old_length = _length(old_normal)
    new_length = _length(new_normal)
    dot = np.einsum("nc,nc->n", old_normal, new_normal)
    turned_little = dot >= _MIN_NORMAL_COSINE * old_length * new_length
    big_enough = new_length >= np.minimum(area_floor, old_length)
    return turned_little & big_enough & (new_length > 0)


# --------------------------------------------------------------------------------------------
# Split


def _rotate_corners(
    faces: np.ndarray, midpoints: np.ndarray, rotation: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Rotate each face's corners (and edge midpoints) to start at corner `rotation` [N]; the
    winding is unchanged. Returns columns a, b, c, m_ab, m_bc, m_ca, each [N]."""
    index = (rotation[:, None] + np.arange(3)) % 3
    rotated = np.take_along_axis(faces, index, axis=1)
    rotated_mid = np.take_along_axis(midpoints, index, axis=1)
    return (*rotated.T, *rotated_mid.T)


def _split_long_edges(working: _Working, max_length: float) -> int:
    """Split every edge longer than max_length at its midpoint in one pass; faces with one,
    two or three split edges become two, three or four faces. Returns the split count."""
    verts, faces = working.verts, working.faces
    vertex_count = len(verts)
    adjacency = edge_adjacency(faces, vertex_count)
    edges = adjacency.edges
    length = _length(verts[edges[:, 0]] - verts[edges[:, 1]])
    split = length > max_length
    split_count = int(split.sum())
    if split_count == 0:
        return 0
    midpoint = np.full(len(edges), -1, dtype=np.int64)
    midpoint[split] = vertex_count + np.arange(split_count)
    ends = edges[split]
    rows = np.repeat(np.arange(split_count), 2)
    average = scipy.sparse.csr_matrix(
        (np.full(2 * split_count, 0.5), (rows, ends.reshape(-1))),
        shape=(split_count, vertex_count),
    )
    working.transfer = scipy.sparse.vstack(
        [working.transfer, average @ working.transfer], format="csr"
    )
    verts = np.concatenate([verts, 0.5 * (verts[ends[:, 0]] + verts[ends[:, 1]])])
    working.verts = verts

    face_split = split[adjacency.face_edges]
    face_midpoint = midpoint[adjacency.face_edges]
    split_per_face = face_split.sum(axis=1)
    pieces = [faces[split_per_face == 0]]

    select = split_per_face == 1
    if select.any():
        # Rotate the split edge to a-b: triangles a-m-c and m-b-c.
        rotation = np.argmax(face_split[select], axis=1)
        a, b, c, m_ab, _, _ = _rotate_corners(faces[select], face_midpoint[select], rotation)
        pieces += [np.stack([a, m_ab, c], 1), np.stack([m_ab, b, c], 1)]

    select = split_per_face == 2
    if select.any():
        # Rotate the unsplit edge to c-a: corner triangle m_ab-b-m_bc, then the quad
        # a-m_ab-m_bc-c cut along its shorter diagonal.
        rotation = (np.argmin(face_split[select], axis=1) + 1) % 3
        a, b, c, m_ab, m_bc, _ = _rotate_corners(faces[select], face_midpoint[select], rotation)
        cut_from_a = np.linalg.norm(verts[a] - verts[m_bc], axis=1) <= np.linalg.norm(
            verts[m_ab] - verts[c], axis=1
        )
        first = np.where(
            cut_from_a[:, None], np.stack([a, m_ab, m_bc], 1), np.stack([a, m_ab, c], 1)
        )
        second = np.where(
            cut_from_a[:, None], np.stack([a, m_bc, c], 1), np.stack([m_ab, m_bc, c], 1)
        )
        pieces += [np.stack([m_ab, b, m_bc], 1), first, second]

    select = split_per_face == 3
    if select.any():
        a, b, c = faces[select].T
        m_ab, m_bc, m_ca = face_midpoint[select].T
        pieces += [
            np.stack([a, m_ab, m_ca], 1),
            np.stack([m_ab, b, m_bc], 1),
            np.stack([m_ca, m_bc, c], 1),
            np.stack([m_ab, m_bc, m_ca], 1),
        ]
    working.faces = np.concatenate(pieces).astype(np.int64)
    return split_count


# --------------------------------------------------------------------------------------------
# Collapse


def _priority_ranks(preferred_first: np.ndarray, generator: np.random.Generator) -> np.ndarray:
    """Unique int64 priorities [N]: highest for the smallest preferred_first, random ties."""
    count = len(preferred_first)
    order = np.lexsort((generator.random(count), preferred_first))
    priority = np.empty(count, dtype=np.int64)
    priority[order] = np.arange(count, 0, -1)
    return priority


def _select_separated_edges(
    first: np.ndarray,
    second: np.ndarray,
    priority: np.ndarray,
    ring_offsets: np.ndarray,
    ring: np.ndarray,
    vertex_count: int,
) -> np.ndarray:
    """[N] bool: a set of candidate edges (first, second [N]) whose ends are at least two edges
    apart, so no face touches two of them.

    An edge wins a round when its priority is the largest among the candidates with an end in
    the closed one-ring of either of its ends; two winners would each have to beat the other,
    so they cannot conflict. Later rounds retry the candidates away from all winners.
    """
    ring_source = np.repeat(np.arange(vertex_count), np.diff(ring_offsets))
    active = np.ones(len(first), dtype=bool)
    selected = np.zeros(len(first), dtype=bool)
    for _ in range(_SELECTION_ROUNDS):
        candidate = np.flatnonzero(active)
        if len(candidate) == 0:
            break
        best = np.full(vertex_count, -1, dtype=np.int64)
        np.maximum.at(best, first[candidate], priority[candidate])
        np.maximum.at(best, second[candidate], priority[candidate])
        near_best = best.copy()
        np.maximum.at(near_best, ring_source, best[ring])
        rival = np.maximum(near_best[first[candidate]], near_best[second[candidate]])
        winner = candidate[priority[candidate] == rival]
        selected[winner] = True
        zone = np.zeros(vertex_count, dtype=bool)
        zone[first[winner]] = True
        zone[second[winner]] = True
        near_zone = zone.copy()
        near_zone[ring_source[zone[ring]]] = True
        active &= ~(near_zone[first] | near_zone[second])
    return selected


def _collapse_pass(
    working: _Working,
    min_length: float,
    max_length: float,
    area_floor: float,
    generator: np.random.Generator,
) -> int:
    """Collapse an independent set of valid edges shorter than min_length. Returns the count.

    Valid: the link condition holds (the ends share exactly the neighbours of the faces on the
    edge, so the result stays manifold with the same topology); an interior edge does not join
    two boundary vertices; the merged vertex keeps valence >= 3 (2 on the boundary) and so do
    the vertices opposite the edge; no new edge exceeds max_length; no surrounding face turns
    over or becomes a sliver. The merged vertex sits at the midpoint, or at the boundary end
    when only one end is on the boundary (so boundaries stay on the boundary).
    """
    verts, faces = working.verts, working.faces
    vertex_count = len(verts)
    adjacency = edge_adjacency(faces, vertex_count)
    edges = adjacency.edges
    length = _length(verts[edges[:, 0]] - verts[edges[:, 1]])
    candidate = np.flatnonzero(length < min_length)
    if len(candidate) == 0:
        return 0
    boundary_edge = adjacency.edge_face_count == 1
    boundary_vertex = np.zeros(vertex_count, dtype=bool)
    boundary_vertex[edges[boundary_edge].reshape(-1)] = True
    minimum_valence = np.where(boundary_vertex, 2, 3)
    valence = np.bincount(edges.reshape(-1), minlength=vertex_count)
    flat = faces.reshape(-1)
    half_edges = adjacency.edge_half_edges
    opposite = np.where(half_edges >= 0, flat[3 * (half_edges // 3) + (half_edges % 3 + 2) % 3], -1)

    # Cheap checks first, so the costly ones below run on fewer candidates.
    first, second = edges[candidate, 0], edges[candidate, 1]
    on_boundary = boundary_edge[candidate]
    first_boundary, second_boundary = boundary_vertex[first], boundary_vertex[second]
    valid = ~(first_boundary & second_boundary & ~on_boundary)
    expected = np.where(on_boundary, 1, 2)
    merged_valence = valence[first] + valence[second] - 2 - expected
    valid &= merged_valence >= np.where(first_boundary | second_boundary, 2, 3)
    candidate_opposite = opposite[candidate]
    opposite_safe = np.maximum(candidate_opposite, 0)
    valid &= np.all(
        (candidate_opposite < 0) | (valence[opposite_safe] - 1 >= minimum_valence[opposite_safe]),
        axis=1,
    )
    candidate = candidate[valid]
    if len(candidate) == 0:
        return 0
    first, second = edges[candidate, 0], edges[candidate, 1]
    on_boundary = boundary_edge[candidate]
    first_boundary, second_boundary = boundary_vertex[first], boundary_vertex[second]
    # Along a boundary edge, a corner end stays put (two corners cannot merge), so the outline
    # keeps its corners.
    if on_boundary.any():
        _, corner, _, _ = _boundary_geometry(verts, faces, adjacency)
        first_boundary = first_boundary & ~(on_boundary & corner[second])
        second_boundary = second_boundary & ~(on_boundary & corner[first])
        keep = ~(on_boundary & corner[first] & corner[second])
        candidate, first, second = candidate[keep], first[keep], second[keep]
        on_boundary = on_boundary[keep]
        first_boundary, second_boundary = first_boundary[keep], second_boundary[keep]
        if len(candidate) == 0:
            return 0
    first_weight = np.where(
        first_boundary & ~second_boundary,
        1.0,
        np.where(second_boundary & ~first_boundary, 0.0, 0.5),
    )
    position = first_weight[:, None] * verts[first] + (1 - first_weight)[:, None] * verts[second]

    # Link condition: the common neighbours are exactly the opposite vertices (2, or 1 on the
    # boundary). And no new edge longer than max_length.
    count = len(candidate)
    ring_offsets, ring = edges_one_ring(edges, vertex_count)
    owner_first, neighbour_first = expand_csr(ring_offsets, ring, first)
    owner_second, neighbour_second = expand_csr(ring_offsets, ring, second)
    owner = np.concatenate([owner_first, owner_second])
    neighbour = np.concatenate([neighbour_first, neighbour_second])
    keys = np.sort(owner * vertex_count + neighbour)
    repeated = keys[1:][keys[1:] == keys[:-1]]
    common = np.bincount(repeated // vertex_count, minlength=count)
    valid = common == np.where(on_boundary, 1, 2)
    other = (neighbour != first[owner]) & (neighbour != second[owner])
    stretched = _length(position[owner] - verts[neighbour]) > max_length
    valid &= np.bincount(owner[other & stretched], minlength=count) == 0
    candidate, first, second = candidate[valid], first[valid], second[valid]
    first_weight, position = first_weight[valid], position[valid]
    count = len(candidate)
    if count == 0:
        return 0

    # Faces around either end keep their orientation and area (the two faces on the edge
    # disappear and are skipped).
    face_offsets, face_list = csr_from_pairs(
        flat, np.repeat(np.arange(len(faces), dtype=np.int64), 3), vertex_count
    )
    owner_face_first, around_first = expand_csr(face_offsets, face_list, first)
    owner_face_second, around_second = expand_csr(face_offsets, face_list, second)
    owner_face = np.concatenate([owner_face_first, owner_face_second])
    corners = faces[np.concatenate([around_first, around_second])]
    has_first = corners == first[owner_face, None]
    has_second = corners == second[owner_face, None]
    survives = ~(has_first.any(axis=1) & has_second.any(axis=1))
    owner_face, corners = owner_face[survives], corners[survives]
    moving = (has_first | has_second)[survives]
    old_corners = verts[corners]
    new_corners = np.where(moving[..., None], position[owner_face, None, :], old_corners)
    kept = _normal_kept(_doubled_normals(old_corners), _doubled_normals(new_corners), area_floor)
    valid = np.bincount(owner_face[~kept], minlength=count) == 0
    candidate, first, second = candidate[valid], first[valid], second[valid]
    first_weight, position = first_weight[valid], position[valid]
    if len(candidate) == 0:
        return 0

    priority = _priority_ranks(length[candidate], generator)
    selected = _select_separated_edges(first, second, priority, ring_offsets, ring, vertex_count)
    # Two chosen collapses can share an opposite vertex (it is two edges from both); make sure
    # its valence survives both.
    chosen_opposite = opposite[candidate[selected]]
    drop = np.bincount(chosen_opposite[chosen_opposite >= 0], minlength=vertex_count)
    too_low = valence - drop < minimum_valence
    too_low_opposite = np.where(
        chosen_opposite >= 0, too_low[np.maximum(chosen_opposite, 0)], False
    )
    selected[np.flatnonzero(selected)[too_low_opposite.any(axis=1)]] = False
    chosen = np.flatnonzero(selected)
    if len(chosen) == 0:
        return 0

    kept_vertex, removed_vertex = first[chosen], second[chosen]
    weight = first_weight[chosen]
    working.verts = verts.copy()
    working.verts[kept_vertex] = position[chosen]
    remap = np.arange(vertex_count)
    remap[removed_vertex] = kept_vertex
    new_faces = remap[faces]
    degenerate = (
        (new_faces[:, 0] == new_faces[:, 1])
        | (new_faces[:, 1] == new_faces[:, 2])
        | (new_faces[:, 2] == new_faces[:, 0])
    )
    working.faces = new_faces[~degenerate]
    # Transfer: the kept row becomes weight * kept + (1 - weight) * removed.
    row_weight = np.ones(vertex_count)
    row_weight[kept_vertex] = weight
    rows = np.concatenate([np.arange(vertex_count), kept_vertex])
    columns = np.concatenate([np.arange(vertex_count), removed_vertex])
    mixing = scipy.sparse.csr_matrix(
        (np.concatenate([row_weight, 1 - weight]), (rows, columns)),
        shape=(vertex_count, vertex_count),
    )
    working.transfer = mixing @ working.transfer
    _drop_unreferenced(working)
    return len(chosen)


# --------------------------------------------------------------------------------------------
# Flip


def _flip_pass(working: _Working, area_floor: float, generator: np.random.Generator) -> int:
    """Flip an independent set of interior edges that lower the total valence deviation
    (target 6 inside, 4 on the boundary). Returns the count.

    Edge a-b with faces (a, b, c) and (b, a, d) becomes c-d with faces (a, d, c) and
    (d, b, c). Valid when c-d is not an edge already, a and b keep valence >= 3 (2 on the
    boundary), and both new faces keep an orientation close to both old ones and a
    non-sliver area. Chosen flips share no vertex.
    """
    verts, faces = working.verts, working.faces
    vertex_count = len(verts)
    adjacency = edge_adjacency(faces, vertex_count)
    interior = np.flatnonzero(adjacency.edge_face_count == 2)
    if len(interior) == 0:
        return 0
    edges = adjacency.edges
    boundary_vertex = np.zeros(vertex_count, dtype=bool)
    boundary_vertex[edges[adjacency.edge_face_count == 1].reshape(-1)] = True
    valence = np.bincount(edges.reshape(-1), minlength=vertex_count)
    ideal = np.where(boundary_vertex, 4, 6)
    minimum_valence = np.where(boundary_vertex, 2, 3)

    flat = faces.reshape(-1)
    first_half, second_half = adjacency.edge_half_edges[interior].T
    first_face, second_face = first_half // 3, second_half // 3
    a = flat[first_half]
    b = flat[3 * first_face + (first_half % 3 + 1) % 3]
    c = flat[3 * first_face + (first_half % 3 + 2) % 3]
    d = flat[3 * second_face + (second_half % 3 + 2) % 3]
    oriented = flat[second_half] == b

    def deviation(vertex: np.ndarray, change: int) -> np.ndarray:
        return np.abs(valence[vertex] + change - ideal[vertex])

    before = deviation(a, 0) + deviation(b, 0) + deviation(c, 0) + deviation(d, 0)
    after = deviation(a, -1) + deviation(b, -1) + deviation(c, 1) + deviation(d, 1)
    gain = before - after
    valid = oriented & (gain > 0) & (c != d)
    valid &= (valence[a] - 1 >= minimum_valence[a]) & (valence[b] - 1 >= minimum_valence[b])
    valid &= adjacency.find_edges(c, d) < 0

    position_a, position_b, position_c, position_d = verts[a], verts[b], verts[c], verts[d]
    old_first = _cross(position_b - position_a, position_c - position_a)
    old_second = _cross(position_a - position_b, position_d - position_b)
    new_first = _cross(position_d - position_a, position_c - position_a)
    new_second = _cross(position_b - position_d, position_c - position_d)
    for new in (new_first, new_second):
        for old in (old_first, old_second):
            valid &= _normal_kept(old, new, area_floor)

    chosen = np.flatnonzero(valid)
    if len(chosen) == 0:
        return 0
    priority = _priority_ranks(-gain[chosen], generator)
    quads = np.stack([a, b, c, d], axis=1)[chosen]
    active = np.ones(len(chosen), dtype=bool)
    selected = np.zeros(len(chosen), dtype=bool)
    for _ in range(_SELECTION_ROUNDS):
        candidate = np.flatnonzero(active)
        if len(candidate) == 0:
            break
        best = np.full(vertex_count, -1, dtype=np.int64)
        np.maximum.at(best, quads[candidate].reshape(-1), np.repeat(priority[candidate], 4))
        winner = candidate[priority[candidate] == best[quads[candidate]].max(axis=1)]
        selected[winner] = True
        used = np.zeros(vertex_count, dtype=bool)
        used[quads[winner].reshape(-1)] = True
        active &= ~used[quads].any(axis=1)
    chosen = chosen[selected]
    new_faces = faces.copy()
    new_faces[first_face[chosen]] = np.stack([a[chosen], d[chosen], c[chosen]], axis=1)
    new_faces[second_face[chosen]] = np.stack([d[chosen], b[chosen], c[chosen]], axis=1)
    working.faces = new_faces
    return len(chosen)


# --------------------------------------------------------------------------------------------
# Relaxation and projection


class _SurfaceProjector:
    """Nearest points on a fixed triangle mesh: a k-d tree over four samples per triangle
    (centroid and the midpoints between it and each corner) proposes candidate triangles, and
    the exact closest point on each candidate decides. Approximate only where a far larger
    triangle lies nearer than every proposed one, which needs very uneven triangle sizes."""

    def __init__(self, verts: np.ndarray, faces: np.ndarray) -> None:
        self.triangles = verts[faces]  # [F, 3, 3]
        centroid = self.triangles.mean(axis=1)
        inner = 0.5 * (centroid[:, None, :] + self.triangles)
        samples = np.concatenate([centroid, inner.reshape(-1, 3)])
        face_index = np.arange(len(faces), dtype=np.int64)
        self.sample_face = np.concatenate([face_index, np.repeat(face_index, 3)])
        self.tree = scipy.spatial.cKDTree(samples)

    def project(self, points: np.ndarray) -> np.ndarray:
        """points [N, 3] -> nearest points [N, 3] on the surface."""
        count = min(_PROJECTION_CANDIDATES, len(self.sample_face))
        _, sample = self.tree.query(points, k=count)
        sample = sample.reshape(len(points), count)
        candidate = self.sample_face[sample]
        closest = trimesh.triangles.closest_point(
            self.triangles[candidate.reshape(-1)], np.repeat(points, count, axis=0)
        ).reshape(len(points), count, 3)
        distance = np.linalg.norm(closest - points[:, None, :], axis=-1)
        return closest[np.arange(len(points)), np.argmin(distance, axis=1)]


def _boundary_geometry(
    verts: np.ndarray, faces: np.ndarray, adjacency: EdgeAdjacency
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Boundary shape per vertex, or None for a closed mesh: (on_boundary [V] bool, corner [V]
    bool: the boundary turns by more than _BOUNDARY_CORNER_DEGREES there, unit_tangent [V, 3]
    along the boundary, neighbour_mean [V, 3] of the boundary neighbours)."""
    vertex_count = len(verts)
    boundary_half = adjacency.edge_half_edges[adjacency.edge_face_count == 1, 0]
    if len(boundary_half) == 0:
        return None
    flat = faces.reshape(-1)
    # A boundary half-edge runs start -> end in its face's winding, so at a boundary vertex
    # the incoming and outgoing directions add up along the boundary.
    start = flat[boundary_half]
    end = flat[3 * (boundary_half // 3) + (boundary_half % 3 + 1) % 3]
    direction = verts[end] - verts[start]
    direction /= np.maximum(_length(direction), 1e-300)[:, None]
    both_ends = np.concatenate([start, end])
    tangent = np.zeros_like(verts)
    neighbour_sum = np.zeros_like(verts)
    for axis in range(3):
        tangent[:, axis] = np.bincount(
            both_ends, weights=np.tile(direction[:, axis], 2), minlength=vertex_count
        )
        neighbour_sum[:, axis] = np.bincount(
            both_ends,
            weights=np.concatenate([verts[end, axis], verts[start, axis]]),
            minlength=vertex_count,
        )
    boundary_count = np.bincount(both_ends, minlength=vertex_count)
    on_boundary = boundary_count > 0
    # |incoming + outgoing| = 2 cos(turn / 2): small where the boundary turns sharply.
    tangent_length = _length(tangent)
    smooth = (boundary_count == 2) & (
        tangent_length >= 2 * np.cos(np.radians(_BOUNDARY_CORNER_DEGREES) / 2)
    )
    unit_tangent = tangent / np.maximum(tangent_length, 1e-300)[:, None]
    neighbour_mean = neighbour_sum / np.maximum(boundary_count, 1)[:, None]
    return on_boundary, on_boundary & ~smooth, unit_tangent, neighbour_mean


def _relax(
    working: _Working,
    weight: float,
    area_weighted: bool,
    area_floor: float,
    projector: _SurfaceProjector | None,
) -> None:
    """Move vertices toward their one-ring centroid in their tangent plane (boundary vertices
    along the boundary; sharp boundary corners stay), optionally onto the input surface; then
    put back any vertex of a face that would turn over or become a sliver, until none does."""
    verts, faces = working.verts, working.faces
    vertex_count = len(verts)
    corners = verts[faces]
    old_normal = _doubled_normals(corners)
    flat = faces.reshape(-1)
    if area_weighted:
        face_weight = np.repeat(np.linalg.norm(old_normal, axis=1), 3)
        face_centroid = np.repeat(corners.mean(axis=1), 3, axis=0)
        total = np.bincount(flat, weights=face_weight, minlength=vertex_count)
        centroid = (
            np.stack(
                [
                    np.bincount(
                        flat, weights=face_weight * face_centroid[:, axis], minlength=vertex_count
                    )
                    for axis in range(3)
                ],
                axis=1,
            )
            / np.maximum(total, 1e-300)[:, None]
        )
    else:
        edges = edge_adjacency(faces, vertex_count).edges
        sources = np.concatenate([edges[:, 0], edges[:, 1]])
        targets = np.concatenate([edges[:, 1], edges[:, 0]])
        total = np.bincount(sources, minlength=vertex_count)
        centroid = (
            np.stack(
                [
                    np.bincount(sources, weights=verts[targets, axis], minlength=vertex_count)
                    for axis in range(3)
                ],
                axis=1,
            )
            / np.maximum(total, 1)[:, None]
        )
    normal = np.zeros_like(verts)
    for axis in range(3):
        normal[:, axis] = np.bincount(
            flat, weights=np.repeat(old_normal[:, axis], 3), minlength=vertex_count
        )
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    step = centroid - verts
    step -= np.einsum("vc,vc->v", step, normal)[:, None] * normal

    # Boundary vertices slide along the boundary toward the mean of their two boundary
    # neighbours; corners stay.
    boundary = _boundary_geometry(verts, faces, edge_adjacency(faces, vertex_count))
    if boundary is not None:
        on_boundary, corner, unit_tangent, neighbour_mean = boundary
        along = np.einsum("vc,vc->v", neighbour_mean - verts, unit_tangent)
        boundary_step = np.where(corner[:, None], 0.0, along[:, None] * unit_tangent)
        step[on_boundary] = boundary_step[on_boundary]

    moved = verts + weight * step
    if projector is not None:
        moved = projector.project(moved)
    while True:
        kept = _normal_kept(old_normal, _doubled_normals(moved[faces]), area_floor)
        # A face none of whose corners moved is as it was (even an input sliver).
        untouched = np.all(moved[faces] == corners, axis=(1, 2))
        bad = ~kept & ~untouched
        if not bad.any():
            break
        # Each round puts back at least one moved vertex, so this ends.
        restore = faces[bad].reshape(-1)
        moved[restore] = verts[restore]
    working.verts = moved
