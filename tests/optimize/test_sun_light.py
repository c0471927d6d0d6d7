"""The `pbr` fit's sun: split off the environment, shadowed by a shadow map (hand-computable
cases), and the fit with a sun against the fit without one on a tiny sunlit scene."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at
from recon.config.run_config import FitConfig
from recon.errors import ReconError
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.mesh.uv import bake_vertex_attribute, dilate, unwrap
from recon.optimize.checkpoint import History
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.material_stage import pbr_light_record, run_pbr_texture_stage
from recon.optimize.scene_model import LightModel, psnr_from_mse
from recon.optimize.sun_light import ShadowMap, ShadowSettings, reclaim_sun, split_sun
from recon.render.environment import latlong_directions, prefilter_environment
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, sh_basis
from recon.render.texture import build_mip_pyramid


def _quad(half: float, height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A horizontal square [-half, half]^2 in x, z at y = height, facing +y."""
    verts = torch.tensor(
        [[-half, height, -half], [half, height, -half], [half, height, half], [-half, height, half]]
    )
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    return verts, faces


def _ground_and_occluder() -> tuple[torch.Tensor, torch.Tensor]:
    """A 2 x 2 ground at y = 0 and a 1 x 1 occluder above its centre at y = 0.5."""
    ground, ground_faces = _quad(1.0, 0.0)
    occluder, occluder_faces = _quad(0.5, 0.5)
    return torch.cat([ground, occluder]), torch.cat([ground_faces, occluder_faces + 4])


def _ground_grid(count: int = 40) -> torch.Tensor:
    """Points [count^2, 3] at texel centres of the ground (y = 0)."""
    ticks = (torch.arange(count, dtype=torch.float32) + 0.5) / count * 2 - 1
    x, z = torch.meshgrid(ticks, ticks, indexing="ij")
    return torch.stack([x, torch.zeros_like(x), z], -1).reshape(-1, 3)


def sun_visibility(verts, faces, points, normals, direction, settings) -> torch.Tensor:
    """Visibility [N, 1] through the fit's path: a map drawn along the sun, then looked up."""
    return ShadowMap.draw(verts, faces, direction, settings).visibility(points, normals, settings)


def test_overhead_sun_shadows_the_occluders_share_of_the_ground():
    verts, faces = _ground_and_occluder()
    points = _ground_grid()
    normals = torch.tensor([0.0, 1.0, 0.0]).expand_as(points)
    visible = sun_visibility(
        verts, faces, points, normals, torch.tensor([0.0, 1.0, 0.0]), ShadowSettings(256)
    )
    assert visible.shape == (points.shape[0], 1)
    shadowed = float((visible < 0.5).float().mean())
    # The occluder covers a quarter of the ground's area.
    assert shadowed == pytest.approx(0.25, abs=0.02)
    # The occluder's own top is lit (no acne).
    top = sun_visibility(
        verts, faces, torch.tensor([[0.1, 0.5, -0.2]]), normals[:1], normals[0], ShadowSettings(256)
    )
    assert float(top) > 0.9


def test_slanted_sun_moves_the_shadow_by_height_times_tan():
    verts, faces = _ground_and_occluder()
    # 45 degrees toward +x: the shadow of x in [-0.5, 0.5] at height 0.5 falls on x in [-1, 0].
    points = torch.tensor([[-0.75, 0.0, 0.0], [-0.25, 0.0, 0.2], [0.25, 0.0, 0.0], [0.75, 0, 0]])
    normals = torch.tensor([0.0, 1.0, 0.0]).expand_as(points)
    visible = sun_visibility(
        verts, faces, points, normals, torch.tensor([1.0, 1.0, 0.0]), ShadowSettings(256)
    )[:, 0]
    assert visible.tolist() == pytest.approx([0.0, 0.0, 1.0, 1.0], abs=0.05)


