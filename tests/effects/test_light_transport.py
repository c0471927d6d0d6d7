"""Model effects specular, shadows, interreflection: the dominant light, shadow-map visibility,
mesh occlusion, identity at zero, gradients against central differences (float64) and
recovery of their own parameters from a render they changed.
Under a light fixed to the camera (frame 'camera'), an object and its camera turned together
keep the same highlight and shadow; two views of one batch get their own light direction."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import trimesh

from recon.camera import Cameras, look_at
from recon.effects import EffectContext, Interreflection, Shadows, Specular, dominant_light
from recon.effects.forward import render_with_effects
from recon.effects.light_transport import (
    OCCLUSION_TOLERANCE,
    mean_irradiance,
    vertex_occlusion,
    view_directions,
    view_light_directions,
)
from recon.effects.registry import make_effect
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting, sh_basis


def _context(scene) -> EffectContext:
    return EffectContext(scene.mesh, scene.lighting, scene.cameras, scene.views)


def _double(output):
    return replace(
        output,
        color=output.color.double(),
        alpha=output.alpha.double(),
        normals=output.normals.double(),
        albedo=output.albedo.double(),
    )


def test_dominant_light_prefers_the_brightest_sun_then_the_sh_linear_band():
    lighting = Lighting.constant(0.5)
    weak = DirectionalLight(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.5, 0.5, 0.5]))
    strong = DirectionalLight(torch.tensor([0.0, 2.0, 0.0]), torch.tensor([2.0, 1.0, 1.0]))
    lighting.directional = [weak, strong]
    direction, irradiance = dominant_light(lighting)
    torch.testing.assert_close(direction, torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(irradiance, torch.tensor([2.0, 1.0, 1.0]))
    # A delta light of irradiance E along d projected into SH has band one E Y_1m(d): the
    # linear band gives back d and E.
    toward = torch.nn.functional.normalize(torch.tensor([0.3, 0.8, -0.5]), dim=0)
    sh = Lighting.constant(0.2).sh_coefficients.clone()
    sh[1:4] += sh_basis(toward)[1:4, None] * torch.tensor([[1.5, 1.2, 0.9]])
    direction, irradiance = dominant_light(Lighting(sh_coefficients=sh))
    torch.testing.assert_close(direction, toward)
    torch.testing.assert_close(irradiance, torch.tensor([1.5, 1.2, 0.9]))
    # A uniform environment has no dominant direction.
    assert torch.equal(dominant_light(Lighting.constant(1.0))[1], torch.zeros(3))
    # Mean irradiance: pi x the uniform radiance, plus a quarter of each sun.
    torch.testing.assert_close(
        mean_irradiance(lighting), math.pi * 0.5 + torch.tensor([0.625, 0.375, 0.375])
    )


def test_view_directions_point_back_to_the_camera(sphere_scene):
    cameras = sphere_scene.cameras
    directions = view_directions(cameras, 40, 40, torch.zeros(()))
    # The pixels around the principal point (20, 20) look along the optical axis.
    centre = directions[:, 19:21, 19:21].mean(dim=(1, 2))
    toward_camera = torch.nn.functional.normalize(cameras.centers(), dim=-1)  # looks at 0
    torch.testing.assert_close(
        torch.nn.functional.normalize(centre, dim=-1), toward_camera, atol=2e-3, rtol=0
    )


@pytest.mark.parametrize("effect_class", [Specular, Shadows, Interreflection])
def test_identity_at_zero_is_exact(effect_class, shadow_scene):
    effect = effect_class()
    output = effect(shadow_scene.output, _context(shadow_scene))
    assert torch.equal(output.color, shadow_scene.output.color)
    assert (
        output.alpha is shadow_scene.output.alpha and output.normals is shadow_scene.output.normals
    )


def test_shading_effects_need_a_context(sphere_scene):
    with pytest.raises(ReconError, match="EffectContext"):
        Specular()(sphere_scene.output, None)
    context = replace(_context(sphere_scene), cameras=sphere_scene.cameras[0])
    with pytest.raises(ReconError, match="cameras"):
        Shadows()(sphere_scene.output, context)


def test_shadow_map_darkens_the_cast_shadow_only(shadow_scene, sphere_scene):
    direction = dominant_light(shadow_scene.lighting)[0]
    effect = Shadows(map_resolution=128)
    visibility = effect.visibility(shadow_scene.output, shadow_scene.mesh, direction).detach()
    normals = shadow_scene.output.normals
    facing = (normals * direction).sum(-1) > 0.3
    lit_share = float((visibility[..., 0][facing] > 0.95).double().mean())
    shadowed_share = float((visibility[..., 0][facing] < 0.05).double().mean())
    # Most light-facing surface is lit (no acne); the sphere's shadow on the ground is dark.
    assert lit_share > 0.85 and shadowed_share > 0.03
    assert float(visibility[shadow_scene.output.mask == 0].min()) == 1.0
    # A convex sphere casts nothing onto itself where it faces the light.
    direction = dominant_light(sphere_scene.lighting)[0]
    alone = Shadows(map_resolution=128).visibility(
        sphere_scene.output, sphere_scene.mesh, direction
    )
    facing = (sphere_scene.output.normals * direction).sum(-1) > 0.2
    assert float(alone.detach()[..., 0][facing].min()) > 0.95


def test_shadow_map_is_cached_for_an_unchanged_mesh(shadow_scene):
    effect = Shadows(map_resolution=64)
    direction = dominant_light(shadow_scene.lighting)[0]
    first = effect.shadow_map(shadow_scene.mesh, direction)[1]
    assert effect.shadow_map(shadow_scene.mesh, direction)[1] is first
    moved = replace(shadow_scene.mesh, verts=shadow_scene.mesh.verts + 0.01)
    assert effect.shadow_map(moved, direction)[1] is not first


def test_receivers_are_kept_without_grad_and_give_the_same_visibility(shadow_scene):
    """A probe renders one frozen scene many times: without gradients the depth-test inputs
    are kept for the same fragments and maps (one map or one per view), and a softness change
    gives exactly what a fresh module computes; with gradients nothing is kept."""
    output, mesh = shadow_scene.output, shadow_scene.mesh
    direction = dominant_light(shadow_scene.lighting)[0]
    turned = torch.nn.functional.normalize(direction + torch.tensor([0.0, 0.0, 0.3]), dim=-1)
    per_view = torch.stack([direction, turned, direction])  # a camera-frame light's [B, 3]
    for directions in (direction, per_view):
        effect = Shadows(map_resolution=64)
        with torch.no_grad():
            first = effect.receivers(output, mesh, directions)[1]
            assert effect.receivers(output, mesh, directions)[1] is first
            effect.log_softness.fill_(0.7)
            kept = effect.visibility(output, mesh, directions)
            fresh = Shadows(map_resolution=64)
            fresh.log_softness.fill_(0.7)
            assert torch.equal(kept, fresh.visibility(output, mesh, directions))
            other = replace(output, fragments=replace(output.fragments))
            assert effect.receivers(other, mesh, directions)[1] is not first
    effect = Shadows(map_resolution=64)
    first = effect.receivers(output, mesh, direction)[1]
    assert effect.receivers(output, mesh, direction)[1] is not first


def test_visibility_is_kept_for_the_same_softness_without_grad(shadow_scene):
    """A probe's Jacobian column that moves the strength leaves the visibility as it was:
    kept for the same receivers and softness, recomputed (as a fresh module's) for another."""
    output, mesh = shadow_scene.output, shadow_scene.mesh
    direction = dominant_light(shadow_scene.lighting)[0]
    effect = Shadows(map_resolution=64)
    with torch.no_grad():
        first = effect.visibility(output, mesh, direction)
        effect.strength.fill_(0.5)
        assert effect.visibility(output, mesh, direction) is first
        effect.log_softness.fill_(0.4)
        softer = effect.visibility(output, mesh, direction)
        fresh = Shadows(map_resolution=64)
        fresh.log_softness.fill_(0.4)
        assert softer is not first and torch.equal(
            softer, fresh.visibility(output, mesh, direction)
        )
        assert not torch.equal(softer, first)
    assert effect.visibility(output, mesh, direction) is not softer  # gradients: computed
    # The whole effect with its kept visibility and direct light: a fresh module's image.
    context = _context(shadow_scene)
    with torch.no_grad():
        for strength, softness in ((0.3, 0.0), (0.6, 0.0), (0.6, 0.5)):
            effect.strength.fill_(strength)
            effect.log_softness.fill_(softness)
            fresh = Shadows(map_resolution=64)
            fresh.strength.fill_(strength)
            fresh.log_softness.fill_(softness)
            assert torch.equal(effect(output, context).color, fresh(output, context).color)


def test_occlusion_is_kept_for_a_nudge_and_redrawn_for_a_move(shadow_scene):
    effect = Interreflection(directions=16, map_resolution=32)
    mesh = shadow_scene.mesh
    first = effect.occlusion(mesh)
    diagonal = float((mesh.verts.max(0).values - mesh.verts.min(0).values).norm())
    nudged = replace(mesh, verts=mesh.verts + 0.5 * OCCLUSION_TOLERANCE * diagonal)
    assert effect.occlusion(nudged) is first
    moved = replace(mesh, verts=mesh.verts * 1.05)
    assert effect.occlusion(moved) is not first


def test_vertex_occlusion_is_zero_on_a_convex_shape_and_high_under_an_overhang(
    sphere_scene, shadow_scene
):
    convex = vertex_occlusion(sphere_scene.mesh.verts, sphere_scene.mesh.faces, 32, 64)
    assert float(convex.max()) < 0.05
    verts = shadow_scene.mesh.verts
    occlusion = vertex_occlusion(verts, shadow_scene.mesh.faces, 32, 64)
    top = (verts[:, 1] > -0.26) & (verts[:, 1] < 0) & (verts[:, [0, 2]].abs().amax(-1) < 0.9)
    radius = verts[:, [0, 2]].norm(dim=-1)
    under, far = occlusion[top & (radius < 0.2)], occlusion[top & (radius > 0.7)]
    assert float(under.mean()) > 0.2 and float(far.mean()) < 0.12


def _set(effect, values: dict) -> None:
    with torch.no_grad():
        for name, value in values.items():
            getattr(effect, name).fill_(value)


@pytest.mark.parametrize(
    "effect_class, values, checked",
    [
        (Specular, {"strength": 0.3, "log_exponent": 0.4}, ["strength", "log_exponent"]),
        (Shadows, {"strength": 0.6, "log_softness": 0.5}, ["strength", "log_softness"]),
        (Interreflection, {"strength": 0.8}, ["strength"]),
    ],
)
def test_gradients_match_central_differences(
    effect_class, values, checked, shadow_scene, central_difference
):
    output = _double(shadow_scene.output)
    context = _context(shadow_scene)
    effect = effect_class().double()
    if effect_class is Shadows:
        effect = Shadows(map_resolution=96).double()
    _set(effect, values)
    weights = torch.rand(
        output.color.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64
    )

    def loss():
        return (effect(output, context).color * weights).sum()

    effect.zero_grad()
    loss().backward()
    for name in checked:
        parameter = getattr(effect, name)
        expected = central_difference(loss, parameter, ())
        assert expected != 0.0
        assert parameter.grad.item() == pytest.approx(expected, rel=1e-5, abs=1e-9)


def _recover(effect, scene, values, steps, adam_fit):
    context = _context(scene)
    _set(effect, values)
    with torch.no_grad():
        target = effect(scene.output, context).color
    truth = effect.parameters_summary()
    effect.reset_parameters()
    adam_fit(effect, lambda: effect(scene.output, context).color, target, steps)
    return truth, effect.parameters_summary()


def test_specular_recovers_strength_and_exponent(shadow_scene, adam_fit):
    truth, recovered = _recover(
        Specular(), shadow_scene, {"strength": 0.3, "log_exponent": 0.5}, 100, adam_fit
    )
    assert recovered["strength"] == pytest.approx(truth["strength"], rel=0.05)
    assert recovered["exponent"] == pytest.approx(truth["exponent"], rel=0.1)
    assert recovered["equivalent_roughness"] == pytest.approx(
        truth["equivalent_roughness"], rel=0.05
    )


def test_shadows_recover_strength(shadow_scene, adam_fit):
    truth, recovered = _recover(
        Shadows(map_resolution=128),
        shadow_scene,
        {"strength": 0.7, "log_softness": 0.5},
        100,
        adam_fit,
    )
    assert recovered["strength"] == pytest.approx(0.7, rel=0.05)
    assert recovered["softness_texels"] == pytest.approx(truth["softness_texels"], rel=0.3)


def test_interreflection_recovers_strength(shadow_scene, adam_fit):
    truth, recovered = _recover(Interreflection(), shadow_scene, {"strength": 0.8}, 100, adam_fit)
    assert recovered["strength"] == pytest.approx(0.8, rel=0.05)
    assert 0.0 < recovered["mean_vertex_occlusion"] < 0.5


def rotation_matrix(axis: list[float], angle: float) -> torch.Tensor:
    axis = torch.nn.functional.normalize(torch.tensor(axis), dim=0)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def scene() -> tuple[Mesh, Cameras]:
    """A lumpy sphere with a small sphere beside it (to cast a shadow), one 48 px camera."""
    big = trimesh.creation.icosphere(subdivisions=3)
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.35)
    # Between the big sphere and the light (toward (-0.2, 0.67, 0.71) in the world).
    small.apply_translation([-0.35, 1.15, 1.2])
    both = trimesh.util.concatenate([big, small])
    verts = torch.tensor(both.vertices, dtype=torch.float32) * torch.tensor([1.0, 0.8, 0.9])
    mesh = Mesh(verts, torch.tensor(both.faces), vertex_colors=torch.full_like(verts, 0.6))
    world_to_cam = look_at(torch.tensor([[0.5, 0.8, 3.5]]), torch.zeros(1, 3))
    intrinsics = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]])
    return mesh, Cameras(world_to_cam, intrinsics, (48, 48), near=0.1, far=10.0)


