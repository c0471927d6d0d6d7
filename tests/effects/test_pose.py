"""Model effect pose_error: Rodrigues rotations, identity at zero, gradients against central
differences (float64, on the cameras), and recovery of per-view corrections through renders."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from recon.effects import PoseError
from recon.effects.pose import axis_angle_to_matrix, skew
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer

ROTATIONS = torch.tensor([[0.0, 0.0, 0.0], [0.01, -0.015, 0.005], [-0.012, 0.008, 0.01]])
TRANSLATIONS = torch.tensor([[0.0, 0.0, 0.0], [0.02, -0.01, 0.03], [-0.015, 0.02, -0.02]])


def test_axis_angle_matches_the_matrix_exponential():
    vectors = torch.tensor(
        [[0.0, 0.0, 0.0], [1e-5, -2e-5, 0.0], [0.3, -0.2, 0.5], [0.0, 3.0, 0.0]],
        dtype=torch.float64,
    )
    rotations = axis_angle_to_matrix(vectors)
    torch.testing.assert_close(rotations, torch.linalg.matrix_exp(skew(vectors)))
    assert torch.equal(rotations[0], torch.eye(3, dtype=torch.float64))


def test_identity_at_zero_is_exact(torus_scene):
    effect = PoseError(3)
    cameras = effect.apply_to_cameras(torus_scene.cameras, torus_scene.views)
    assert torch.equal(cameras.world_to_cam, torus_scene.cameras.world_to_cam)
    assert effect.apply_to_cameras(torus_scene.cameras, None) is torus_scene.cameras


def test_gradients_match_central_differences(torus_scene, central_difference):
    cameras = torus_scene.cameras
    cameras = replace(cameras, world_to_cam=cameras.world_to_cam.double())
    effect = PoseError(3, translation_scale=0.5).double()
    weights = torch.rand(3, 4, 4, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for rotation in (torch.zeros(3, 3), ROTATIONS):
        with torch.no_grad():
            effect.rotation.copy_(rotation)
            effect.translation.copy_(TRANSLATIONS)

        def loss():
            return (
                effect.apply_to_cameras(cameras, torch.tensor([2, 1, 0])).world_to_cam * weights
            ).sum()

        effect.zero_grad()
        loss().backward()
        for parameter, index in ((effect.rotation, (1, 0)), (effect.rotation, (2, 2))):
            expected = central_difference(loss, parameter, index)
            assert parameter.grad[index].item() == pytest.approx(expected, rel=1e-6, abs=1e-9)
        index = (1, 1)
        expected = central_difference(loss, effect.translation, index)
        assert effect.translation.grad[index].item() == pytest.approx(expected, rel=1e-6)
        # View 0 is pinned: no gradient, identity correction.
        assert torch.all(effect.rotation.grad[0] == 0) and torch.all(
            effect.translation.grad[0] == 0
        )
        assert torch.equal(effect.corrections()[0], torch.eye(4, dtype=torch.float64))


def _render(scene, effect, topology):
    cameras = effect.apply_to_cameras(scene.cameras, scene.views)
    return Renderer().render(scene.mesh, cameras, scene.lighting, topology=topology)


def _target(scene, rotation, translation, topology):
    effect = PoseError(3)
    with torch.no_grad():
        effect.rotation.copy_(rotation)
        effect.translation.copy_(translation)
        output = _render(scene, effect, topology)
    return effect, (output.color, output.alpha)


def test_render_gradient_at_zero_points_towards_the_truth(torus_scene):
    topology = build_topology(torus_scene.mesh.faces, torus_scene.mesh.verts.shape[0])
    _, (color, alpha) = _target(torus_scene, ROTATIONS * 0.5, torch.zeros(3, 3), topology)
    effect = PoseError(3)
    output = _render(torus_scene, effect, topology)
    loss = ((output.color - color) ** 2).mean() + ((output.alpha - alpha) ** 2).mean()
    loss.backward()
    descent = -effect.rotation.grad
    for view in (1, 2):
        cosine = torch.nn.functional.cosine_similarity(descent[view], ROTATIONS[view], dim=0)
        assert float(cosine) > 0.5


def _fit(scene, effect, target, topology, groups, steps, adam_fit):
    chosen = [group for group in effect.parameter_groups() if group["name"] in groups]
    return adam_fit(effect, lambda: tuple(_outputs(scene, effect, topology)), target, steps, chosen)


def _outputs(scene, effect, topology):
    output = _render(scene, effect, topology)
    return output.color, output.alpha


def test_recovers_rotations_with_translations_held(torus_scene, adam_fit):
    topology = build_topology(torus_scene.mesh.faces, torus_scene.mesh.verts.shape[0])
    truth, target = _target(torus_scene, ROTATIONS, torch.zeros(3, 3), topology)
    effect = PoseError(3)
    _fit(torus_scene, effect, target, topology, {"pose_error.rotation"}, 80, adam_fit)
    recovered = torch.tensor(effect.parameters_summary()["rotation_vectors_deg"])
    expected = torch.tensor(truth.parameters_summary()["rotation_vectors_deg"])
    assert float((recovered - expected).norm(dim=-1).max()) < 0.1  # degrees
    assert torch.all(recovered[0] == 0)


def test_recovers_poses_up_to_reprojection(torus_scene, adam_fit):
    # Jointly, a small rotation about the camera's x or y axis and a sideways shift move the
    # image almost alike at 40 degrees field of view (only perspective tells them apart): the
    # valley is flat, so the check is on what the images constrain, the projected points.
    topology = build_topology(torus_scene.mesh.faces, torus_scene.mesh.verts.shape[0])
    truth, target = _target(torus_scene, ROTATIONS, TRANSLATIONS, topology)
    effect = PoseError(3)
    groups = {"pose_error.rotation", "pose_error.translation"}
    _fit(torus_scene, effect, target, topology, groups, 100, adam_fit)
    with torch.no_grad():
        views = torus_scene.views
        recovered = effect.apply_to_cameras(torus_scene.cameras, views)
        expected = truth.apply_to_cameras(torus_scene.cameras, views)
        verts = torus_scene.mesh.verts
        error = (recovered.project_to_pixels(verts) - expected.project_to_pixels(verts)).norm(
            dim=-1
        )
    assert float(error.mean(dim=-1).max()) < 0.1  # pixels, at 32 x 32
    summary = effect.parameters_summary()
    assert summary["rotation_deg"][0] == 0.0 and summary["translation_norms"][0] == 0.0
    # The correction moved the views by about the true amount.
    expected_angles = torch.rad2deg(ROTATIONS.norm(dim=-1))
    assert all(
        0.3 * float(angle) < recovered_angle < 3 * float(angle)
        for angle, recovered_angle in zip(
            expected_angles[1:], summary["rotation_deg"][1:], strict=True
        )
    )