def test_split_sun_moves_the_spot_into_a_directional_light():
    size = (32, 64)
    directions, solid_angle = latlong_directions(*size)
    sun = torch.nn.functional.normalize(torch.tensor([0.6, 0.7, 0.35]), dim=0)
    spot = 40 * torch.exp((directions @ sun - 1) / 0.002)
    sky = 0.3 + 0.1 * directions[..., 1:2].clamp_min(0)
    environment = sky + spot[..., None] * torch.tensor([1.0, 0.9, 0.8])
    remaining, direction, irradiance = split_sun(environment, 10.0)
    expected = (spot * solid_angle).sum() * torch.tensor([1.0, 0.9, 0.8])
    assert torch.allclose(irradiance, expected, rtol=0.05)
    assert math.degrees(math.acos(float(direction @ sun))) < 2.0
    # The spot is gone (but for its tail beyond the cone around the brightest texel); outside
    # the cone nothing changes.
    left = ((remaining - sky).mean(-1) * solid_angle).sum()
    assert abs(float(left)) < 0.02 * float(irradiance.mean())
    far = (directions @ sun) < math.cos(math.radians(15))
    assert torch.equal(remaining[far], environment[far])
    with pytest.raises(ReconError, match="cone_degrees"):
        split_sun(environment, 95.0)


def test_reclaim_sun_takes_back_the_sun_an_sh_light_absorbed():
    size = (32, 64)
    directions, _ = latlong_directions(*size)
    sun = torch.nn.functional.normalize(torch.tensor([0.6, 0.7, 0.35]), dim=0)
    irradiance = torch.tensor([2.5, 2.0, 1.5])
    # What an order-2 SH light holds of a sun: I sum_k Y_k(d) Y_k(w), over a uniform sky.
    kernel = sh_basis(directions.reshape(-1, 3)) @ sh_basis(sun[None])[0]
    environment = 0.4 + kernel.reshape(*size, 1) * irradiance
    remaining, reclaimed = reclaim_sun(environment, sun)
    assert torch.allclose(reclaimed, irradiance, rtol=0.02)
    assert float((remaining - 0.4).abs().max()) < 0.02
    # A sky without a sun along d gives nothing; half a share gives half.
    assert float(reclaim_sun(torch.full((*size, 3), 0.4), sun)[1].abs().max()) < 1e-4
    assert torch.allclose(reclaim_sun(environment, sun, 0.5)[1], irradiance / 2, rtol=0.02)


def test_visibility_scales_the_directional_term_with_gradients():
    from recon.render.pbr import PbrMaterial, pbr_shade

    generator = torch.Generator().manual_seed(0)
    count = 6
    normals = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=generator, dtype=torch.float64) + torch.tensor([0, 2, 0]),
        dim=-1,
    )
    to_viewer = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=generator, dtype=torch.float64) + torch.tensor([0, 2, 1]),
        dim=-1,
    )
    base = torch.rand(count, 3, generator=generator, dtype=torch.float64)
    roughness = torch.full((count, 1), 0.4, dtype=torch.float64)
    material = PbrMaterial(base, roughness, torch.zeros_like(roughness))
    visibility = torch.tensor([[0.0], [0.25], [1.0], [1.0], [0.5], [0.0]], dtype=torch.float64)
    direction = torch.tensor([0.3, 1.0, 0.2], dtype=torch.float64, requires_grad=True)
    irradiance = torch.tensor([2.0, 1.5, 1.0], dtype=torch.float64, requires_grad=True)

    def shade(direction, irradiance, visibility):
        light = DirectionalLight(torch.nn.functional.normalize(direction, dim=0), irradiance)
        return pbr_shade(material, normals, to_viewer, None, [light], [visibility])

    unshadowed = shade(direction, irradiance, torch.ones_like(visibility))
    assert torch.allclose(shade(direction, irradiance, visibility), unshadowed * visibility)
    assert torch.autograd.gradcheck(
        lambda d, e: shade(d, e, visibility), (direction, irradiance), eps=1e-6, atol=1e-6
    )
    with pytest.raises(ReconError, match="directional visibilities"):
        pbr_shade(material, normals, to_viewer, None, [], [visibility])


# --------------------------------------------------------------------------------------------
# the fit
# --------------------------------------------------------------------------------------------

SIZE = 32
SUN = (0.5, 0.8, 0.3)


def _cameras(count: int) -> Cameras:
    index = torch.arange(count, dtype=torch.float32) + 0.5
    height = 1 - 2 * index / count
    radius = (1 - height**2).sqrt()
    angle = index * 2.399963
    eyes = 3.0 * torch.stack([radius * torch.cos(angle), height, radius * torch.sin(angle)], -1)
    intrinsics = intrinsics_from_fov(35.0, (SIZE, SIZE)).expand(count, 3, 3)
    return Cameras(look_at(eyes), intrinsics, (SIZE, SIZE))


