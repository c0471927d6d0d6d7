"""Laplacians: zero row sums, symmetry, L @ constant = 0, linear precision of the cotangent
Laplacian on flat meshes, clamping, the torch tensors, and the Large Steps factorisation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh import laplacian, topology


def grid_patch(cells: int = 6, jitter: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An open flat square patch (z = 0) of cells x cells quads, two triangles each; interior
    vertices moved by up to jitter x spacing (small jitter keeps every angle acute enough)."""
    x, y = np.meshgrid(np.linspace(0, 1, cells + 1), np.linspace(0, 1, cells + 1))
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    if jitter:
        interior = index[1:-1, 1:-1].ravel()
        generator = np.random.default_rng(0)
        verts[interior, :2] += generator.uniform(-jitter, jitter, (len(interior), 2)) / cells
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return verts, faces


def interior_mask(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    return ~topology.boundary_vertex_mask(faces, vertex_count)


def test_uniform_laplacian_structure() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    matrix = laplacian.uniform_laplacian(sphere.faces)
    assert isinstance(matrix, scipy.sparse.csr_matrix)
    assert matrix.shape == (len(sphere.vertices),) * 2
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=1)).ravel(), 0.0)
    assert abs(matrix - matrix.T).max() == 0
    np.testing.assert_array_equal(matrix.diagonal(), topology.vertex_valence(sphere.faces))
    off_diagonal = matrix - scipy.sparse.diags(matrix.diagonal())
    assert set(np.unique(off_diagonal.data)) <= {-1.0, 0.0}
    np.testing.assert_allclose(matrix @ np.full(matrix.shape[0], 3.7), 0.0, atol=1e-12)


def test_uniform_laplacian_unreferenced_vertex_row_is_zero() -> None:
    matrix = laplacian.uniform_laplacian(np.array([[0, 1, 2]]), vertex_count=4)
    assert matrix.shape == (4, 4)
    assert matrix[3].nnz == 0 or np.all(matrix[3].toarray() == 0)


def test_uniform_laplacian_torch_matches_scipy() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=1)
    faces = torch.from_numpy(sphere.faces)
    dense = laplacian.uniform_laplacian(sphere.faces).toarray()
    coo = laplacian.uniform_laplacian_torch(faces, dtype=torch.float64)
    assert coo.layout == torch.sparse_coo and coo.is_coalesced()
    np.testing.assert_array_equal(coo.to_dense().numpy(), dense)
    csr = laplacian.uniform_laplacian_torch(faces, layout=torch.sparse_csr)
    assert csr.layout == torch.sparse_csr and csr.dtype == torch.float32
    np.testing.assert_array_equal(csr.to_dense().numpy(), dense)
    # Differentiable smoothness term through the sparse product.
    verts = torch.tensor(sphere.vertices, dtype=torch.float32, requires_grad=True)
    energy = torch.sparse.mm(coo.float(), verts).square().sum()
    energy.backward()
    assert verts.grad is not None and torch.isfinite(verts.grad).all()
    with pytest.raises(ReconError, match="layout"):
        laplacian.to_torch_sparse(scipy.sparse.identity(3), layout=torch.strided)


def test_cotangent_laplacian_structure_and_semidefinite() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    matrix = laplacian.cotangent_laplacian(sphere.vertices, sphere.faces)
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=1)).ravel(), 0.0, atol=1e-12)
    assert abs(matrix - matrix.T).max() < 1e-12
    eigenvalues = np.linalg.eigvalsh(matrix.toarray())
    assert eigenvalues.min() > -1e-9
    assert np.sum(eigenvalues < 1e-9) == 1  # one connected component: only constants vanish


def test_cotangent_regular_grid_is_the_five_point_stencil() -> None:
    verts, faces = grid_patch(cells=6)
    matrix = laplacian.cotangent_laplacian(verts, faces)
    inside = interior_mask(faces, len(verts))
    # Right isosceles triangles: cot 45 = 1 on the axis edges, cot 90 = 0 on the diagonals.
    np.testing.assert_allclose(matrix.diagonal()[inside], 4.0, atol=1e-12)
    for function in (verts[:, 0], 2 * verts[:, 0] - 3 * verts[:, 1] + 1):
        np.testing.assert_allclose((matrix @ function)[inside], 0.0, atol=1e-12)


def test_cotangent_linear_precision_on_irregular_flat_mesh() -> None:
    verts, faces = grid_patch(cells=8, jitter=0.2)
    inside = interior_mask(faces, len(verts))
    linear = 0.3 * verts[:, 0] - 1.7 * verts[:, 1] + 0.5
    raw = laplacian.cotangent_laplacian(verts, faces, minimum_weight=None)
    np.testing.assert_allclose((raw @ linear)[inside], 0.0, atol=1e-10)
    # The uniform Laplacian has no such precision on an irregular mesh.
    uniform = laplacian.uniform_laplacian(faces)
    assert np.abs((uniform @ linear)[inside]).max() > 1e-3


def test_cotangent_clamping_removes_negative_weights() -> None:
    # Two obtuse triangles on the shared edge 0-1: both opposite angles are 150 degrees.
    verts = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, 0.27, 0], [0, -0.27, 0]])
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    raw = laplacian.cotangent_laplacian(verts, faces, minimum_weight=None)
    assert raw[0, 1] > 0  # a negative weight w_01 makes a positive off-diagonal entry
    clamped = laplacian.cotangent_laplacian(verts, faces)
    assert clamped[0, 1] == 0
    off_diagonal = clamped - scipy.sparse.diags(clamped.diagonal())
    assert off_diagonal.max() <= 0
    capped = laplacian.cotangent_laplacian(verts, faces, maximum_weight=0.5)
    assert (-(capped - scipy.sparse.diags(capped.diagonal())).toarray()).max() <= 0.5
    torch_matrix = laplacian.cotangent_laplacian_torch(
        torch.tensor(verts, dtype=torch.float32), torch.from_numpy(faces)
    )
    np.testing.assert_allclose(torch_matrix.to_dense().numpy(), clamped.toarray(), atol=1e-6)


def test_large_steps_system_factorises() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    matrix = laplacian.uniform_laplacian(sphere.faces)
    system = (scipy.sparse.identity(matrix.shape[0]) + 25.0 * matrix).tocsc()
    solve = scipy.sparse.linalg.factorized(system)
    latent = system @ sphere.vertices
    np.testing.assert_allclose(
        np.stack([solve(latent[:, axis]) for axis in range(3)], 1), sphere.vertices, atol=1e-9
    )
