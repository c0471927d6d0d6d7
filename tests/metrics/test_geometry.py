"""Geometry metrics against analytic cases (spheres), mesh statistics, per-vertex error, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.metrics import geometry_metrics, mesh_stats, per_vertex_error, sampling_floor

# Samples per mesh: enough for stable means, small enough to keep the file at a few seconds.
APPROXIMATE_SAMPLES = 20_000
EXACT_SAMPLES = 4_000
# The bounding-box diagonal of a sphere of radius 1 (the reference in every sphere test).
DIAGONAL = 2.0 * math.sqrt(3.0)


def as_mesh(mesh: trimesh.Trimesh) -> Mesh:
    return Mesh(
        torch.tensor(mesh.vertices, dtype=torch.float32),
        torch.tensor(mesh.faces, dtype=torch.int64),
    )


def sphere(radius: float = 1.0, subdivisions: int = 4) -> Mesh:
    """An icosphere (5120 faces at 4 subdivisions); its faces sag at most ~1e-3 inside."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh.vertices *= radius
    return as_mesh(mesh)


def moved(mesh: Mesh, offset: tuple[float, float, float]) -> Mesh:
    return Mesh(mesh.verts + torch.tensor(offset), mesh.faces)


@pytest.fixture(scope="module")
def unit_sphere() -> Mesh:
    return sphere()


def test_mesh_against_itself_approximate_sits_on_the_sampling_floor(unit_sphere: Mesh) -> None:
    result = geometry_metrics(unit_sphere, unit_sphere, samples=APPROXIMATE_SAMPLES)
    # The floor: half the mean sample spacing, 0.5 * sqrt(area / N), area in diagonal units.
    area = 4 * math.pi / DIAGONAL**2
    floor = 0.5 * math.sqrt(area / APPROXIMATE_SAMPLES)
    assert result["sampling_floor"] == pytest.approx(floor, rel=0.01)
    assert sampling_floor(area, APPROXIMATE_SAMPLES) == pytest.approx(floor, rel=0.01)
    assert 0.85 * floor < result["chamfer_l1"] < 1.15 * floor
    assert result["chamfer_l2"] == pytest.approx(area / (math.pi * APPROXIMATE_SAMPLES), rel=0.2)
    assert result["normal_consistency"] > 0.99
    assert result["f1@2%"] == 1.0 and result["f1@1%"] > 0.99
    assert result["samples"] == APPROXIMATE_SAMPLES
    assert result["reference_diagonal"] == pytest.approx(DIAGONAL, rel=1e-6)


def test_mesh_against_itself_exact_is_zero(unit_sphere: Mesh) -> None:
    result = geometry_metrics(unit_sphere, unit_sphere, samples=EXACT_SAMPLES, exact=True)
    assert result["chamfer_l1"] < 1e-9 and result["hausdorff"] < 1e-9
    assert result["sampling_floor"] == 0.0
    assert result["normal_consistency"] > 0.999
    assert all(result[f"f1@{label}"] == 1.0 for label in ("0.5%", "1%", "2%"))


def test_concentric_spheres_measure_the_radial_gap(unit_sphere: Mesh) -> None:
    gap = 0.1
    outer = sphere(1.0 + gap)
    expected = gap / DIAGONAL
    approximate = geometry_metrics(outer, unit_sphere, samples=APPROXIMATE_SAMPLES)
    exact = geometry_metrics(outer, unit_sphere, samples=APPROXIMATE_SAMPLES, exact=True)
    for result in (approximate, exact):
        assert result["chamfer_l1"] == pytest.approx(expected, rel=0.1)
        assert result["accuracy"] == pytest.approx(expected, rel=0.1)
        assert result["completeness"] == pytest.approx(expected, rel=0.1)
        assert result["chamfer_l2"] == pytest.approx(expected**2, rel=0.2)
        assert result["hausdorff_p95"] == pytest.approx(expected, rel=0.1)
    assert exact["hausdorff"] == pytest.approx(expected, rel=0.05)
    assert exact["chamfer_l1"] == pytest.approx(expected, rel=0.02)
    # Same samples in both modes: the nearest SAMPLE is never nearer than the nearest surface
    # point, and the excess stays within the sampling floor.
    excess = approximate["chamfer_l1"] - exact["chamfer_l1"]
    assert 0.0 <= excess <= approximate["sampling_floor"]
    assert exact["hausdorff"] <= approximate["hausdorff"]


