"""The model-effect interface: the registry, the common attributes, and the forward-model
functions (stage selection, physical order, identity of the whole chain at zero)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from recon.config.run_config import EFFECT_NAMES
from recon.effects import (
    MODEL_EFFECTS,
    EffectContext,
    ModelEffect,
    apply_camera_effects,
    apply_image_effects,
    apply_shading_effects,
    make_effect,
    render_with_effects,
)
from recon.effects.forward import IMAGE_ORDER, SHADING_ORDER
from recon.errors import ReconError
from recon.render.renderer import Renderer

PER_VIEW = {"exposure", "white_balance", "motion_blur", "pose_error"}
PINNED = {"exposure", "white_balance", "pose_error"}


def test_registry_holds_every_addable_catalogue_effect():
    assert set(MODEL_EFFECTS) == set(EFFECT_NAMES) - {"noise"} and len(MODEL_EFFECTS) == 11
    stages = {name: effect.stage for name, effect in MODEL_EFFECTS.items()}
    assert {name for name, stage in stages.items() if stage == "camera"} == {"pose_error"}
    assert {name for name, stage in stages.items() if stage == "shading"} == set(SHADING_ORDER)
    assert {name for name, stage in stages.items() if stage == "image"} == set(IMAGE_ORDER)
    assert {name for name, effect in MODEL_EFFECTS.items() if effect.per_view} == PER_VIEW


@pytest.mark.parametrize("name", sorted(MODEL_EFFECTS))
def test_every_effect_starts_at_the_identity_with_its_own_settings(name):
    effect = make_effect(name, 4)
    assert isinstance(effect, ModelEffect) and effect.name == name
    assert effect.is_identity() and effect.learning_rate == type(effect).default_learning_rate
    assert 0.0 <= effect.lock_fraction <= 1.0
    assert effect.pinned_view == (0 if name in PINNED else None)
    assert effect.is_locked(0.0) == (effect.lock_fraction > 0) and not effect.is_locked(1.0)
    groups = effect.parameter_groups()
    assert sum(len(group["params"]) for group in groups) == len(list(effect.parameters()))
    assert all(group["lr"] > 0 for group in groups)
    json.dumps(effect.parameters_summary())  # JSON-ready
    tuned = make_effect(name, 4, learning_rate=0.123, lock_fraction=0.0)
    assert tuned.learning_rate == 0.123 and not tuned.is_locked(0.0)


def test_camera_effects_default_to_a_longer_lock():
    assert make_effect("pose_error", 2).lock_fraction == 0.3


def test_registry_errors_name_the_problem():
    with pytest.raises(ReconError, match="did you mean 'exposure'"):
        make_effect("exposur", 3)
    with pytest.raises(ReconError, match="did you mean 'white_balance'"):
        make_effect("white_balanse", 3)
    with pytest.raises(ReconError, match="floor"):
        make_effect("noise", 3)
    with pytest.raises(ReconError, match="view_count"):
        make_effect("exposure")
    with pytest.raises(ReconError, match="bad options"):
        make_effect("vignetting", 3, colour="red")
    with pytest.raises(ReconError, match="lock_fraction"):
        make_effect("vignetting", lock_fraction=1.5)
    with pytest.raises(ReconError, match="pinned_view"):
        make_effect("exposure", 3, pinned_view=3)
    with pytest.raises(ReconError, match="pinned_view"):
        make_effect("vignetting", 3, pinned_view=0)


def test_view_indices_are_checked(sphere_scene):
    color, alpha = sphere_scene.output.color, sphere_scene.output.alpha
    exposure = make_effect("exposure", 3)
    with pytest.raises(ReconError, match=r"must lie in \[0, 2\]"):
        exposure(color, alpha, sphere_scene.cameras, torch.tensor([0, 1, 3]))
    with pytest.raises(ReconError, match=r"shape \[3\]"):
        exposure(color, alpha, sphere_scene.cameras, torch.tensor([0, 1]))
    with pytest.raises(ReconError, match="integers"):
        exposure(color, alpha, sphere_scene.cameras, torch.tensor([0.0, 1.0, 2.0]))


def test_stage_functions_pick_their_stage_and_keep_the_identity(shadow_scene):
    effects = [make_effect(name, 3) for name in MODEL_EFFECTS]
    views = shadow_scene.views
    cameras = apply_camera_effects(effects, shadow_scene.cameras, views)
    assert torch.equal(cameras.world_to_cam, shadow_scene.cameras.world_to_cam)
    context = EffectContext(shadow_scene.mesh, shadow_scene.lighting, cameras, views, Renderer())
    output = apply_shading_effects(effects, shadow_scene.output, context)
    assert torch.equal(output.color, shadow_scene.output.color)
    color, alpha = apply_image_effects(effects, output.color, output.alpha, cameras, views)
    assert torch.equal(color, shadow_scene.output.color)
    assert torch.equal(alpha, shadow_scene.output.alpha)
    # Nothing to apply: the inputs come back.
    assert apply_camera_effects(None, cameras, views) is cameras
    assert apply_image_effects([], color, alpha, cameras, views) == (color, alpha)


def test_render_with_effects_at_zero_equals_the_plain_render(shadow_scene):
    effects = [make_effect(name, 3) for name in MODEL_EFFECTS]
    renderer = Renderer()
    plain = renderer.render(shadow_scene.mesh, shadow_scene.cameras, shadow_scene.lighting)
    with_effects = render_with_effects(
        renderer,
        shadow_scene.mesh,
        shadow_scene.cameras,
        shadow_scene.lighting,
        effects,
        shadow_scene.views,
    )
    assert torch.equal(with_effects.color, plain.color)
    assert torch.equal(with_effects.alpha, plain.alpha)


def test_image_effects_run_in_physical_order_whatever_the_list_order(sphere_scene):
    color, alpha = sphere_scene.output.color.detach(), sphere_scene.output.alpha.detach()
    cameras, views = sphere_scene.cameras, sphere_scene.views
    exposure = make_effect("exposure", 3, pinned_view=None)
    response = make_effect("response_curve")
    with torch.no_grad():
        exposure.log_gain.fill_(math.log(2.0))
        response.log_gamma.fill_(math.log(2.0))
    # The gain is applied before the curve: (2 x)^2, not 2 x^2.
    for effects in ([exposure, response], [response, exposure]):
        result, _ = apply_image_effects(effects, color, alpha, cameras, views)
        torch.testing.assert_close(result, response.curve(2.0 * color).detach())


def test_each_effect_may_be_used_once(sphere_scene):
    effects = [make_effect("exposure", 3), make_effect("exposure", 3)]
    with pytest.raises(ReconError, match="repeated"):
        apply_image_effects(
            effects, sphere_scene.output.color, sphere_scene.output.alpha, None, None
        )
    with pytest.raises(ReconError, match="ModelEffect"):
        apply_camera_effects(["pose_error"], sphere_scene.cameras, None)


def test_gradients_reach_every_effect_through_the_forward_model(shadow_scene):
    # With each effect a little off zero, one backward pass reaches all of them.
    effects = [make_effect(name, 3) for name in MODEL_EFFECTS]
    with torch.no_grad():
        for effect in effects:
            for parameter in effect.parameters():
                parameter.fill_(0.01)
    output = render_with_effects(
        Renderer(),
        shadow_scene.mesh,
        shadow_scene.cameras,
        shadow_scene.lighting,
        effects,
        shadow_scene.views,
    )
    weights = torch.rand(output.color.shape, generator=torch.Generator().manual_seed(0))
    (output.color * weights).sum().backward()
    for effect in effects:
        gradients = [parameter.grad for parameter in effect.parameters()]
        assert all(
            gradient is not None and torch.isfinite(gradient).all() for gradient in gradients
        )
        assert any(bool((gradient != 0).any()) for gradient in gradients), effect.name
