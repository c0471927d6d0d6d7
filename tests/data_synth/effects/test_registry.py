"""World effect registry: construction and parameter validation, sampled strengths, ordering,
light-transport skipping, determinism, and device independence."""

from __future__ import annotations

import copy

import pytest
import torch

from data_synth.effects.base import CATALOGUE, LIGHT_TRANSPORT, STAGE_ORDER, AppliedEffect, Capture
from data_synth.effects.registry import (
    APPLICATION_ORDER,
    WORLD_EFFECTS,
    apply_effects,
    make_world_effect,
)
from recon.camera.cameras import orbit_cameras
from recon.errors import ReconError

IMAGE_EFFECTS = sorted(WORLD_EFFECTS)


def make_capture(count: int = 3, size: int = 24, device: str | torch.device = "cpu") -> Capture:
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(count, size, size, 3, generator=generator) * 0.8
    alpha = (torch.rand(count, size, size, 1, generator=generator) > 0.2).float()
    cameras = orbit_cameras(count, (size, size)).to(device)
    return Capture((images * alpha).to(device), alpha.to(device), cameras)


def test_registry_covers_every_image_effect_of_the_catalogue() -> None:
    assert set(WORLD_EFFECTS) == set(CATALOGUE) - set(LIGHT_TRANSPORT)
    assert set(APPLICATION_ORDER) == set(WORLD_EFFECTS)
    for name, effect_type in WORLD_EFFECTS.items():
        assert effect_type.name == name and effect_type.stage in STAGE_ORDER
        effect = make_world_effect(name, {})
        assert effect.parameters == effect_type.default_parameters()
    # APPLICATION_ORDER respects the stage order.
    stages = [STAGE_ORDER.index(WORLD_EFFECTS[name].stage) for name in APPLICATION_ORDER]
    assert stages == sorted(stages)


def test_unknown_parameter_names_the_effect_and_suggests_the_closest() -> None:
    with pytest.raises(ReconError, match=r"exposure.*'spread_stop'.*did you mean 'spread_stops'"):
        make_world_effect("exposure", {"spread_stop": 0.5})


@pytest.mark.parametrize(
    ("name", "parameters", "pattern"),
    [
        ("exposure", {"spread_stops": -0.1}, r"exposure.*spread_stops.*\[0, 3\]"),
        ("noise", {"read_noise": float("nan")}, r"noise.*read_noise.*finite"),
        ("vignetting", {"strength": "strong"}, r"vignetting.*strength.*number"),
        ("pose_error", {"pin_first_view": 2}, r"pose_error.*pin_first_view.*true/false"),
        ("lens_distortion", {"p1": 0.5}, r"lens_distortion.*p1"),
        ("defocus_blur", {"radius_px": True}, r"defocus_blur.*radius_px.*number"),
    ],
)
def test_bad_parameter_values_are_rejected(name: str, parameters: dict, pattern: str) -> None:
    with pytest.raises(ReconError, match=pattern):
        make_world_effect(name, parameters)


def test_unknown_and_light_transport_effect_names() -> None:
    with pytest.raises(ReconError, match="did you mean 'vignetting'"):
        make_world_effect("vignette", {})
    with pytest.raises(ReconError, match="light-transport"):
        make_world_effect("shadows", {})


@pytest.mark.parametrize("name", IMAGE_EFFECTS)
def test_sampled_strengths_are_valid_and_seeded(name: str) -> None:
    effect_type = WORLD_EFFECTS[name]
    cameras = orbit_cameras(2, (128, 128))
    for seed in range(4):
        first = effect_type.sample_strength(torch.Generator().manual_seed(seed), cameras)
        again = effect_type.sample_strength(torch.Generator().manual_seed(seed), cameras)
        assert first == again
        assert effect_type(first).parameters == {**effect_type.default_parameters(), **first}
    assert first != effect_type.sample_strength(torch.Generator().manual_seed(99), cameras)


def test_sampled_ranges_match_the_blind_benchmark_brief() -> None:
    generator = torch.Generator().manual_seed(3)
    corner = 2**0.5 * 0.36397  # tan(20 deg) * sqrt(2): the nominal 40 degree image's corner
    for _ in range(8):
        assert 0.3 <= WORLD_EFFECTS["exposure"].sample_strength(generator)["spread_stops"] <= 0.8
        radius = WORLD_EFFECTS["defocus_blur"].sample_strength(generator)["radius_px"]
        assert 1.0 <= radius <= 2.5
        k1 = WORLD_EFFECTS["lens_distortion"].sample_strength(generator)["k1"]
        assert 0.05 - 1e-3 <= abs(k1) * corner**2 <= 0.2 + 1e-3


