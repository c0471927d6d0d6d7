"""Isotropic remeshing: topology and orientation invariants, edge-length statistics, attribute
transfer, determinism and boundaries, on an icosphere, a torus, an anisotropically
triangulated ellipsoid and an open patch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh import topology
from recon.mesh.remesh import remesh


def uv_ellipsoid(
    rings: int = 12, segments: int = 48, radii: tuple[float, float, float] = (3.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """A latitude-longitude sphere with poles on the x axis, stretched along x: long thin
    triangles around the long axis and fans of slivers at the poles. Outward winding."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    ring_points = np.stack(
        [np.cos(theta), np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi)], -1
    ).reshape(-1, 3)
    verts = np.concatenate([[[1.0, 0, 0]], ring_points, [[-1.0, 0, 0]]]) * np.array(radii)
    column = np.arange(segments)
    next_column = (column + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + next_column, 1 + column], 1)]
    for ring in range(rings - 2):
        a, b = 1 + ring * segments + column, 1 + ring * segments + next_column
        c, d = a + segments, b + segments
        faces += [np.stack([a, b, d], 1), np.stack([a, d, c], 1)]
    last_ring = 1 + (rings - 2) * segments
    south = np.full(segments, len(verts) - 1)
    faces.append(np.stack([south, last_ring + column, last_ring + next_column], 1))
    faces = np.concatenate(faces)
    if trimesh.Trimesh(verts, faces, process=False).volume < 0:
        faces = faces[:, [0, 2, 1]]
    return verts, faces


def wavy_patch(cells: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """An open unit-square patch, gently curved in z, with its boundary on x, y in {0, 1}."""
    x, y = np.meshgrid(np.linspace(0, 1, cells + 1), np.linspace(0, 1, cells + 1))
    verts = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel())], axis=1)
    index = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    return verts, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def edge_lengths(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    edges, _ = topology.unique_edges(faces)
    return np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1)


