"""The world's glossy material: a spatially varying roughness (scene.material.roughness_texture)
reaches the renders of both backends (recon's split-sum shading and Mitsuba's principled BSDF
with a bitmap roughness), and the synth stage writes the true maps with the reference mesh."""

from __future__ import annotations

import math

import pytest
import torch

from data_synth.environment import project_to_sh
from data_synth.material import (
    WorldMaterial,
    render_views_pbr,
    roughness_pattern,
    world_environment,
    world_material,
)
from data_synth.scene import WorldLighting
from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at
from recon.config.checks import ConfigFieldError
from recon.config.run_config import EffectConfig, MaterialConfig, OwnSpecularConfig
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.environment import latlong_directions
from recon.render.shading import Lighting

SIZE = 32


def test_roughness_pattern_spans_its_range_in_patches():
    material = MaterialConfig(
        albedo="patches", roughness_texture="patches", roughness_range=[0.1, 0.5]
    )
    pattern = roughness_pattern(material, (32, 32))
    assert pattern.shape == (32, 32)
    assert float(pattern.min()) == pytest.approx(0.1) and float(pattern.max()) == pytest.approx(0.5)
    # Voronoi patches: a handful of constant regions, seeded apart from the albedo's pattern.
    assert 4 <= len(torch.unique(pattern)) <= 24
    torch.testing.assert_close(pattern, roughness_pattern(material, (32, 32)))
    assert roughness_pattern(MaterialConfig(), (32, 32)) is None


def test_roughness_texture_settings_are_checked_by_name():
    with pytest.raises(ConfigFieldError, match="roughness_range"):
        MaterialConfig(roughness_texture="noise", roughness_range=[0.5, 0.2])
    with pytest.raises(ConfigFieldError, match="roughness_texture.*vertex_noise"):
        MaterialConfig(albedo="vertex_noise", roughness_texture="noise")


def _plane() -> Mesh:
    """A 2 x 2 quad in z = 0 facing +z; u runs along +x."""
    verts = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    return Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=torch.full((16, 16, 3), 0.2))


def test_world_material_takes_the_texture_and_refuses_two_roughnesses():
    mesh = _plane()
    material = MaterialConfig(
        albedo="checker", roughness_texture="stripes", roughness_range=[0.2, 0.6]
    )
    found = world_material([EffectConfig("specular", {"specular_level": 0.7})], material, mesh)
    assert found.textured and found.roughness.shape == (16, 16)
    assert found.specular_level == pytest.approx(0.7) and found.metalness == 0.0
    assert torch.unique(found.roughness).tolist() == pytest.approx([0.2, 0.6])
    assert found.maps().shape == (16, 16, 2)
    uniform = world_material([EffectConfig("specular", {"roughness": 0.3})], MaterialConfig(), mesh)
    assert not uniform.textured and torch.unique(uniform.roughness).tolist() == pytest.approx([0.3])
    assert world_material([], material, mesh) is None
    with pytest.raises(ReconError, match="roughness 0.3 and scene.material.roughness_texture"):
        world_material([EffectConfig("specular", {"roughness": 0.3})], material, mesh)
    with pytest.raises(ReconError, match="roughplastic takes a single roughness"):
        world_material([EffectConfig("specular", {"plastic": True})], material, mesh)


def test_world_environment_is_the_map_plus_the_rest_of_the_sh_light():
    directions, _ = latlong_directions(16, 32)
    environment = 1 + directions[..., 1:2].expand(16, 32, 3) + 0.5 * directions[..., :1]
    ambient = 0.25
    sh = project_to_sh(environment)
    sh[0] += ambient * math.sqrt(4 * math.pi)
    world = WorldLighting(Lighting(sh_coefficients=sh), environment_map=environment)
    found = world_environment(world, (8, 16))
    pooled = torch.nn.functional.avg_pool2d(environment.permute(2, 0, 1)[None], 2)[0]
    torch.testing.assert_close(found, pooled.permute(1, 2, 0) + ambient, atol=1e-5, rtol=0)
    # Without a map: the SH radiance itself (exact for this band-1 field, up to quadrature).
    only_sh = world_environment(WorldLighting(Lighting(sh_coefficients=sh)), (8, 16))
    coarse, _ = latlong_directions(8, 16)
    expected = 1 + coarse[..., 1:2] + 0.5 * coarse[..., :1] + ambient
    torch.testing.assert_close(only_sh, expected.expand(8, 16, 3), atol=0.02, rtol=0)