def turned(mesh: Mesh, cameras: Cameras, rotation: torch.Tensor) -> tuple[Mesh, Cameras]:
    """Object and camera rotated together: x -> R x, world_to_cam -> world_to_cam R^T."""
    rigid = torch.eye(4)
    rigid[:3, :3] = rotation.T
    moved = Mesh(mesh.verts @ rotation.T, mesh.faces, vertex_colors=mesh.vertex_colors)
    return moved, Cameras(
        cameras.world_to_cam @ rigid, cameras.intrinsics, cameras.image_size, 0.1, 10.0
    )


def lighting(frame: str) -> Lighting:
    sh = torch.zeros(9, 3)
    sh[0] = 0.2 * math.sqrt(4 * math.pi)
    # Toward the light in camera axes (OpenCV: y down): up-left of the camera, toward it.
    sun = DirectionalLight(torch.tensor([-0.3, -0.5, -0.8]), torch.full((3,), 2.0))
    return Lighting(sh_coefficients=sh, directional=[sun], frame=frame)


def effects() -> list:
    specular = make_effect("specular")
    shadows = make_effect("shadows", map_resolution=256)
    with torch.no_grad():
        specular.strength.fill_(0.8)
        shadows.strength.fill_(1.0)
    return [specular, shadows]


def render(mesh: Mesh, cameras: Cameras, light: Lighting, chosen: list) -> torch.Tensor:
    with torch.no_grad():
        return render_with_effects(Renderer(), mesh, cameras, light, chosen).color


