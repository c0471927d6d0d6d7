"""The fitted material against the true one over the surface (recon.metrics.material): a mesh
against itself with another UV layout and its map baked again scores ~0, a perturbed map scores
its perturbation, and unseen or far-away surface is left out."""

from __future__ import annotations

import math

import pytest
import torch

from recon.camera import Cameras, intrinsics_from_fov, look_at
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.mesh.uv import bake_vertex_attribute, dilate
from recon.metrics.material import material_metrics, sample_maps, seen_points
from tests.material_scenes import position_material, unwrapped_sphere


@pytest.fixture(scope="module")
def spheres() -> tuple[Mesh, torch.Tensor, Mesh, torch.Tensor]:
    reference, reference_maps = unwrapped_sphere(128)
    fitted, fitted_maps = unwrapped_sphere(96)
    return reference, reference_maps, fitted, fitted_maps


def test_the_reference_against_itself_with_other_uvs_scores_about_zero(spheres):
    reference, reference_maps, fitted, fitted_maps = spheres
    # Another layout: the same surface point has other UVs in the two meshes.
    assert not torch.equal(fitted.uvs, reference.uvs)
    metrics = material_metrics(fitted, fitted_maps, reference, reference_maps, samples=4000)
    assert metrics["compared_fraction"] == 1.0 and metrics["seen_fraction"] is None
    # What is left is the bilinear lookup's blend across texel borders at chart edges.
    assert metrics["roughness_mae"] < 2e-3 and metrics["metalness_mae"] < 3e-3
    assert metrics["roughness_within_tolerance"] == 1.0
    assert metrics["metalness_within_tolerance"] == 1.0
    assert abs(metrics["roughness_true_median"] - 0.3) < 0.02
    # On a sphere x is uniform in [-1, 1] by area (Archimedes): the best uniform roughness
    # (0.3) is off by 0.15 E|x| = 0.075 on average.
    assert metrics["roughness_uniform_mae"] == pytest.approx(0.075, abs=0.004)


def test_a_perturbed_map_scores_its_perturbation(spheres):
    reference, reference_maps, fitted, fitted_maps = spheres
    shifted = fitted_maps + torch.tensor([0.08, -0.2])
    metrics = material_metrics(fitted, shifted, reference, reference_maps, samples=4000)
    assert metrics["roughness_mae"] == pytest.approx(0.08, abs=3e-3)
    assert metrics["roughness_bias"] == pytest.approx(0.08, abs=3e-3)
    assert metrics["roughness_within_tolerance"] == 0.0
    assert metrics["metalness_bias"] == pytest.approx(-0.2, abs=3e-3)
    assert metrics["metalness_median_error"] == pytest.approx(0.2, abs=3e-3)


def test_a_map_wrong_where_the_meshes_part_is_not_compared(spheres):
    """Samples farther than max_distance from the reference compare a geometry error, not a
    material one: a fitted sphere bulging out on one side is compared on the rest only."""
    reference, reference_maps, fitted, fitted_maps = spheres
    bulge = fitted.verts[:, 0] > 0.5
    verts = fitted.verts.clone()
    verts[bulge] *= 1.1
    moved = Mesh(verts, fitted.faces, uvs=fitted.uvs, uv_faces=fitted.uv_faces)
    metrics = material_metrics(moved, fitted_maps, reference, reference_maps, samples=4000)
    assert 0.6 < metrics["compared_fraction"] < 0.95
    assert metrics["matched_fraction"] == metrics["compared_fraction"]
    assert metrics["roughness_mae"] < 3e-3


def test_surface_no_training_view_saw_is_left_out(spheres):
    reference, reference_maps, fitted, fitted_maps = spheres
    eye = torch.tensor([[0.0, 0.0, 4.0]])
    cameras = Cameras(
        look_at(eye, torch.zeros(1, 3)), intrinsics_from_fov(40.0, (48, 48)), (48, 48)
    )
    centres = fitted.verts[fitted.faces].mean(1).double().numpy()
    seen = seen_points(centres, fitted, cameras)
    # Seen from +z: the front (short of the silhouette, at z 0.25, where a pixel spans a steep
    # depth range), none of the back.
    assert seen[centres[:, 2] > 0.6].all() and not seen[centres[:, 2] < 0.0].any()
    # A material wrong only on the unseen back does not count.
    wrong_back = position_material(fitted.verts)
    wrong_back[fitted.verts[:, 2] < -0.05, 0] += 0.3
    baked, coverage = bake_vertex_attribute(fitted, wrong_back, tuple(fitted_maps.shape[:2]))
    maps = dilate(baked, coverage)
    seen_only = material_metrics(fitted, maps, reference, reference_maps, 4000, seen_from=cameras)
    everywhere = material_metrics(fitted, maps, reference, reference_maps, 4000)
    assert 0.3 < seen_only["seen_fraction"] < 0.7
    assert seen_only["compared_fraction"] == seen_only["seen_fraction"]
    assert seen_only["roughness_mae"] < 3e-3 and everywhere["roughness_mae"] > 0.1


def test_sample_maps_reads_texel_centres_exactly():
    maps = torch.arange(8, dtype=torch.float32).reshape(2, 2, 2)
    centres = torch.tensor([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75]]).numpy()
    torch.testing.assert_close(sample_maps(maps, centres), maps.reshape(4, 2)[:3])


def test_maps_of_the_wrong_shape_are_named(spheres):
    reference, reference_maps, fitted, fitted_maps = spheres
    with pytest.raises(ReconError, match=r"fitted_maps: expected \[h, w, >= 2\].*\(96, 96, 1\)"):
        material_metrics(fitted, fitted_maps[..., :1], reference, reference_maps, 100)
    far = Mesh(fitted.verts + 10 * math.pi, fitted.faces, uvs=fitted.uvs, uv_faces=fitted.uv_faces)
    with pytest.raises(ReconError, match="none of 100 samples"):
        material_metrics(far, fitted_maps, reference, reference_maps, 100)