@pytest.mark.parametrize("size", [32, 48, 64])
def test_a_sampled_defocus_on_a_small_image_is_not_the_identity(size: int) -> None:
    # Scaled with the image, the 128 px range fell inside the centre pixel below about 64 px.
    from data_synth.effects.optics import disk_kernel

    cameras = orbit_cameras(2, (size, size))
    for seed in range(6):
        generator = torch.Generator().manual_seed(seed)
        radius = WORLD_EFFECTS["defocus_blur"].sample_strength(generator, cameras)["radius_px"]
        assert radius >= 1.0
        assert float(disk_kernel(radius).max()) < 0.5


@pytest.mark.parametrize(
    ("name", "parameters"),
    [
        ("exposure", {"spread_stops": 0.0}),
        ("white_balance", {"spread_kelvin": 0.0}),
        ("vignetting", {"cos_power": 0.0, "strength": 0.0}),
        ("lens_distortion", {}),
        ("defocus_blur", {"radius_px": 0.0}),
        ("motion_blur", {"length_px": 0.0}),
        ("pose_error", {"rotation_deg": 0.0, "translation": 0.0}),
    ],
)
def test_zero_strength_is_the_identity(name: str, parameters: dict) -> None:
    capture = make_capture()
    before = copy.deepcopy(capture)
    apply_effects(capture, [make_world_effect(name, parameters)], torch.Generator().manual_seed(1))
    torch.testing.assert_close(capture.images, before.images, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(capture.alpha, before.alpha)
    torch.testing.assert_close(
        capture.cameras.world_to_cam, before.cameras.world_to_cam, rtol=0, atol=1e-7
    )


class RecordingEffect:
    """A stand-in effect that records when it ran."""

    def __init__(self, name: str, stage: str, log: list[str]) -> None:
        self.name, self.stage, self.log = name, stage, log

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        self.log.append(self.name)
        return AppliedEffect(self.name, {})


def test_apply_effects_runs_in_physical_order_and_skips_light_transport() -> None:
    log: list[str] = []
    shuffled = ["response_curve", "noise", "exposure", "vignetting", "pose_error", "white_balance",
                "lens_distortion", "motion_blur", "defocus_blur"]  # fmt: skip
    effects = [RecordingEffect(name, WORLD_EFFECTS[name].stage, log) for name in shuffled]
    effects.insert(2, RecordingEffect("shadows", "light_transport", log))
    effects.append(("specular", {"anything": 1.0}))  # never built: the caller renders it
    applied = apply_effects(make_capture(), effects, torch.Generator().manual_seed(0))
    assert log == list(APPLICATION_ORDER)
    assert [item.name for item in applied] == list(APPLICATION_ORDER)


def test_apply_effects_rejects_repeated_effects() -> None:
    effects = [("exposure", {}), make_world_effect("exposure", {"spread_stops": 1.0})]
    with pytest.raises(ReconError, match="repeated.*exposure"):
        apply_effects(make_capture(), effects, torch.Generator())


def all_effects() -> list:
    generator = torch.Generator().manual_seed(5)
    cameras = orbit_cameras(3, (24, 24))
    return [
        make_world_effect(name, WORLD_EFFECTS[name].sample_strength(generator, cameras))
        for name in IMAGE_EFFECTS
    ]


def test_apply_effects_is_deterministic_and_effects_draw_independently() -> None:
    results = []
    for _ in range(2):
        capture = make_capture()
        applied = apply_effects(capture, all_effects(), torch.Generator().manual_seed(42))
        results.append((capture, applied))
    (first, first_applied), (second, second_applied) = results
    assert torch.equal(first.images, second.images) and torch.equal(first.alpha, second.alpha)
    assert torch.equal(first.cameras.world_to_cam, second.cameras.world_to_cam)
    assert [item.parameters for item in first_applied] == [
        item.parameters for item in second_applied
    ]
    assert float(first.images.min()) >= 0.0
    # Exposure's draws do not depend on which other effects are on.
    exposure = next(effect for effect in all_effects() if effect.name == "exposure")
    alone = apply_effects(make_capture(), [exposure], torch.Generator().manual_seed(42))
    with_others = next(item for item in first_applied if item.name == "exposure")
    assert alone[0].parameters["ratios"] == with_others.parameters["ratios"]
    # Another seed draws other values.
    other = apply_effects(make_capture(), [exposure], torch.Generator().manual_seed(43))
    assert other[0].parameters["ratios"] != alone[0].parameters["ratios"]


def test_effects_give_the_same_result_on_every_device(device: torch.device) -> None:
    reference = make_capture()
    apply_effects(reference, all_effects(), torch.Generator().manual_seed(8))
    capture = make_capture(device=device)
    apply_effects(capture, all_effects(), torch.Generator().manual_seed(8))
    torch.testing.assert_close(capture.images.cpu(), reference.images, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(capture.alpha.cpu(), reference.alpha, rtol=1e-4, atol=1e-4)