def test_translated_copy_gives_the_analytic_distances(unit_sphere: Mesh) -> None:
    shift = 0.05
    direction = np.array([1.0, 2.0, 2.0]) / 3.0
    shifted = moved(unit_sphere, tuple(shift * direction))
    # A point at cos(angle) = u to the shift on one sphere lies |sqrt(1 - 2 s u + s^2) - 1| from
    # the other; u is uniform on [-1, 1] over the sphere, and both directions are alike.
    u = np.linspace(-1.0, 1.0, 200_001)
    expected = float(np.mean(np.abs(np.sqrt(1 - 2 * shift * u + shift**2) - 1))) / DIAGONAL
    exact = geometry_metrics(shifted, unit_sphere, samples=EXACT_SAMPLES, exact=True)
    assert exact["chamfer_l1"] == pytest.approx(expected, rel=0.05)
    assert exact["hausdorff"] == pytest.approx(shift / DIAGONAL, rel=0.05)
    approximate = geometry_metrics(shifted, unit_sphere, samples=APPROXIMATE_SAMPLES)
    assert abs(approximate["chamfer_l1"] - expected) <= approximate["sampling_floor"]


def test_normal_consistency_is_orientation_blind_but_sees_noise(unit_sphere: Mesh) -> None:
    flipped = Mesh(unit_sphere.verts, unit_sphere.faces[:, [0, 2, 1]])
    exact = geometry_metrics(flipped, unit_sphere, samples=EXACT_SAMPLES, exact=True)
    assert exact["normal_consistency"] > 0.999 and exact["chamfer_l1"] < 1e-9
    approximate = geometry_metrics(flipped, unit_sphere, samples=APPROXIMATE_SAMPLES)
    assert approximate["normal_consistency"] > 0.99
    generator = torch.Generator().manual_seed(0)
    noisy = Mesh(
        unit_sphere.verts + 0.01 * torch.randn(unit_sphere.verts.shape, generator=generator),
        unit_sphere.faces,
    )
    noisy_exact = geometry_metrics(noisy, unit_sphere, samples=EXACT_SAMPLES, exact=True)
    noisy_approximate = geometry_metrics(noisy, unit_sphere, samples=APPROXIMATE_SAMPLES)
    assert noisy_exact["normal_consistency"] < 0.98
    assert noisy_approximate["normal_consistency"] < 0.98


@pytest.mark.parametrize("exact", [False, True])
def test_f1_switches_at_the_threshold(unit_sphere: Mesh, exact: bool) -> None:
    threshold = 0.02
    samples = EXACT_SAMPLES if exact else APPROXIMATE_SAMPLES
    for factor, expected_f1 in ((0.5, 1.0), (1.5, 0.0)):
        gap = factor * threshold * DIAGONAL
        result = geometry_metrics(
            sphere(1.0 + gap), unit_sphere, samples=samples, thresholds=(threshold,), exact=exact
        )
        assert result["f1@2%"] == expected_f1
        assert result["precision@2%"] == expected_f1 and result["recall@2%"] == expected_f1
        assert "f1@1%" not in result


def test_results_are_deterministic_in_the_seed(unit_sphere: Mesh) -> None:
    outer = sphere(1.05, subdivisions=3)
    first = geometry_metrics(outer, unit_sphere, samples=5_000, seed=7)
    again = geometry_metrics(outer, unit_sphere, samples=5_000, seed=7)
    other = geometry_metrics(outer, unit_sphere, samples=5_000, seed=8)
    assert first == again
    assert first["chamfer_l1"] != other["chamfer_l1"]


def test_per_vertex_error_is_the_distance_to_the_reference_surface(unit_sphere: Mesh) -> None:
    gap = 0.1
    errors = per_vertex_error(sphere(1.0 + gap), unit_sphere)
    assert errors.shape == (unit_sphere.verts.shape[0],) and errors.dtype == torch.float32
    # Outer vertices lie on radius 1.1; the inner mesh's faces sag up to ~1e-3 inside radius 1.
    assert torch.all(errors >= gap / DIAGONAL * (1 - 1e-4))
    assert torch.all(errors <= (gap + 2e-3) / DIAGONAL)
    assert float(per_vertex_error(unit_sphere, unit_sphere).max()) < 1e-6