@pytest.mark.parametrize("angle", [0.9, 2.5])
def test_camera_frame_highlight_and_shadow_turn_with_the_camera(angle: float) -> None:
    mesh, cameras = scene()
    moved_mesh, moved_cameras = turned(mesh, cameras, rotation_matrix([0.1, 1.0, 0.3], angle))
    chosen = effects()
    light = lighting("camera")
    plain = render(mesh, cameras, light, [])
    before = render(mesh, cameras, light, chosen)
    after = render(moved_mesh, moved_cameras, light, chosen)
    # The effects change the image (a highlight brightens, a shadow darkens) ...
    assert float((before - plain).max()) > 0.05
    assert float((before - plain).min()) < -0.02
    # ... and turn with the pair: the same highlight, the same shadowed pixels (up to the
    # shadow map's texel grid, which is laid out in world axes).
    assert float((before - after).abs().mean()) < 1e-3
    shadowed_before = (plain - before).amax(-1) > 0.02
    plain_after = render(moved_mesh, moved_cameras, light, [])
    shadowed_after = (plain_after - after).amax(-1) > 0.02
    overlap = (shadowed_before & shadowed_after).sum() / (shadowed_before | shadowed_after).sum()
    assert int(shadowed_before.sum()) > 20 and float(overlap) > 0.9
    highlight = (before - plain).amax(-1) > 0.05
    highlight_after = (after - plain_after).amax(-1) > 0.05
    overlap = (highlight & highlight_after).sum() / (highlight | highlight_after).sum()
    assert int(highlight.sum()) > 5 and float(overlap) > 0.9
    # A world-frame light's highlight stays in the world: the turned pair looks different.
    world = lighting("world")
    world_before = render(mesh, cameras, world, chosen)
    world_after = render(moved_mesh, moved_cameras, world, chosen)
    assert float((world_before - world_after).abs().max()) > 0.05


