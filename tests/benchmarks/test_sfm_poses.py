"""benchmarks.sfm_poses: the similarity alignment recovers a known transform, and the pose
errors of cameras that differ from the truth by a similarity alone are zero, while a turned
camera's rotation error is its turn."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.sfm_poses import pose_errors, umeyama
from recon.camera import orbit_cameras


def rotation_about(axis: list[float], angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def test_umeyama_recovers_a_similarity() -> None:
    points = np.random.default_rng(0).normal(size=(20, 3))
    rotation = rotation_about([0.3, 1.0, -0.2], 1.1)
    moved = 2.5 * points @ rotation.T + np.array([1.0, -2.0, 0.5])
    scale, found, translation = umeyama(points, moved)
    assert scale == pytest.approx(2.5)
    assert np.allclose(found, rotation) and np.allclose(translation, [1.0, -2.0, 0.5])


def test_pose_errors_ignore_a_similarity_and_measure_a_turn() -> None:
    truth = orbit_cameras(8, (32, 32), distance=3.0)
    # The same rig in another frame, x' = s R x + t: a camera x_cam = W x + w becomes
    # x_cam = W R^T x' + (s w - W R^T t) (up to the scale s, which SfM cannot know).
    rotation = torch.tensor(rotation_about([1.0, 0.2, 0.1], 0.8), dtype=torch.float32)
    scale, offset = 0.5, torch.tensor([3.0, 1.0, -2.0])
    world_to_cam = truth.world_to_cam.clone()
    turned_axes = truth.world_to_cam[:, :3, :3] @ rotation.T
    world_to_cam[:, :3, :3] = turned_axes
    world_to_cam[:, :3, 3] = scale * truth.world_to_cam[:, :3, 3] - turned_axes @ offset
    estimate = type(truth)(world_to_cam, truth.intrinsics, truth.image_size, truth.near, truth.far)
    errors = pose_errors(truth, estimate)
    assert errors["rotation_error_deg"]["max"] < 0.1  # float32 cameras
    assert errors["centre_error"]["max"] < 1e-3
    assert errors["alignment_scale"] == pytest.approx(2.0, rel=1e-4)
    # Turn one camera by 5 degrees about its own axis: its rotation error is 5 degrees.
    turned = world_to_cam.clone()
    turned[3, :3, :3] = (
        torch.tensor(rotation_about([0, 0, 1], math.radians(5.0))).float() @ (turned[3, :3, :3])
    )
    turned[3, :3, 3] = (
        torch.tensor(rotation_about([0, 0, 1], math.radians(5.0))).float() @ (turned[3, :3, 3])
    )
    errors = pose_errors(truth, type(truth)(turned, truth.intrinsics, (32, 32), 0.1, 10.0))
    assert errors["rotation_error_deg"]["max"] == pytest.approx(5.0, abs=0.1)
    assert errors["centre_error"]["max"] < 1e-3
