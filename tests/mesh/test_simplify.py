"""Decimation with fast-simplification and mesh repair: the output is an oriented manifold
without zero-area faces, near the requested face count; repair finds and counts each defect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh import topology
from recon.mesh.simplify import RepairReport, repair, simplify


def load_merged(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Geometry of an OBJ with UV-seam and normal copies merged (positions shared by index)."""
    mesh = trimesh.load(path, process=False, force="mesh")
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def doubled_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    corners = verts[faces]
    return np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )


def assert_clean(verts: np.ndarray, faces: np.ndarray) -> None:
    assert topology.is_manifold(faces)
    assert topology.is_consistently_oriented(faces)
    assert doubled_areas(verts, faces).min() > 0
    assert len(np.unique(faces)) == len(verts)


def check_simplify(verts: np.ndarray, faces: np.ndarray, fraction: float) -> None:
    target = int(fraction * len(faces))
    out_verts, out_faces = simplify(verts, faces, target_faces=target)
    assert_clean(out_verts, out_faces)
    assert abs(len(out_faces) - target) <= 0.05 * target
    if topology.is_closed(faces):
        assert topology.is_closed(out_faces)
        assert trimesh.Trimesh(out_verts, out_faces, process=False).volume > 0


@pytest.mark.parametrize("fraction", [0.5, 0.1])
def test_simplify_sphere_and_torus(fraction: float) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4)
    check_simplify(sphere.vertices, sphere.faces, fraction)
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    check_simplify(torus.vertices, torus.faces, fraction)


@pytest.mark.shared
@pytest.mark.parametrize("name", ["bob_tri.obj", "spot_triangulated.obj"])
def test_simplify_shared_meshes(shared_meshes: Path, name: str) -> None:
    path = shared_meshes / name
    if not path.is_file():
        pytest.skip(f"{name} is absent")
    verts, faces = load_merged(path)
    for fraction in (0.5, 0.1):
        check_simplify(verts, faces, fraction)
    if name == "bob_tri.obj":
        _, small = simplify(verts, faces, target_faces=len(faces) // 4)
        assert topology.genus(small) == 1


def test_simplify_arguments_and_types() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.from_numpy(sphere.faces)
    out_verts, out_faces = simplify(verts, faces, target_reduction=0.75)
    assert out_verts.dtype == torch.float32 and out_faces.dtype == torch.int64
    assert abs(len(out_faces) - 320) <= 16
    # A target at or above the face count only repairs.
    same_verts, same_faces = simplify(sphere.vertices, sphere.faces, target_faces=10**6)
    np.testing.assert_array_equal(same_faces, sphere.faces)
    with pytest.raises(ReconError, match="exactly one"):
        simplify(verts, faces)
    with pytest.raises(ReconError, match="exactly one"):
        simplify(verts, faces, target_faces=100, target_reduction=0.5)
    with pytest.raises(ReconError, match="target_reduction"):
        simplify(verts, faces, target_reduction=1.0)


def test_repair_leaves_a_clean_mesh_alone() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    verts, faces, report = repair(sphere.vertices, sphere.faces)
    assert report == RepairReport() and report.changes == 0
    np.testing.assert_array_equal(faces, sphere.faces)
    np.testing.assert_array_equal(verts, sphere.vertices)


def test_repair_fixes_and_counts_each_defect() -> None:
    cube = trimesh.creation.box()
    verts = np.asarray(cube.vertices, dtype=np.float64)
    faces = np.asarray(cube.faces)
    count = len(verts)
    # An inverted closed part: a second cube, shifted, wound inside out.
    inverted = faces[:, [0, 2, 1]] + count
    # An open fan beside it: a fin (third face on an edge, smallest) and a bow-tie vertex.
    fan_verts = np.array(
        [
            [5.0, 0, 0],  # a = 2 count
            [6.0, 0, 0],  # b
            [5.5, 1, 0],  # c
            [5.5, -1, 0],  # d
            [5.5, 0, 0.2],  # e: the fin's tip, small
            [4.0, 1, 0],  # f: bow-tie wing at a
            [4.0, -1, 0],  # g
            [9.0, 9, 9],  # h: unreferenced
        ]
    )
    a, b, c, d, e, f, g, _, midpoint = 2 * count + np.arange(9)
    fan_verts = np.concatenate([fan_verts, [[5.5, 0, 0]]])  # midpoint of a-b
    fan_faces = np.array([[a, b, c], [b, a, d], [a, b, e], [a, f, g]])
    all_verts = np.concatenate([verts, verts + [2.0, 0, 0], fan_verts])
    all_faces = np.concatenate(
        [
            faces,
            inverted,
            fan_faces,
            [[a, a, b]],  # repeats a vertex
            [[a, midpoint, b]],  # collinear: zero area
            [faces[3, [1, 2, 0]]],  # a cube face again, rotated
        ]
    )
    all_faces[7] = all_faces[7, [0, 2, 1]]  # one cube face flipped

    out_verts, out_faces, report = repair(all_verts, all_faces)
    assert report.degenerate_faces_removed == 1
    assert report.zero_area_faces_removed == 1
    assert report.duplicate_faces_removed == 1
    assert report.non_manifold_faces_removed == 1
    assert report.non_manifold_vertices_split == 1
    # The stray point, the midpoint (only in the zero-area face) and the fin's tip.
    assert report.unreferenced_vertices_removed == 3
    assert report.faces_flipped == 1 + 12  # the flipped cube face, then the inverted cube
    assert report.inconsistent_edges_left == 0
    assert report.changes == 1 + 1 + 1 + 1 + 1 + 3 + 13
    assert_clean(out_verts, out_faces)
    assert len(out_faces) == 12 + 12 + 3
    count, labels = topology.face_components(out_faces)
    assert count == 4  # two cubes, the two-face diamond, the split-off wing
    for component in range(count):
        part = out_faces[labels == component]
        if topology.is_closed(part):
            assert trimesh.Trimesh(out_verts, part, process=False).volume > 0
    # The fin's small tip face went; the two big faces on the shared edge stayed.
    assert not np.any(np.all(np.isclose(out_verts, [5.5, 0, 0.2]), axis=1))
    assert np.any(np.all(np.isclose(out_verts, [5.5, 1, 0]), axis=1))


def test_repair_keeps_torch_types() -> None:
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 1, 1]])
    out_verts, out_faces, report = repair(verts, faces)
    assert out_verts.dtype == torch.float64 and out_faces.dtype == torch.int64
    assert out_verts.shape == (3, 3) and out_faces.shape == (1, 3)
    assert report.degenerate_faces_removed == 1 and report.unreferenced_vertices_removed == 1
