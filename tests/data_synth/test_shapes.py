"""Built-in procedural shapes: closed, manifold, outward, of the stated genus, deterministic."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
import trimesh

from data_synth.shapes import SHAPE_GENUS, SHAPES, make_shape
from recon.errors import ReconError
from recon.mesh.mesh import Mesh

SHAPE_NAMES = sorted(SHAPES)


@functools.cache
def default_shape(name: str) -> Mesh:
    """Each default shape built once per test session (the checks below only read it)."""
    return make_shape(name)


def as_trimesh(mesh: Mesh) -> trimesh.Trimesh:
    """The mesh as a trimesh without any processing (no merging, no reordering)."""
    return trimesh.Trimesh(
        vertices=mesh.verts.double().numpy(), faces=mesh.faces.numpy(), process=False
    )


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges [E, 2] of faces [F, 3]."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def uv_signed_areas(mesh: Mesh) -> np.ndarray:
    """Signed areas [F] of the UV triangles."""
    corners = mesh.uvs.double().numpy()[mesh.uv_faces.numpy()]  # [F, 3, 2]
    first, second = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return 0.5 * (first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0])


def test_registry_lists_the_required_shapes() -> None:
    required = {"sphere", "torus", "rounded_box", "dumbbell", "double_torus", "blob"}
    assert required <= set(SHAPES)
    assert set(SHAPE_GENUS) == set(SHAPES)


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_dtypes_and_shapes(name: str) -> None:
    mesh = default_shape(name)
    assert mesh.verts.dtype == torch.float32 and mesh.verts.shape[1] == 3
    assert mesh.faces.dtype == torch.int64 and mesh.faces.shape[1] == 3
    # Defaults give a workable density: thousands of faces, not millions.
    assert 2_000 <= mesh.faces.shape[0] <= 30_000


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_closed_manifold_and_outward(name: str) -> None:
    mesh = as_trimesh(default_shape(name))
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.body_count == 1
    # Counter-clockwise from outside <=> positive signed volume.
    assert mesh.volume > 0
    # Every edge has exactly two faces, traversed in opposite directions (2-manifold, oriented).
    faces = default_shape(name).faces.numpy()
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_euler_characteristic_matches_genus(name: str) -> None:
    mesh = default_shape(name)
    faces = mesh.faces.numpy()
    euler = mesh.verts.shape[0] - len(unique_edges(faces)) + faces.shape[0]
    assert euler == 2 - 2 * SHAPE_GENUS[name]


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_centred_and_inside_the_unit_sphere(name: str) -> None:
    verts = default_shape(name).verts.double()
    radius = float(verts.norm(dim=1).max())
    assert 0.75 <= radius <= 1.0
    box_centre = 0.5 * (verts.min(dim=0).values + verts.max(dim=0).values)
    assert float(box_centre.norm()) < 0.02


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_no_degenerate_faces_or_duplicate_vertices(name: str) -> None:
    mesh = default_shape(name)
    trimesh_mesh = as_trimesh(mesh)
    areas = trimesh_mesh.area_faces
    assert areas.min() > 1e-3 * np.median(areas)
    assert np.degrees(trimesh_mesh.face_angles.min()) > 3.0
    faces = mesh.faces.numpy()
    assert np.all(faces[:, 0] != faces[:, 1]) and np.all(faces[:, 1] != faces[:, 2])
    assert np.all(faces[:, 0] != faces[:, 2])
    # Shared by index: no two vertices at the same position, none unused.
    verts = mesh.verts.numpy()
    assert len(np.unique(np.round(verts, 6), axis=0)) == len(verts)
    assert len(np.unique(faces)) == len(verts)


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_deterministic(name: str) -> None:
    first, second = make_shape(name, resolution=24), make_shape(name, resolution=24)
    assert torch.equal(first.verts, second.verts)
    assert torch.equal(first.faces, second.faces)
    assert (first.uvs is None) == (second.uvs is None)
    if first.uvs is not None:
        assert torch.equal(first.uvs, second.uvs)
        assert torch.equal(first.uv_faces, second.uv_faces)


@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_resolution_controls_density(name: str) -> None:
    coarse, fine = make_shape(name, resolution=16), make_shape(name, resolution=40)
    assert fine.faces.shape[0] > 2 * coarse.faces.shape[0]
    coarse_mesh = as_trimesh(coarse)
    assert coarse_mesh.is_watertight and coarse_mesh.volume > 0


@pytest.mark.parametrize("name", ["sphere", "torus", "blob"])
def test_uvs_are_seam_split_and_cover_the_unit_square(name: str) -> None:
    mesh = default_shape(name)
    assert mesh.uvs is not None and mesh.uv_faces is not None
    assert mesh.uvs.dtype == torch.float32 and mesh.uvs.shape[1] == 2
    assert mesh.uv_faces.dtype == torch.int64
    assert mesh.uv_faces.shape == mesh.faces.shape
    uvs = mesh.uvs.numpy()
    assert np.allclose(uvs.min(axis=0), 0.0, atol=1e-6)
    assert np.allclose(uvs.max(axis=0), 1.0, atol=1e-6)
    # The seams are split in UV space only: more UVs than positions, and no UV triangle wraps
    # across the texture.
    assert mesh.uvs.shape[0] > mesh.verts.shape[0]
    corners = uvs[mesh.uv_faces.numpy()]
    assert (corners.max(axis=1) - corners.min(axis=1)).max() < 0.25
    # One consistent orientation in UV space (no folded triangles).
    areas = uv_signed_areas(mesh)
    assert np.all(areas > 0) or np.all(areas < 0)


def test_torus_uvs_follow_the_parametrisation() -> None:
    mesh = default_shape("torus")
    verts = mesh.verts.double().numpy()
    corner_uvs = mesh.uvs.double().numpy()[mesh.uv_faces.numpy()].reshape(-1, 2)
    corner_verts = verts[mesh.faces.numpy()].reshape(-1, 3)
    # u is the angle around z; the seam corners at u = 1 share positions with u = 0.
    around = np.arctan2(corner_verts[:, 1], corner_verts[:, 0]) % (2 * math.pi)
    expected = around / (2 * math.pi)
    difference = np.abs(corner_uvs[:, 0] - expected)
    assert np.all(np.minimum(difference, 1.0 - difference) < 1e-4)


def test_sphere_uv_v_is_zero_at_the_north_pole() -> None:
    mesh = default_shape("sphere")
    verts = mesh.verts.double().numpy()
    corner_uvs = mesh.uvs.double().numpy()[mesh.uv_faces.numpy()].reshape(-1, 2)
    corner_verts = verts[mesh.faces.numpy()].reshape(-1, 3)
    polar_angle = np.arctan2(np.hypot(corner_verts[:, 0], corner_verts[:, 1]), corner_verts[:, 2])
    assert np.allclose(corner_uvs[:, 1], polar_angle / math.pi, atol=1e-5)
    assert corner_uvs[np.argmax(corner_verts[:, 2]), 1] == 0.0


def test_rounded_box_has_flat_sides_and_sharp_edges() -> None:
    mesh = as_trimesh(default_shape("rounded_box"))
    normals, areas = mesh.face_normals, mesh.area_faces
    # Most of the area lies on the six flat sides (normals along an axis)...
    on_axis = np.abs(normals).max(axis=1) > 1.0 - 1e-9
    assert areas[on_axis].sum() > 0.85 * areas.sum()
    # ...and the turn between adjacent sides is concentrated in a narrow band.
    assert np.degrees(mesh.face_adjacency_angles.max()) >= 40.0
    sharp = make_shape("rounded_box", bevel_radius=0.0)
    angles = np.degrees(as_trimesh(sharp).face_adjacency_angles)
    assert np.isclose(angles.max(), 90.0)
    assert as_trimesh(sharp).is_watertight


def test_dumbbell_has_a_thin_rod() -> None:
    verts = default_shape("dumbbell").verts.double().numpy()
    middle = np.abs(verts[:, 0]) < 0.05
    distance_from_axis = np.hypot(verts[middle, 1], verts[middle, 2])
    assert 0.06 < distance_from_axis.max() < 0.1


def test_blob_seed_changes_the_shape_but_not_the_topology() -> None:
    first, second = make_shape("blob", seed=1), make_shape("blob", seed=2)
    assert torch.equal(first.faces, second.faces)
    assert not torch.allclose(first.verts, second.verts)
    assert as_trimesh(second).is_watertight


def test_unknown_name_suggests_the_closest() -> None:
    with pytest.raises(ReconError) as error:
        make_shape("sphre")
    message = str(error.value)
    assert "'sphere'" in message and "did you mean" in message
    assert all(name in message for name in SHAPES)
    with pytest.raises(ReconError, match="double_torus"):
        make_shape("double-torus")


def test_bad_parameters_raise_recon_error() -> None:
    with pytest.raises(ReconError, match="major_radius"):
        make_shape("torus", major_radiu=0.5)
    with pytest.raises(ReconError, match="minor_radius"):
        make_shape("torus", major_radius=0.3, minor_radius=0.4)
    with pytest.raises(ReconError, match="resolution"):
        make_shape("sphere", resolution=2)
    with pytest.raises(ReconError, match="unit sphere"):
        make_shape("sphere", radius=1.5)
    with pytest.raises(ReconError, match="separation"):
        make_shape("double_torus", separation=2.0)
