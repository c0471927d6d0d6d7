"""World camera and response effects: pose error (rigid, realised, images untouched) and the
filmic response curve (monotone, 0 -> 0, stored as what an sRGB reader must see)."""

from __future__ import annotations

import math

import torch

from data_synth.effects.base import Capture
from data_synth.effects.camera import PoseError, axis_angle_to_matrix
from data_synth.effects.response import TABLE_SAMPLES, ResponseCurve
from recon.camera.cameras import check_rigid, orbit_cameras, rigid_inverse
from recon.io.images import linear_to_srgb, srgb_to_linear


def make_capture(count: int = 5, size: int = 16) -> Capture:
    images = torch.rand(count, size, size, 3, generator=torch.Generator().manual_seed(0))
    alpha = torch.rand(count, size, size, 1, generator=torch.Generator().manual_seed(1))
    return Capture(images, alpha, orbit_cameras(count, (size, size), distance=4.0))


# -------------------------------------------------------------------------------- pose error


def test_axis_angle_to_matrix_matches_a_known_rotation() -> None:
    rotation = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64))
    expected = torch.tensor(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    torch.testing.assert_close(rotation[0], expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(
        axis_angle_to_matrix(torch.zeros(1, 3, dtype=torch.float64))[0],
        torch.eye(3, dtype=torch.float64),
    )


def test_pose_error_perturbs_cameras_by_the_realised_rigid_motion() -> None:
    capture = make_capture()
    images, alpha, original = capture.images.clone(), capture.alpha.clone(), capture.cameras
    effect = PoseError({"rotation_deg": 2.0, "translation": 0.01})
    applied = effect.apply(capture, torch.Generator().manual_seed(9))
    assert torch.equal(capture.images, images) and torch.equal(capture.alpha, alpha)
    assert torch.equal(capture.cameras.intrinsics, original.intrinsics)
    check_rigid(capture.cameras.world_to_cam, "perturbed world_to_cam")
    delta = capture.cameras.world_to_cam.double() @ rigid_inverse(original.world_to_cam.double())
    check_rigid(delta, "perturbation")
    rotation_trace = delta[:, :3, :3].diagonal(dim1=-2, dim2=-1).sum(-1)
    angles = torch.rad2deg(torch.acos(((rotation_trace - 1) / 2).clamp(-1, 1)))
    realised = torch.tensor(applied.parameters["rotation_deg"], dtype=torch.float64)
    torch.testing.assert_close(angles, realised, atol=2e-3, rtol=0)
    assert float(realised.max()) > 0.5  # 2 degrees std: visibly perturbed
    vectors = torch.deg2rad(
        torch.tensor(applied.parameters["rotation_vectors_deg"], dtype=torch.float64)
    )
    torch.testing.assert_close(delta[:, :3, :3], axis_angle_to_matrix(vectors), atol=1e-5, rtol=0)
    translations = torch.tensor(applied.parameters["translations"], dtype=torch.float64)
    torch.testing.assert_close(delta[:, :3, 3], translations, atol=1e-5, rtol=0)
    # The camera centre moves by as much as the camera-frame translation.
    shifts = torch.tensor(applied.parameters["centre_shifts"], dtype=torch.float64)
    torch.testing.assert_close(shifts.norm(dim=-1), translations.norm(dim=-1), atol=1e-5, rtol=0)
    # Translations scale with the camera distance (4): 1 % std per component.
    assert 0.005 < float(translations.abs().mean()) < 0.08


def test_pose_error_can_pin_the_first_view() -> None:
    capture = make_capture()
    original = capture.cameras.world_to_cam.clone()
    applied = PoseError({"rotation_deg": 1.0, "pin_first_view": 1.0}).apply(
        capture, torch.Generator().manual_seed(2)
    )
    assert torch.equal(capture.cameras.world_to_cam[0], original[0])
    assert not torch.allclose(capture.cameras.world_to_cam[1:], original[1:])
    assert applied.parameters["rotation_deg"][0] == 0.0


def test_pose_error_zero_strength_is_the_identity() -> None:
    capture = make_capture()
    original = capture.cameras.world_to_cam.clone()
    PoseError({"rotation_deg": 0.0, "translation": 0.0}).apply(capture, torch.Generator())
    torch.testing.assert_close(capture.cameras.world_to_cam, original, atol=1e-7, rtol=0)


# ---------------------------------------------------------------------------- response curve


def test_response_curve_is_monotone_from_zero_to_one() -> None:
    for parameters in (
        {},
        {"toe": 0.3, "shoulder": 5.0, "gamma": 1.0},
        {"toe": 0.0, "shoulder": 0.0},
    ):
        effect = ResponseCurve(parameters)
        exposure = torch.linspace(0.0, 2.0, 2001, dtype=torch.float64)
        observed = effect.observed_linear(exposure)
        assert float(observed[0]) == 0.0
        assert (
            abs(float(effect.observed_linear(torch.tensor(1.0, dtype=torch.float64))) - 1) < 1e-12
        )
        assert bool((observed.diff() >= 0).all())
        assert bool((observed[exposure <= 1].diff() > 0).all())  # strictly, below saturation


def test_response_curve_stores_what_an_srgb_reader_must_see() -> None:
    effect = ResponseCurve({"toe": 0.05, "shoulder": 0.8, "gamma": 2.4})
    grey = torch.full((1, 4, 4, 3), 0.18)
    capture = Capture(grey.clone(), torch.ones(1, 4, 4, 1), orbit_cameras(1, (4, 4)))
    applied = effect.apply(capture, torch.Generator())
    # The writer encodes with sRGB: the stored code value is the camera's curve, not sRGB(E).
    code = float(linear_to_srgb(capture.images[0, 0, 0, 0].double()))
    toed = 0.18 * 1.05 * 0.18 / (0.18 + 0.05)
    expected_code = (1.8 * toed / (1 + 0.8 * toed)) ** (1 / 2.4)
    assert abs(code - expected_code) < 1e-5
    mid_grey = applied.parameters["mid_grey"]
    assert abs(mid_grey["code_value"] - expected_code) < 1e-5
    assert (
        abs(mid_grey["observed_linear"] - float(srgb_to_linear(torch.tensor(expected_code)))) < 1e-5
    )
    assert abs(mid_grey["observed_linear"] - 0.18) > 0.01  # mid-grey moved
    torch.testing.assert_close(capture.alpha, torch.ones(1, 4, 4, 1))
    table = applied.parameters["table"]
    assert len(table["true_linear"]) == len(table["observed_linear"]) == TABLE_SAMPLES
    interpolated = torch.tensor(table["observed_linear"])[46]  # true 46/255 ~ 0.1804
    assert abs(float(interpolated) - mid_grey["observed_linear"]) < 2e-3
    assert 0.5 < applied.parameters["effective_exponent"] < 2.0


def test_response_curve_sampled_strengths_distort_but_keep_mid_grey_plausible() -> None:
    for seed in range(6):
        parameters = ResponseCurve.sample_strength(torch.Generator().manual_seed(seed))
        effect = ResponseCurve(parameters)
        code = float(effect.code_value(torch.tensor(0.18, dtype=torch.float64)))
        assert 0.35 < code < 0.62, (parameters, code)
        exposure = torch.linspace(0.02, 1.0, 50, dtype=torch.float64)
        distortion = (effect.observed_linear(exposure) - exposure).abs().max()
        assert float(distortion) > 0.02  # detectable against the sRGB identity
