"""Flat-field frames: a uniformly lit card through the capture's camera chain (data_synth).
scripts/add_flat_field.py, which completes older runs with them: tests/scripts/."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from data_synth.effects.registry import make_world_effect
from data_synth.effects.world_effect import pixel_grid
from data_synth.flat_field import flat_field_capture
from recon.config.run_config import CameraRigConfig, CaptureConfig, EffectConfig, FlatFieldConfig
from recon.diagnose.flat_field import measure_flat_field
from tests.data_synth.test_stage import effects_record, read_split, synth

SIZE = 48
CAPTURE = CaptureConfig(
    cameras=CameraRigConfig(rig="fibonacci", distance=3.0, fov_deg=40.0, resolution=[SIZE, SIZE]),
    flat_field=FlatFieldConfig(views=2, radiance=0.4),
)
VIGNETTING = EffectConfig(
    "vignetting",
    {
        "cos_power": 3.0,
        "strength": 0.3,
        "barrel_radius": 1.6,
        "offset_x_px": 1.5,
        "offset_y_px": -1.0,
    },
)


def test_without_effects_the_card_is_uniform_and_the_geometric_effects_leave_it_so():
    geometric = [
        EffectConfig("lens_distortion", {"k1": -0.2}),
        EffectConfig("defocus_blur", {"radius_px": 2.0}),
        EffectConfig("pose_error", {"rotation_deg": 2.0}),
        EffectConfig("shadows", {}),
    ]
    capture, realised = flat_field_capture(CAPTURE, geometric, seed=3)
    assert capture.images.shape == (2, SIZE, SIZE, 3)
    assert torch.equal(capture.images, torch.full_like(capture.images, 0.4))
    assert torch.equal(capture.alpha, torch.ones(2, SIZE, SIZE, 1))
    assert realised == []


def test_vignetting_darkens_the_card_by_its_own_falloff_and_exposure_scales_each_frame():
    effects = [VIGNETTING, EffectConfig("exposure", {"spread_stops": 0.5})]
    capture, realised = flat_field_capture(CAPTURE, effects, seed=5)
    names = [item["name"] for item in realised]
    assert names == ["vignetting", "exposure"]
    ratios = torch.tensor(realised[1]["parameters"]["ratios"], dtype=torch.float64)
    world = make_world_effect("vignetting", VIGNETTING.parameters)
    u, v = pixel_grid(SIZE, SIZE, torch.empty(0, dtype=torch.float64))
    natural, mechanical = world.falloff(capture.cameras, u, v)
    expected = 0.4 * ratios[:, None, None] * natural * mechanical
    assert torch.allclose(capture.images[..., 0].double(), expected, rtol=1e-5)
    # The diagnosis' measurement reads the realised corner falloff back off the frames.
    measured = measure_flat_field(capture.images)
    true_corner = sum(realised[0]["parameters"]["corner_falloff"]) / 2
    true_half = sum(realised[0]["parameters"]["half_radius_falloff"]) / 2
    assert true_corner < 0.85
    assert measured["corner_falloff"] == pytest.approx(true_corner, rel=0.01)
    assert measured["half_radius_falloff"] == pytest.approx(true_half, rel=0.005)


def test_synth_writes_the_split_without_moving_the_views(tmp_path):
    capture = {
        "train_views": 2,
        "effects": [{"name": "vignetting", "parameters": {"strength": 0.3}}],
    }
    without = synth(tmp_path, "without", {"capture": capture})
    with_frames = synth(
        tmp_path, "with", {"capture": {**capture, "flat_field": {"views": 3, "radiance": 0.5}}}
    )
    assert not (without / "dataset" / "transforms_flat_field.json").exists()
    assert torch.equal(read_split(without).images, read_split(with_frames).images)
    frames = read_split(with_frames, "flat_field")
    assert frames.images.shape == (3, 32, 32, 3) and torch.all(frames.masks == 1)
    centre = frames.images[:, 14:18, 14:18].mean()
    assert float(centre) == pytest.approx(0.5, rel=0.02)
    assert float(frames.images[:, 0, 0].mean()) < 0.95 * float(centre)
    realised = effects_record(with_frames)["realised"]["flat_field"]
    assert [item["name"] for item in realised] == ["vignetting"]


def test_flat_field_config_is_checked():
    from recon.config.checks import ConfigFieldError

    with pytest.raises(ConfigFieldError, match="views"):
        FlatFieldConfig(views=-1)
    with pytest.raises(ConfigFieldError, match="radiance"):
        replace(CAPTURE.flat_field, radiance=0.0)
