"""Mesh Laplacians as scipy.sparse CSR matrices and torch sparse tensors.

Sign convention: L = D - W (positive semi-definite), so (L x)_i = sum_j w_ij (x_i - x_j), every
row sums to zero and L @ constant = 0. That is the form Large Steps factorises as I + lambda L
(scipy.sparse.linalg.splu / factorized, elsewhere) and a smoothness regulariser penalises
(|| L v ||^2 or v^T L v).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse
import torch

from recon.errors import ReconError
from recon.mesh.topology import as_numpy_faces, edge_adjacency, resolve_vertex_count

# Cotangents of angles this close to 0 or 180 degrees are capped so sliver triangles cannot
# produce huge weights (cot of 0.01 degrees is about 5700).
_COTANGENT_LIMIT = 1e3


def _as_numpy_verts(verts: np.ndarray | torch.Tensor) -> np.ndarray:
    """verts [V, 3] as float64 numpy."""
    if isinstance(verts, torch.Tensor):
        verts = verts.detach().cpu().numpy()
    verts = np.asarray(verts, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ReconError(f"verts: expected shape [V, 3], got {tuple(verts.shape)}")
    return verts


def _laplacian_from_weights(
    rows: np.ndarray, columns: np.ndarray, weights: np.ndarray, vertex_count: int
) -> scipy.sparse.csr_matrix:
    """L = D - W from symmetric off-diagonal weights listed once per undirected edge."""
    both_rows = np.concatenate([rows, columns])
    both_columns = np.concatenate([columns, rows])
    adjacency = scipy.sparse.coo_matrix(
        (np.concatenate([weights, weights]), (both_rows, both_columns)),
        shape=(vertex_count, vertex_count),
    ).tocsr()
    degree = np.asarray(adjacency.sum(axis=1)).reshape(-1)
    laplacian = scipy.sparse.diags(degree, format="csr") - adjacency
    laplacian.sum_duplicates()
    laplacian.sort_indices()
    return laplacian.tocsr()


def uniform_laplacian(
    faces: np.ndarray | torch.Tensor, vertex_count: int | None = None
) -> scipy.sparse.csr_matrix:
    """Combinatorial Laplacian L = D - A: [V, V] float64 CSR, L_ii = valence, L_ij = -1 per
    edge. faces: [F, 3]; vertex_count: V (default one past the largest index; unreferenced
    vertices get an all-zero row)."""
    faces = as_numpy_faces(faces)
    vertex_count = resolve_vertex_count(faces, vertex_count)
    edges = edge_adjacency(faces, vertex_count).edges
    return _laplacian_from_weights(
        edges[:, 0], edges[:, 1], np.ones(len(edges), dtype=np.float64), vertex_count
    )


def cotangent_weights(
    verts: np.ndarray | torch.Tensor, faces: np.ndarray | torch.Tensor
) -> np.ndarray:
    """[F, 3] float64 cotangent of the angle at corner k, which is the weight contribution to
    the opposite edge faces[f, (k + 1) % 3] - faces[f, (k + 2) % 3]; capped to
    [-_COTANGENT_LIMIT, _COTANGENT_LIMIT] (zero-area faces contribute 0)."""
    verts = _as_numpy_verts(verts)
    faces = as_numpy_faces(faces)
    corners = verts[faces]  # [F, 3, 3]
    to_next = corners[:, [1, 2, 0]] - corners  # corner k -> k + 1
    to_previous = corners[:, [2, 0, 1]] - corners  # corner k -> k - 1
    dot = np.einsum("fkc,fkc->fk", to_next, to_previous)
    cross = np.linalg.norm(np.cross(to_next, to_previous), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cotangent = np.where(cross > 0, dot / np.where(cross > 0, cross, 1.0), 0.0)
    return np.clip(cotangent, -_COTANGENT_LIMIT, _COTANGENT_LIMIT)


def cotangent_laplacian(
    verts: np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor,
    minimum_weight: float | None = 0.0,
    maximum_weight: float | None = None,
) -> scipy.sparse.csr_matrix:
    """Cotangent Laplacian L = D - W with w_ij = (cot alpha_ij + cot beta_ij) / 2, [V, V]
    float64 CSR (unreferenced vertices get an all-zero row).

    verts: [V, 3]; faces: [F, 3].
    minimum_weight: edge weights are clamped below to this (default 0, so obtuse triangles
        cannot make weights negative: L stays positive semi-definite and an M-matrix, which
        keeps I + lambda L well conditioned); None keeps the raw weights (exact linear
        precision on any planar mesh).
    maximum_weight: optional upper clamp (e.g. against sliver triangles).
    On a planar Delaunay mesh (no obtuse angle opposite an interior edge) clamping changes
    nothing, and L applied to a linear function is zero on interior vertices.
    """
    verts = _as_numpy_verts(verts)
    faces = as_numpy_faces(faces)
    vertex_count = resolve_vertex_count(faces, verts.shape[0])
    if vertex_count != verts.shape[0]:
        raise ReconError(f"faces: index {vertex_count - 1} out of range for {verts.shape[0]} verts")
    adjacency = edge_adjacency(faces, vertex_count)
    cotangent = cotangent_weights(verts, faces)
    # The angle at corner k is opposite the edge of half-edge k + 1.
    opposite_edge = adjacency.face_edges[:, [1, 2, 0]]
    weights = 0.5 * np.bincount(
        opposite_edge.reshape(-1), weights=cotangent.reshape(-1), minlength=len(adjacency.edges)
    )
    if minimum_weight is not None or maximum_weight is not None:
        weights = np.clip(weights, minimum_weight, maximum_weight)
    edges = adjacency.edges
    return _laplacian_from_weights(edges[:, 0], edges[:, 1], weights, vertex_count)


def to_torch_sparse(
    matrix: scipy.sparse.spmatrix | scipy.sparse.sparray,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
    layout: torch.layout = torch.sparse_coo,
) -> torch.Tensor:
    """A scipy sparse matrix as a coalesced torch sparse COO tensor (or CSR with
    layout=torch.sparse_csr). torch.sparse.mm(L, v) with v [V, 3] is differentiable in v."""
    coo = scipy.sparse.coo_matrix(matrix)
    indices = torch.from_numpy(np.stack([coo.row, coo.col]).astype(np.int64))
    values = torch.from_numpy(coo.data.astype(np.float64)).to(dtype)
    tensor = torch.sparse_coo_tensor(indices, values, coo.shape, check_invariants=True).coalesce()
    if layout == torch.sparse_csr:
        with warnings.catch_warnings():
            # torch flags CSR as beta on first use; CPU CSR @ dense is what Large Steps needs.
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            tensor = tensor.to_sparse_csr()
    elif layout != torch.sparse_coo:
        raise ReconError(f"layout: expected torch.sparse_coo or torch.sparse_csr, got {layout}")
    return tensor.to(device) if device is not None else tensor


def uniform_laplacian_torch(
    faces: np.ndarray | torch.Tensor,
    vertex_count: int | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
    layout: torch.layout = torch.sparse_coo,
) -> torch.Tensor:
    """uniform_laplacian as a torch sparse [V, V] tensor (device defaults to faces' device when
    faces is a tensor, else CPU)."""
    if device is None and isinstance(faces, torch.Tensor):
        device = faces.device
    return to_torch_sparse(uniform_laplacian(faces, vertex_count), dtype, device, layout)


def cotangent_laplacian_torch(
    verts: np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor,
    minimum_weight: float | None = 0.0,
    maximum_weight: float | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
    layout: torch.layout = torch.sparse_coo,
) -> torch.Tensor:
    """cotangent_laplacian as a torch sparse [V, V] tensor (weights are computed from verts
    once, without autograd)."""
    if device is None and isinstance(verts, torch.Tensor):
        device = verts.device
    matrix = cotangent_laplacian(verts, faces, minimum_weight, maximum_weight)
    return to_torch_sparse(matrix, dtype, device, layout)