def assert_remesh_invariants(
    original_verts: np.ndarray,
    original_faces: np.ndarray,
    verts: np.ndarray,
    faces: np.ndarray,
    target: float,
) -> None:
    """Manifold, oriented, same closedness and Euler characteristic (so the same genus), no
    degenerate or flipped faces, edge lengths near the target."""
    assert topology.is_manifold(faces)
    assert topology.is_consistently_oriented(faces)
    assert topology.is_closed(faces) == topology.is_closed(original_faces)
    assert topology.euler_characteristic(faces) == topology.euler_characteristic(original_faces)
    assert len(np.unique(faces)) == len(verts)  # no unreferenced vertices
    corners = verts[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    doubled_area = np.linalg.norm(normals, axis=1)
    assert doubled_area.min() > 0.05 * target**2
    # Each face's normal agrees with the input surface's at the point nearest its centroid.
    original = trimesh.Trimesh(original_verts, original_faces, process=False)
    _, _, nearest_face = trimesh.proximity.closest_point(original, corners.mean(axis=1))
    agreement = np.einsum(
        "fc,fc->f", normals / doubled_area[:, None], original.face_normals[nearest_face]
    )
    assert agreement.min() > 0
    ratio = edge_lengths(verts, faces) / target
    assert np.mean((ratio > 0.5) & (ratio < 1.5)) >= 0.9
    assert 0.85 < ratio.mean() < 1.15


def test_icosphere_remesh_invariants_and_attributes() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    verts, faces = sphere.vertices, sphere.faces
    target = 0.1  # the icosphere's edges are about 0.08
    albedo = np.concatenate([verts[:, :1], np.full((len(verts), 2), 0.25)], axis=1)
    result = remesh(verts, faces, target, iterations=3, attributes={"albedo": albedo})
    assert_remesh_invariants(verts, faces, result.verts, result.faces, target)
    carried = result.attributes["albedo"]
    assert carried.shape == (len(result.verts), 3) and carried.dtype == albedo.dtype
    # A smooth attribute (x) stays close to the new vertices' x; constants stay exact.
    assert np.abs(carried[:, 0] - result.verts[:, 0]).max() < target
    np.testing.assert_allclose(carried[:, 1:], 0.25)
    np.testing.assert_allclose(np.asarray(result.vertex_transfer.sum(axis=1)).ravel(), 1.0)
    np.testing.assert_allclose(result.vertex_transfer @ albedo, carried)


def test_torus_keeps_genus_one() -> None:
    torus = trimesh.creation.torus(
        major_radius=1.0, minor_radius=0.35, major_sections=48, minor_sections=16
    )
    target = 0.12
    result = remesh(torus.vertices, torus.faces, target, iterations=4)
    assert_remesh_invariants(torus.vertices, torus.faces, result.verts, result.faces, target)
    assert topology.genus(result.faces) == 1


@pytest.mark.parametrize("project_to_input", [False, True])
def test_anisotropic_ellipsoid(project_to_input: bool) -> None:
    verts, faces = uv_ellipsoid()
    target = 0.25
    before = edge_lengths(verts, faces) / target
    assert np.mean((before > 0.5) & (before < 1.5)) < 0.6  # the input is badly shaped
    result = remesh(verts, faces, target, iterations=6, project_to_input=project_to_input)
    assert_remesh_invariants(verts, faces, result.verts, result.faces, target)
    assert topology.genus(result.faces) == 0
    if project_to_input:
        original = trimesh.Trimesh(verts, faces, process=False)
        _, distance, _ = trimesh.proximity.closest_point(original, result.verts)
        assert distance.max() < 1e-3 * target


def test_open_patch_keeps_its_boundary() -> None:
    verts, faces = wavy_patch()
    target = 0.08
    result = remesh(verts, faces, target, iterations=4)
    assert_remesh_invariants(verts, faces, result.verts, result.faces, target)
    boundary = np.unique(topology.boundary_edges(result.faces))
    x, y = result.verts[boundary, 0], result.verts[boundary, 1]
    to_side = np.minimum.reduce([np.abs(x), np.abs(1 - x), np.abs(y), np.abs(1 - y)])
    assert to_side.max() < 1e-9  # boundary vertices stayed on the square's sides
    for corner in ([0, 0], [1, 0], [0, 1], [1, 1]):
        assert np.min(np.linalg.norm(result.verts[:, :2] - corner, axis=1)) < 1e-9


def test_deterministic_and_torch_round_trip() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.from_numpy(sphere.faces)
    moments = {
        "albedo": torch.rand(len(verts), 3, generator=torch.Generator().manual_seed(0)),
        "adam_second_moment": torch.zeros(len(verts)),
    }
    first = remesh(verts, faces, 0.12, attributes=moments)
    second = remesh(verts, faces, 0.12, attributes=moments)
    assert first.verts.dtype == torch.float32 and first.faces.dtype == torch.int64
    assert torch.equal(first.verts, second.verts)
    assert torch.equal(first.faces, second.faces)
    assert torch.equal(first.attributes["albedo"], second.attributes["albedo"])
    assert first.attributes["adam_second_moment"].shape == (len(first.verts),)
    assert torch.all(first.attributes["adam_second_moment"] == 0)
    albedo = first.attributes["albedo"]
    assert albedo.min() >= 0 and albedo.max() <= 1  # convex combinations of the inputs


def test_halving_the_target_quadruples_the_faces() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    coarse = remesh(sphere.vertices, sphere.faces, 0.2, iterations=4)
    fine = remesh(coarse.verts, coarse.faces, 0.1, iterations=3)
    ratio = len(fine.faces) / len(coarse.faces)
    assert 3.2 < ratio < 4.8
    assert_remesh_invariants(sphere.vertices, sphere.faces, fine.verts, fine.faces, 0.1)


def test_bad_input_raises() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ReconError, match="target_length"):
        remesh(sphere.vertices, sphere.faces, 0.0)
    flipped = sphere.faces.copy()
    flipped[0] = flipped[0, [0, 2, 1]]
    with pytest.raises(ReconError, match="winding"):
        remesh(sphere.vertices, flipped, 0.3)
    fin = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(ReconError, match="edge-manifold"):
        remesh(np.random.default_rng(0).random((5, 3)), fin, 0.3)
    with pytest.raises(ReconError, match="attributes"):
        remesh(sphere.vertices, sphere.faces, 0.3, attributes={"albedo": np.zeros((3, 3))})