@pytest.fixture(scope="module")
def sunlit_scene():
    """A sphere with a smaller sphere floating over it, under a dim sky and a strong sun that
    casts the small one's shadow on the big one."""
    big = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.25)
    small.apply_translation(0.95 * torch.nn.functional.normalize(torch.tensor(SUN), dim=0).numpy())
    both = trimesh.util.concatenate([big, small])
    verts = torch.tensor(both.vertices, dtype=torch.float32)
    faces = torch.tensor(both.faces, dtype=torch.int64)
    uvs, uv_faces = unwrap(verts, faces, resolution=64)
    colour = torch.full((verts.shape[0], 3), 0.6)
    base, coverage = bake_vertex_attribute((faces, uvs, uv_faces), colour, (64, 64))
    base = dilate(base.float(), coverage)
    texture = torch.cat([base, torch.tensor([0.4, 0.0]).expand(64, 64, 2)], -1)
    mesh = Mesh(verts, faces, uvs=uvs.float(), uv_faces=uv_faces, texture=base)
    cameras = _cameras(16)
    renderer = Renderer(texture_boundary="clamp")
    sky = torch.full((16, 32, 3), 0.15)
    sun = DirectionalLight(
        torch.nn.functional.normalize(torch.tensor(SUN), dim=0), torch.full((3,), 3.0)
    )
    with torch.no_grad():
        buffers = renderer.surface_buffers(mesh, cameras)
        from recon.optimize.material_stage import shadowed_suns

        output = renderer.shade_pbr(
            buffers,
            cameras.centers(),
            texture,
            prefilter_environment(sky, 6),
            directional=[sun],
            directional_visibility=shadowed_suns(buffers, [sun], ShadowSettings()),
            mip_pyramid=build_mip_pyramid(texture),
        )
    train = [i for i in range(16) if i % 4]
    test = [i for i in range(16) if not i % 4]

    def split(indices, name):
        index = torch.tensor(indices)
        return CaptureSet(
            cameras[index],
            output.color[index],
            output.alpha[index],
            [str(i) for i in indices],
            name,
        )

    return mesh, split(train, "train"), split(test, "test")


def _fit(scene, tmp_path, suns: int):
    mesh, train, _ = scene
    config = FitConfig()
    config.texture.steps = 30
    config.texture.views_per_step = 3
    config.texture.texture_size = 64
    config.texture.learning_rate = 0.0  # geometry given: compare the light models only
    config.checkpoint_every = 1000
    config.material = "pbr"
    config.pbr.environment_size = [16, 32]
    config.pbr.environment_learning_rate = 0.1
    config.pbr.sun_lights = suns
    # The light seed: on this tiny scene the highlights seed overshoots (an environment mean
    # of about 0.8 for a 0.15 sky), with or without a sun; the test compares the light models.
    config.pbr.environment_seed = "light"
    config.pbr.sun_learning_rate = 0.2
    config.pbr.material_texture_size = 1
    # The geometry stage's light: the sky right, its sun 15 degrees off and half as bright.
    albedo = torch.full((mesh.verts.shape[0], 3), 0.6)
    light = LightModel(ambient=0.15, with_sun=True)
    with torch.no_grad():
        light.sun_direction.copy_(torch.tensor([0.3, 0.9, 0.2]))
        light.sun_log_irradiance.fill_(math.log(1.5))
    geometry = GeometryResult(mesh.verts, mesh.faces, albedo, light)
    torch.manual_seed(0)
    return run_pbr_texture_stage(
        train,
        geometry,
        config,
        torch.device("cpu"),
        0,
        tmp_path / f"{suns}.pt",
        History(tmp_path / f"h{suns}"),
    )


def test_a_shadowed_sun_fits_a_sunlit_scene_better_than_the_environment_alone(
    sunlit_scene, tmp_path
):
    _, _, test = sunlit_scene
    renderer = Renderer(texture_boundary="clamp")
    scores = {}
    for suns in (0, 1):
        result = _fit(sunlit_scene, tmp_path, suns)
        with torch.no_grad():
            color = result.render(renderer, test.cameras).color
        scores[suns] = psnr_from_mse(float(((color - test.images) ** 2).mean()))
        if suns:
            (sun,) = result.suns
            truth = torch.nn.functional.normalize(torch.tensor(SUN), dim=0)
            assert math.degrees(math.acos(float(sun.direction_to_light @ truth))) < 5
            record = pbr_light_record(result, "environment.exr")
            assert len(record["suns"]) == 1 and record["shadow"]["resolution"] == 512
    assert scores[1] > scores[0] + 4.0, scores