def test_views_of_one_batch_get_their_own_light_direction() -> None:
    mesh, cameras = scene()
    rotation = rotation_matrix([0.0, 1.0, 0.0], 1.3)
    _, other = turned(mesh, cameras, rotation)
    pair = Cameras(
        torch.cat([cameras.world_to_cam, other.world_to_cam]),
        cameras.intrinsics.expand(2, 3, 3),
        cameras.image_size,
        0.1,
        10.0,
    )
    directions, _ = view_light_directions(lighting("camera"), pair, torch.zeros(()))
    expected = torch.nn.functional.normalize(torch.tensor([-0.3, -0.5, -0.8]), dim=0)
    for view in range(2):
        rotation_view = pair.world_to_cam[view, :3, :3]
        assert torch.allclose(rotation_view @ directions[view], expected, atol=1e-5)
    # A batch renders each view as it renders alone.
    chosen = effects()
    together = render(mesh, pair, lighting("camera"), chosen)
    alone = render(mesh, other, lighting("camera"), chosen)
    assert float((together[1:] - alone).abs().max()) < 1e-4


def test_a_turned_light_is_the_light_turned():
    """rotated_light_visibility: the identity is vertex_light_visibility; rotation_between
    takes its source onto its target (a half turn for opposite ones); a light turned about
    a torus' axis casts shadows of the same mean strength at other vertices."""
    from data_synth.shapes import torus
    from recon.effects.light_transport import (
        rotated_light_visibility,
        rotation_between,
        vertex_light_visibility,
    )

    mesh = torus(resolution=16)
    lighting = Lighting.constant(0.3)
    lighting.directional = [
        DirectionalLight(torch.tensor([0.3, 0.9, 0.2]), torch.tensor([2.0, 2.0, 2.0]))
    ]
    identity = torch.eye(3, dtype=torch.float64)[None]
    same = rotated_light_visibility(mesh.verts, mesh.faces, lighting, identity)[0]
    assert torch.allclose(same, vertex_light_visibility(mesh.verts, mesh.faces, lighting))
    up, side = torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 0.0, 0.0])
    turn = rotation_between(up, side)
    assert torch.allclose(turn @ up.double(), side.double(), atol=1e-12)
    assert torch.allclose(rotation_between(up, -up) @ up.double(), -up.double(), atol=1e-12)
    # A quarter turn about the torus' own axis (y): the same shadows, elsewhere on the ring.
    quarter = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]).double()
    turned = rotated_light_visibility(mesh.verts, mesh.faces, lighting, quarter[None])[0]
    # (within the shadow maps' texel sampling of a coarse mesh)
    assert float(turned.mean()) == pytest.approx(float(same.mean()), abs=0.03)
    assert float((turned - same).abs().max()) > 0.2  # but not at the same vertices


@pytest.mark.parametrize("overshoot", [0.0, 1e-6])
def test_a_surface_facing_the_light_square_on_has_finite_shadow_gradients(shadow_scene, overshoot):
    # Where a normal points straight at the light (n.l = 1, or a hair over after rounding) the
    # slope bias's sqrt(1 - n.l^2) sits at zero: its derivative must not turn the whole
    # backward pass into NaN (a refit diverged on a path-traced torus this way).
    direction = torch.tensor([0.0, 1.0, 0.0])
    covered = shadow_scene.output.mask > 0
    normals = shadow_scene.output.normals.detach().clone()
    normals[covered[..., 0]] = direction * (1.0 + overshoot)
    normals.requires_grad_(True)
    verts = shadow_scene.mesh.verts.detach().clone().requires_grad_(True)
    mesh = replace(shadow_scene.mesh, verts=verts)
    output = replace(shadow_scene.output, normals=normals)
    sun = direction.clone().requires_grad_(True)
    visibility = Shadows(map_resolution=64).visibility(output, mesh, sun / sun.norm())
    visibility.sum().backward()
    for name, tensor in (("normals", normals), ("verts", verts), ("light", sun)):
        assert tensor.grad is not None and bool(torch.isfinite(tensor.grad).all()), name
