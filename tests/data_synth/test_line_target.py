"""Line-target frames: a striped card through the capture's camera chain (data_synth)."""

from __future__ import annotations

import pytest
import torch

from data_synth.line_target import line_target_capture
from recon.config.run_config import CameraRigConfig, CaptureConfig, EffectConfig, LineTargetConfig
from tests.data_synth.test_stage import effects_record, read_split, synth

SIZE = 48
CAPTURE = CaptureConfig(
    cameras=CameraRigConfig(rig="fibonacci", distance=3.0, fov_deg=40.0, resolution=[SIZE, SIZE]),
    line_target=LineTargetConfig(views=4, radiance=0.5),
)


def test_the_card_shows_two_levels_in_stripes_that_alternate_direction():
    capture, realised, cards = line_target_capture(CAPTURE, [], seed=1)
    assert capture.images.shape == (4, SIZE, SIZE, 3) and realised == []
    assert torch.equal(capture.alpha, torch.ones(4, SIZE, SIZE, 1))
    images = capture.images[..., 0]
    # Box-filtered stripes: every value between the black (a tenth) and the white level.
    assert float(images.min()) >= 0.05 - 1e-6 and float(images.max()) <= 0.5 + 1e-6
    assert float((images > 0.45).float().mean()) > 0.25
    assert float((images < 0.1).float().mean()) > 0.25
    for index, card in enumerate(cards):
        along_rows = float(images[index].diff(dim=0).abs().mean())
        along_columns = float(images[index].diff(dim=1).abs().mean())
        # Even frames: horizontal stripes change down the columns.
        assert (along_rows > along_columns) == (index % 2 == 0), card


def test_the_geometric_effects_bend_or_move_the_stripes_but_a_pose_error_is_left_out():
    plain, _, _ = line_target_capture(CAPTURE, [], seed=2)
    effects = [
        EffectConfig("lens_distortion", {"k1": 0.5}),
        EffectConfig("pose_error", {"rotation_deg": 2.0}),
        EffectConfig("shadows", {}),
    ]
    bent, realised, _ = line_target_capture(CAPTURE, effects, seed=2)
    assert [item["name"] for item in realised] == ["lens_distortion"]
    # The centre barely moves, the corners do (a radial distortion).
    centre = (bent.images - plain.images)[:, 20:28, 20:28].abs().mean()
    corners = (bent.images - plain.images)[:, :6, :6].abs().mean()
    assert float(corners) > 3 * float(centre)
    # The margin: a pincushion lens pulls card, not black, into the corners.
    assert float(bent.images[:, :2, :2].amin()) >= 0.05 * 0.99


def test_synth_writes_the_split_without_moving_the_views(tmp_path):
    capture = {
        "train_views": 2,
        "effects": [{"name": "lens_distortion", "parameters": {"k1": 0.3}}],
    }
    without = synth(tmp_path, "without", {"capture": capture})
    with_frames = synth(tmp_path, "with", {"capture": {**capture, "line_target": {"views": 2}}})
    assert not (without / "dataset" / "transforms_line_target.json").exists()
    assert torch.equal(read_split(without).images, read_split(with_frames).images)
    frames = read_split(with_frames, "line_target")
    assert frames.images.shape == (2, 32, 32, 3) and torch.all(frames.masks == 1)
    realised = effects_record(with_frames)["realised"]["line_target"]
    assert [item["name"] for item in realised] == ["lens_distortion"]


def test_line_target_config_is_checked():
    from recon.config.checks import ConfigFieldError

    with pytest.raises(ConfigFieldError, match="views"):
        LineTargetConfig(views=-1)
    with pytest.raises(ConfigFieldError, match="period_pixels"):
        LineTargetConfig(period_pixels=2.0)
    with pytest.raises(ConfigFieldError, match="supersampling"):
        LineTargetConfig(supersampling=0)