def _glossy_world() -> WorldLighting:
    """Two small bright windows that a mirror at (x = -0.5, 0, 0) and (x = +0.5, 0, 0) reflects
    toward a camera at (0, 0, 3): one highlight in each half of the plane."""
    directions, _ = latlong_directions(64, 128)
    environment = torch.full((64, 128, 1), 0.05)
    for side in (-0.5, 0.5):
        window = torch.nn.functional.normalize(torch.tensor([side, 0.0, 3.0]), dim=0)
        environment = environment + 40 * torch.exp((directions @ window - 1) / 0.004)[..., None]
    environment = environment.expand(64, 128, 3).contiguous()
    return WorldLighting(Lighting(sh_coefficients=project_to_sh(environment)), environment)


def _camera() -> Cameras:
    intrinsics = intrinsics_from_fov(40.0, (SIZE, SIZE))[None]
    return Cameras(look_at(torch.tensor([[0.0, 0.0, 3.0]])), intrinsics, (SIZE, SIZE))


def _split_material(left: float, right: float) -> WorldMaterial:
    """Roughness `left` on u < 1/2 (x < 0), `right` on u > 1/2."""
    roughness = torch.full((16, 16), right)
    roughness[:, :8] = left
    return WorldMaterial(roughness, True, 0.0, 0.5)


def _render(backend: str, material: WorldMaterial) -> torch.Tensor:
    """[H, W] mean radiance of the plane's one view."""
    mesh, world, cameras = _plane(), _glossy_world(), _camera()
    if backend == "own":
        settings = OwnSpecularConfig(environment_size=[32, 64], prefilter_levels=8)
        output = render_views_pbr(mesh, material, cameras, world, settings, 8, "test")[0]
        return output.color[0].mean(-1)
    pytest.importorskip("mitsuba")
    from data_synth.mitsuba_backend import MitsubaOptions, pick_variant, render_mitsuba

    if pick_variant() != "llvm_ad_rgb":
        pytest.skip("llvm_ad_rgb unavailable: renders would be too slow for CI")
    options = MitsubaOptions(spp=64, material="specular", roughness_map=material.roughness)
    colors, _ = render_mitsuba(mesh, cameras, world, options)
    return colors[0].mean(-1)


@pytest.mark.parametrize("backend", ["own", "mitsuba"])
def test_the_smooth_half_shows_the_sharper_highlight(backend):
    """Left half smooth (0.1), right half rough (0.6), and mirrored: the smooth half's highlight
    peaks far higher and is more concentrated, whichever side it is on."""
    half = SIZE // 2
    # Columns grow with world x in this view (OpenCV x right, camera on +z looking at -z).
    for smooth_left in (True, False):
        material = _split_material(0.1, 0.6) if smooth_left else _split_material(0.6, 0.1)
        image = _render(backend, material)
        left, right = image[:, :half], image[:, half:]
        smooth, rough = (left, right) if smooth_left else (right, left)
        assert float(smooth.max()) > 2 * float(rough.max())
        # Sharper: the peak stands further above the half's median.
        assert float(smooth.max() / smooth.median()) > 2 * float(rough.max() / rough.median())


def test_own_backend_refuses_what_split_sum_cannot_shade():
    mesh, cameras = _plane(), _camera()
    world = _glossy_world()
    settings = OwnSpecularConfig()
    with pytest.raises(ReconError, match="roughplastic"):
        render_views_pbr(
            mesh,
            WorldMaterial(torch.full((16, 16), 0.3), False, 0.0, 0.5, True),
            cameras,
            world,
            settings,
            8,
            "test",
        )
    untextured = Mesh(mesh.verts, mesh.faces, vertex_colors=torch.full((4, 3), 0.5))
    with pytest.raises(ReconError, match="textured mesh"):
        render_views_pbr(untextured, _split_material(0.1, 0.6), cameras, world, settings, 8, "test")