def test_mesh_stats_of_closed_surfaces() -> None:
    ball = mesh_stats(sphere(subdivisions=2))
    assert ball["watertight"] and ball["edge_manifold"] and ball["vertex_manifold"]
    assert ball["genus"] == 0 and ball["euler_characteristic"] == 2 and ball["components"] == 1
    assert ball["boundary_edges"] == 0 and ball["degenerate_faces"] == 0
    assert ball["winding_consistent"] and ball["faces"] == 320 and ball["vertices"] == 162
    assert ball["surface_area"] == pytest.approx(4 * math.pi, rel=0.05)
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    torus_stats = mesh_stats(as_mesh(torus))
    assert torus_stats["watertight"] and torus_stats["genus"] == 1
    assert torus_stats["euler_characteristic"] == torus.euler_number == 0
    # Two separate spheres: two components of genus 0.
    pair = trimesh.util.concatenate(
        [trimesh.creation.icosphere(1), trimesh.creation.icosphere(1).apply_translation([3, 0, 0])]
    )
    pair_stats = mesh_stats(as_mesh(pair))
    assert pair_stats["components"] == 2 and pair_stats["genus"] == 0


def test_mesh_stats_of_open_and_non_manifold_meshes() -> None:
    closed = trimesh.creation.icosphere(subdivisions=2)
    # One face removed: a triangular hole of three boundary edges, no genus.
    holed = mesh_stats(as_mesh(trimesh.Trimesh(closed.vertices, closed.faces[1:], process=False)))
    assert holed["boundary_edges"] == 3 and not holed["watertight"] and holed["genus"] is None
    assert holed["edge_manifold"] and holed["vertex_manifold"]
    # A fin: three triangles on one edge.
    verts = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=torch.float32
    )
    fin = mesh_stats(Mesh(verts, torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])))
    assert fin["non_manifold_edges"] == 1 and not fin["edge_manifold"]
    assert fin["boundary_edges"] == 6 and fin["components"] == 1 and fin["genus"] is None
    # A bow tie: two triangles sharing only a vertex (edge-manifold, not vertex-manifold).
    bow_verts = torch.tensor(
        [[0, 0, 0], [1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0]], dtype=torch.float32
    )
    bow = mesh_stats(Mesh(bow_verts, torch.tensor([[0, 1, 2], [0, 3, 4]])))
    assert bow["edge_manifold"] and bow["non_manifold_vertices"] == 1 and not bow["vertex_manifold"]
    # Degenerate faces: a repeated index and three collinear points; plus one unused vertex.
    line_verts = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 5, 5]], dtype=torch.float32
    )
    line = mesh_stats(Mesh(line_verts, torch.tensor([[0, 1, 2], [0, 1, 1], [0, 1, 3]])))
    assert line["degenerate_faces"] == 2 and line["unreferenced_vertices"] == 1


def test_bad_inputs_name_the_argument(unit_sphere: Mesh) -> None:
    empty = Mesh(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(ReconError, match="predicted"):
        geometry_metrics(empty, unit_sphere, samples=100)
    with pytest.raises(ReconError, match="reference"):
        geometry_metrics(unit_sphere, empty, samples=100)
    with pytest.raises(ReconError, match="reference"):
        per_vertex_error(unit_sphere, empty)
    with pytest.raises(ReconError, match="mesh"):
        mesh_stats(empty)
    elsewhere = sphere(subdivisions=1)
    elsewhere.verts = elsewhere.verts.to("meta")  # a second device on any machine
    with pytest.raises(ReconError, match="reference"):
        geometry_metrics(unit_sphere, elsewhere, samples=100)
    with pytest.raises(ReconError, match="reference"):
        per_vertex_error(unit_sphere, elsewhere)
    flat = Mesh(torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), torch.tensor([[0, 1, 2]]))
    with pytest.raises(ReconError, match="predicted.*zero surface area"):
        geometry_metrics(flat, unit_sphere, samples=100)
    with pytest.raises(ReconError, match="samples"):
        geometry_metrics(unit_sphere, unit_sphere, samples=0)
    with pytest.raises(ReconError, match="thresholds"):
        geometry_metrics(unit_sphere, unit_sphere, samples=100, thresholds=(0.01, -0.1))
    with pytest.raises(ReconError, match="predicted"):
        geometry_metrics(unit_sphere.verts, unit_sphere, samples=100)
