"""Topology helpers on meshes with known answers: cube, icosphere, torus, open patch, fin,
bow-tie, and meshes with flipped faces."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh import topology


def grid_patch(cells: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """An open square patch of cells x cells quads, two triangles each, counter-clockwise
    seen from +z: ((cells + 1)^2 verts, 2 cells^2 faces)."""
    x, y = np.meshgrid(np.linspace(0, 1, cells + 1), np.linspace(0, 1, cells + 1))
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return verts, faces


def test_cube_counts_and_face_edge_map() -> None:
    cube = trimesh.creation.box()
    faces = cube.faces
    adjacency = topology.edge_adjacency(faces)
    assert adjacency.edges.shape == (18, 2)
    assert np.all(adjacency.edges[:, 0] < adjacency.edges[:, 1])
    assert np.all(adjacency.edge_face_count == 2)
    # face_edges[f, k] is the edge from faces[f, k] to faces[f, k + 1].
    ends = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1)
    np.testing.assert_array_equal(adjacency.edges[adjacency.face_edges], np.sort(ends, axis=-1))
    # Both faces listed for each edge really contain it.
    for edge, pair in zip(adjacency.edges, adjacency.edge_faces, strict=True):
        for face in pair:
            assert set(edge) <= set(faces[face])
    assert topology.is_closed(faces)
    assert topology.is_manifold(faces)
    assert topology.is_consistently_oriented(faces)
    assert topology.euler_characteristic(faces) == 2
    assert topology.genus(faces) == 0
    assert len(topology.boundary_edges(faces)) == 0
    assert topology.vertex_valence(faces).sum() == 2 * 18


def test_icosphere_valence_one_ring_and_vertex_faces() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    faces = torch.from_numpy(sphere.faces)  # torch input is accepted too
    valence = topology.vertex_valence(faces)
    assert set(np.unique(valence)) == {5, 6}
    assert np.sum(valence == 5) == 12
    offsets, neighbours = topology.one_ring(faces)
    np.testing.assert_array_equal(np.diff(offsets), valence)
    edges = set(map(tuple, topology.unique_edges(faces)[0]))
    for vertex in (0, 17, len(valence) - 1):
        ring = neighbours[offsets[vertex] : offsets[vertex + 1]]
        assert all((min(vertex, n), max(vertex, n)) in edges for n in ring)
    face_offsets, face_list = topology.vertex_faces(faces)
    np.testing.assert_array_equal(np.diff(face_offsets), valence)  # closed: faces = valence
    for vertex in (0, 40):
        around = face_list[face_offsets[vertex] : face_offsets[vertex + 1]]
        assert np.all(np.any(sphere.faces[around] == vertex, axis=1))
    assert topology.genus(faces) == 0


def test_torus_genus_one() -> None:
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    assert topology.is_manifold(torus.faces)
    assert topology.euler_characteristic(torus.faces) == 0
    assert topology.genus(torus.faces) == 1


def test_open_patch_boundary() -> None:
    cells = 4
    _, faces = grid_patch(cells)
    assert topology.is_manifold(faces)
    assert not topology.is_closed(faces)
    boundary = topology.boundary_edges(faces)
    assert len(boundary) == 4 * cells
    # Boundary edges follow their face's winding: every boundary vertex starts one and ends one.
    np.testing.assert_array_equal(
        np.bincount(boundary[:, 0], minlength=25), np.bincount(boundary[:, 1], minlength=25)
    )
    mask = topology.boundary_vertex_mask(faces)
    assert mask.sum() == 4 * cells and not mask[12]  # the centre vertex is interior
    assert topology.euler_characteristic(faces) == 1
    with pytest.raises(ReconError):
        topology.genus(faces)
    offsets, _ = topology.one_ring(faces)
    assert np.diff(offsets)[0] == 3  # corner (0, 0) has a diagonal: neighbours 1, 5, 6


def test_fin_is_not_edge_manifold() -> None:
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    adjacency = topology.edge_adjacency(faces)
    shared = adjacency.find_edges(np.array([1]), np.array([0]))[0]
    assert adjacency.edge_face_count[shared] == 3
    assert not topology.is_edge_manifold(faces)
    assert not topology.is_vertex_manifold(faces)
    _, fan_count = topology.vertex_fans(faces)
    np.testing.assert_array_equal(fan_count, [3, 3, 1, 1, 1])


def test_bow_tie_vertex_is_not_vertex_manifold() -> None:
    faces = np.array([[0, 1, 2], [0, 3, 4]])
    assert topology.is_edge_manifold(faces)
    assert not topology.is_vertex_manifold(faces)
    np.testing.assert_array_equal(topology.non_manifold_vertices(faces), [0])
    corner_fan, _ = topology.vertex_fans(faces)
    assert corner_fan[0, 0] != corner_fan[1, 0]
    # A face repeating a vertex is not edge-manifold either.
    assert not topology.is_edge_manifold(np.array([[0, 1, 1]]))


def test_find_edges() -> None:
    _, faces = grid_patch(2)
    adjacency = topology.edge_adjacency(faces)
    found = adjacency.find_edges(np.array([1, 0, 0]), np.array([0, 4, 8]))
    np.testing.assert_array_equal(adjacency.edges[found[:2]], [[0, 1], [0, 4]])
    assert found[2] == -1


def test_orientation_check_and_fix() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    faces = sphere.faces.copy()
    faces[5] = faces[5, [0, 2, 1]]
    assert not topology.is_consistently_oriented(faces)
    fixed, flipped = topology.orient_faces(faces)
    assert flipped == 1
    np.testing.assert_array_equal(fixed, sphere.faces)

    # Many random flips over two components: each comes back consistent, matching its first
    # face's winding.
    generator = np.random.default_rng(0)
    two = np.concatenate([sphere.faces, sphere.faces + len(sphere.vertices)])
    flips = generator.random(len(two)) < 0.5
    scrambled = two.copy()
    scrambled[flips] = scrambled[flips][:, [1, 0, 2]]
    fixed, flipped = topology.orient_faces(scrambled)
    assert topology.is_consistently_oriented(fixed)
    count, labels = topology.face_components(fixed)
    assert count == 2
    verts = np.concatenate([sphere.vertices, sphere.vertices + 3.0])
    for component in range(2):
        part = fixed[labels == component]
        volume = trimesh.Trimesh(verts, part, process=False).volume
        expected_sign = -1.0 if flips[np.flatnonzero(labels == component)[0]] else 1.0
        assert np.sign(volume) == expected_sign


def test_bad_faces_raise() -> None:
    with pytest.raises(ReconError, match="faces"):
        topology.edge_adjacency(np.zeros((3, 4), dtype=np.int64))
    with pytest.raises(ReconError, match="faces"):
        topology.edge_adjacency(np.array([[0, 1, -1]]))
    with pytest.raises(ReconError, match="vertex_count"):
        topology.vertex_valence(np.array([[0, 1, 5]]), vertex_count=3)
