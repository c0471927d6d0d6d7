"""The Mitsuba backend against recon's own renderer: conventions, agreement, errors.

Every render here is tiny (32-48 px); the whole file runs in well under a minute with
llvm_ad_rgb on two CPU cores. Tests that render skip cleanly when mitsuba is not installed.
"""

from __future__ import annotations

import math
import sys
import warnings

import numpy as np
import pytest
import torch
import trimesh

from data_synth.environment import equirect_directions
from data_synth.mitsuba_backend import (
    DiskSun,
    MitsubaOptions,
    environment_bitmap,
    environment_dict,
    pick_variant,
    plastic_ior,
    render_mitsuba,
)
from data_synth.scene import AreaLight, WorldLighting, build_lighting
from data_synth.shapes import make_shape
from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at, orbit_cameras
from recon.config.run_config import (
    AreaLightConfig,
    EnvironmentConfig,
    LightingConfig,
)
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting, PointLight, sh_basis

# SH band-1 coefficient of a radiance gradient L(w) = g * w_axis (<w_axis, Y_1m> = 4 pi / 3 * k).
_GRADIENT_TO_SH = 0.4886025119029199 * 4 * math.pi / 3


@pytest.fixture
def mitsuba_module():
    """The mitsuba module with the preferred variant selected; skips when it is absent."""
    module = pytest.importorskip("mitsuba")
    variant = pick_variant()
    if variant != "llvm_ad_rgb":
        pytest.skip(f"llvm_ad_rgb unavailable ({variant}): renders would be too slow for CI")
    return module


def psnr(first: torch.Tensor, second: torch.Tensor) -> float:
    """PSNR in dB of linear values clipped to [0, 1], over every pixel and channel."""
    error = ((first.clamp(0, 1) - second.clamp(0, 1)) ** 2).mean()
    return float(-10 * torch.log10(error))


def box_mesh(center: tuple[float, float, float], extents: tuple[float, float, float]) -> Mesh:
    """Axis-aligned box [8 verts, 12 faces], outward counter-clockwise faces."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(center)
    return Mesh(
        torch.tensor(np.asarray(box.vertices), dtype=torch.float32),
        torch.tensor(np.asarray(box.faces), dtype=torch.int64),
    )


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh from several (no UVs)."""
    verts, faces, offset = [], [], 0
    for mesh in meshes:
        verts.append(mesh.verts)
        faces.append(mesh.faces + offset)
        offset += mesh.verts.shape[0]
    return Mesh(torch.cat(verts), torch.cat(faces))


def smooth_sphere_texture(size: int = 64) -> torch.Tensor:
    """A [size, size, 3] albedo, periodic in u and v, constant near the poles (v = 0, 1).

    R, G rotate with u (a mirror flips G), B = 0.45 + 0.35 sin(2 pi v) is brighter in the top
    half of the image than in the bottom half (a v flip inverts it). Periodic and pole-constant,
    so recon's mipmapped lookup and Mitsuba's bilinear one agree at seams and poles.
    """
    coordinates = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    v, u = torch.meshgrid(coordinates, coordinates, indexing="ij")
    envelope = torch.sin(math.pi * v) ** 2
    return torch.stack(
        [
            0.5 + 0.3 * envelope * torch.cos(2 * math.pi * u),
            0.5 + 0.3 * envelope * torch.sin(2 * math.pi * u),
            0.45 + 0.35 * torch.sin(2 * math.pi * v),
        ],
        dim=-1,
    )


def band_limited_lighting() -> Lighting:
    """Ambient + a gradient along an oblique axis + a small band-2 term, all radiance > 0.

    Exactly band 2, so recon's SH irradiance is exact; oblique, so a wrong envmap orientation
    (axis swap, mirror, wrong pole) changes the shading. Plus one directional light.
    """
    sh = torch.zeros(9, 3)
    sh[0] = torch.tensor([0.5, 0.45, 0.4]) * math.sqrt(4 * math.pi)
    gradient = torch.tensor([0.2, 0.25, -0.15])  # L gains gradient . w (|gradient| = 0.35)
    # Y_1-1 ~ y, Y_10 ~ z, Y_11 ~ x.
    sh[1] = gradient[1] * _GRADIENT_TO_SH
    sh[2] = gradient[2] * _GRADIENT_TO_SH
    sh[3] = gradient[0] * _GRADIENT_TO_SH
    sh[4] = 0.05  # xy term: |0.05 * 1.09 * xy| < 0.03, so radiance stays > 0.4 - 0.38
    directional = DirectionalLight(
        torch.nn.functional.normalize(torch.tensor([0.7, 0.6, 0.4]), dim=0),
        torch.tensor([1.6, 1.4, 1.1]),
    )
    return Lighting(sh_coefficients=sh, directional=[directional])


# --------------------------------------------------------------------------------------------
# Variant selection and missing installs
# --------------------------------------------------------------------------------------------


def test_pick_variant_prefers_llvm() -> None:
    mitsuba = pytest.importorskip("mitsuba")
    if "llvm_ad_rgb" not in mitsuba.variants():
        pytest.skip("this mitsuba build has no llvm_ad_rgb")
    assert pick_variant() == "llvm_ad_rgb"
    assert mitsuba.variant() == "llvm_ad_rgb"


def test_pick_variant_falls_back_to_scalar_with_a_warning(monkeypatch) -> None:
    mitsuba = pytest.importorskip("mitsuba")
    real_set_variant = mitsuba.set_variant

    def refuse_llvm(*names: str) -> None:
        if names[0].startswith("llvm"):
            raise ImportError("libLLVM.so: cannot open shared object file")
        real_set_variant(*names)

    monkeypatch.setattr(mitsuba, "set_variant", refuse_llvm)
    try:
        with pytest.warns(RuntimeWarning, match="libllvm19"):
            assert pick_variant() == "scalar_rgb"
        assert mitsuba.variant() == "scalar_rgb"
    finally:
        monkeypatch.undo()
        pick_variant()  # leave the preferred variant selected for the other tests


def test_missing_mitsuba_is_a_clear_error(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # makes `import mitsuba` raise
    with pytest.raises(ReconError, match=r"pip install mitsuba.*libllvm19"):
        pick_variant()


# --------------------------------------------------------------------------------------------
# Conventions
# --------------------------------------------------------------------------------------------


def test_envmap_reproduces_the_sh_radiance_in_every_direction(mitsuba_module) -> None:
    """Mitsuba's envmap lookup (its u = atan2(x, -z) / 2 pi, v = acos(y) / pi, rows on the
    poles, turned by ENVIRONMENT_TO_WORLD) at random directions returns recon's SH radiance."""
    mitsuba = mitsuba_module
    lighting = band_limited_lighting()
    emitter = mitsuba.load_dict(environment_dict(lighting.sh_coefficients))
    directions = torch.nn.functional.normalize(
        torch.randn(2000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64),
        dim=-1,
    )
    mitsuba_radiance = _evaluate_emitter(mitsuba, emitter, directions)
    expected = (sh_basis(directions) @ lighting.sh_coefficients.double()).numpy()
    np.testing.assert_allclose(mitsuba_radiance, expected, rtol=0, atol=3e-3)
    # The same lookup is badly off for a mirrored environment: the check has teeth.
    mirrored = (
        sh_basis(directions * torch.tensor([-1.0, 1.0, 1.0])) @ lighting.sh_coefficients.double()
    ).numpy()
    assert np.abs(mitsuba_radiance - mirrored).max() > 0.1


def _evaluate_emitter(mitsuba, emitter, directions: torch.Tensor) -> np.ndarray:
    """Radiance [N, 3] an environment emitter sends from world directions [N, 3]."""
    import drjit

    interaction = drjit.zeros(mitsuba.SurfaceInteraction3f, directions.shape[0])
    toward_scene = (-directions).float().numpy()
    interaction.wi = mitsuba.Vector3f(toward_scene[:, 0], toward_scene[:, 1], toward_scene[:, 2])
    return np.asarray(emitter.eval(interaction)).reshape(3, -1).T


def test_environment_map_texels_land_in_their_directions(mitsuba_module) -> None:
    """A random map in data_synth.environment's convention (texel centres at theta = pi (i +
    1/2) / h, phi = 2 pi (j + 1/2) / w, direction (sin theta cos phi, cos theta, sin theta sin
    phi)): Mitsuba's envmap returns each texel's value in its direction."""
    mitsuba = mitsuba_module
    height, width = 8, 16
    environment_map = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1))
    emitter = mitsuba.load_dict(environment_dict(None, environment_map=environment_map))
    directions, _ = equirect_directions(height, width)
    radiance = _evaluate_emitter(mitsuba, emitter, directions.reshape(-1, 3).double())
    np.testing.assert_allclose(
        radiance.reshape(height, width, 3), environment_map.numpy(), rtol=0, atol=2e-4
    )


def test_disk_sun_gives_its_irradiance_to_a_facing_plane(mitsuba_module) -> None:
    """A plane facing a disk sun (no other light) has radiance albedo / pi * E."""
    plane = Mesh(
        torch.tensor([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], dtype=torch.float32),
        torch.tensor([[0, 1, 2], [0, 2, 3]]),
    )
    cameras = Cameras(
        look_at(torch.tensor([[0.3, 0.2, 3.0]])), intrinsics_from_fov(30, (16, 16)), (16, 16)
    )
    sun = DiskSun(
        direction_to_light=(0.0, 0.0, 1.0), angular_diameter_deg=6.0, irradiance=(2.0, 1.0, 0.5)
    )
    images, alpha = render_mitsuba(
        plane, cameras, Lighting(torch.zeros(9, 3)), MitsubaOptions(spp=64, suns=(sun,))
    )
    assert bool((alpha > 0.999).all())
    expected = 0.5 / math.pi * torch.tensor([2.0, 1.0, 0.5])
    torch.testing.assert_close(images.mean(dim=(0, 1, 2)), expected, rtol=0.02, atol=0)


def test_camera_marker_lands_on_the_same_pixels(mitsuba_module) -> None:
    """An asymmetric marker (arms of different lengths along +x, +y, +z) seen by two cameras
    with an off-centre principal point on a non-square image: same alpha masks (IoU > 0.95)."""
    marker = merge(
        [
            box_mesh((0.0, 0.0, 0.0), (0.2, 0.2, 0.2)),
            box_mesh((0.45, 0.0, 0.0), (0.7, 0.12, 0.12)),
            box_mesh((0.0, 0.3, 0.0), (0.12, 0.4, 0.12)),
            box_mesh((0.0, 0.0, 0.2), (0.2, 0.2, 0.2)),
        ]
    )
    height, width = 40, 56
    intrinsics = intrinsics_from_fov(35.0, (height, width))
    intrinsics[0, 2] += 7.0  # principal point off the centre in both axes
    intrinsics[1, 2] -= 5.0
    eyes = torch.tensor([[2.0, 1.5, 2.5], [-2.5, -1.0, 1.5]])
    cameras = Cameras(look_at(eyes), intrinsics[None].repeat(2, 1, 1), (height, width), 0.1, 20.0)
    lighting = Lighting.constant(1.0)
    reference = Renderer().render(marker, cameras, lighting)
    _, alpha = render_mitsuba(marker, cameras, lighting, MitsubaOptions(spp=16))
    for view in range(len(cameras)):
        ours = reference.alpha[view, ..., 0] > 0.5
        theirs = alpha[view, ..., 0] > 0.5
        intersection = (ours & theirs).sum().item()
        union = (ours | theirs).sum().item()
        assert union > 40  # the marker is in view
        assert intersection / union > 0.95, f"view {view}: IoU {intersection / union:.3f}"
        # Coverage agrees to the antialiased edge, not only the hard mask.
        assert (reference.alpha[view] - alpha[view]).abs().mean() < 0.01


def test_texture_top_left_lands_where_recon_puts_it(mitsuba_module) -> None:
    """A quad facing the camera with uv (0, 0) at its top-left corner; the texture's top-left
    quadrant is red and its top-right green: both backends put them on the same pixels."""
    half = 0.6
    quad = Mesh(
        torch.tensor([[-half, half, 0], [-half, -half, 0], [half, -half, 0], [half, half, 0]]),
        torch.tensor([[0, 1, 2], [0, 2, 3]]),
        uvs=torch.tensor([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]]),
        uv_faces=torch.tensor([[0, 1, 2], [0, 2, 3]]),
    )
    texture = torch.full((8, 8, 3), 0.4)
    texture[:4, :4] = torch.tensor([0.9, 0.1, 0.1])
    texture[:4, 4:] = torch.tensor([0.1, 0.9, 0.1])
    quad.texture = texture
    # Camera on +z looking at the origin: world +x is image right, world +y is image up.
    cameras = Cameras(
        look_at(torch.tensor([[0.0, 0.0, 3.0]])), intrinsics_from_fov(35, (32, 32)), (32, 32)
    )
    lighting = Lighting.constant(1.0)
    reference = Renderer(texture_filter="linear").render(quad, cameras, lighting)
    images, _ = render_mitsuba(quad, cameras, lighting, MitsubaOptions(spp=64))

    def centroid(image: torch.Tensor, channel: int) -> torch.Tensor:
        weight = (image[..., channel] - image.mean(-1)).clamp_min(0)  # that colour's excess
        rows, columns = torch.meshgrid(
            torch.arange(32.0) + 0.5, torch.arange(32.0) + 0.5, indexing="ij"
        )
        return torch.stack([(weight * columns).sum(), (weight * rows).sum()]) / weight.sum()

    for channel in (0, 1):
        ours = centroid(reference.color[0], channel)
        theirs = centroid(images[0], channel)
        assert (ours - theirs).norm() < 0.5, (
            f"channel {channel}: {ours.tolist()} vs {theirs.tolist()}"
        )
    red = centroid(images[0], 0)
    assert red[0] < 16 and red[1] < 16  # top-left of the image
    assert psnr(reference.color, images) > 30


# --------------------------------------------------------------------------------------------
# Agreement with recon's renderer
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("albedo", ["texture", "vertex_colors"])
def test_agrees_with_recon_renderer_on_a_convex_diffuse_scene(mitsuba_module, albedo: str) -> None:
    """Diffuse sphere, band-limited SH environment + one directional light, direct light only.

    Convex, so nothing is occluded and recon's shadow-free shading is exact; the two must agree
    up to Monte Carlo noise and filtering. PSNR over the full 48 x 48 image (background and
    antialiased silhouettes included), on linear values clipped to [0, 1]: >= 30 dB (measured
    about 37 dB at 256 spp).
    """
    mesh = make_shape("sphere", resolution=32)
    if albedo == "texture":
        mesh.texture = smooth_sphere_texture()
    else:
        directions = torch.nn.functional.normalize(mesh.verts, dim=-1)
        mesh.vertex_colors = 0.5 + 0.3 * directions * torch.tensor([1.0, -0.7, 0.5])
        mesh.uvs = mesh.uv_faces = None
    cameras = orbit_cameras(3, (48, 48), distance=3.0, fov_x_deg=40.0, elevation_deg=25.0)
    lighting = band_limited_lighting()
    reference = Renderer().render(mesh, cameras, lighting)
    images, alpha = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=256, seed=1))
    achieved = psnr(reference.color, images)
    print(f"agreement PSNR ({albedo}): {achieved:.2f} dB")
    assert achieved >= 30.0
    assert (reference.alpha - alpha).abs().mean() < 0.005
    # Not a lucky average: the per-view means agree to 2%.
    torch.testing.assert_close(
        images.mean(dim=(1, 2)), reference.color.mean(dim=(1, 2)), rtol=0.02, atol=0
    )


@pytest.mark.slow
def test_point_lights_agree_with_recon_renderer(mitsuba_module) -> None:
    """An isotropic bulb and a one-sided cosine emitter (recon's stand-in for a small area light)
    over a dim environment, on a convex sphere: the same shading in both (>= 30 dB)."""
    mesh = make_shape("sphere", resolution=32)
    mesh.uvs = mesh.uv_faces = None
    cameras = orbit_cameras(2, (40, 40), distance=3.0, elevation_deg=20.0)
    lighting = Lighting.constant(0.15)
    lighting.points = [
        PointLight(torch.tensor([1.6, 1.8, 1.2]), torch.tensor([6.0, 5.0, 4.0])),
        PointLight(
            torch.tensor([-1.5, 0.5, 2.0]),
            torch.tensor([4.0, 4.0, 6.0]),
            emitter_normal=torch.nn.functional.normalize(torch.tensor([1.0, 0.0, -0.6]), dim=0),
        ),
    ]
    reference = Renderer().render(mesh, cameras, lighting)
    images, _ = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=128, seed=2))
    assert psnr(reference.color, images) >= 30.0
    torch.testing.assert_close(
        images.mean(dim=(1, 2)), reference.color.mean(dim=(1, 2)), rtol=0.03, atol=0
    )


@pytest.mark.slow
def test_world_lighting_renders_the_map_and_true_area_lights(mitsuba_module) -> None:
    """data_synth.scene's WorldLighting (studio map + small area light + ambient): Mitsuba
    renders the full map and the rectangle, recon their SH projection and point stand-in. On a
    convex sphere they still agree (the map's band-3+ and the light's size matter little to a
    Lambertian sphere); counting the stand-in as well would add a whole second light."""
    config = LightingConfig(
        ambient=[0.1, 0.1, 0.1],
        sky_gradient=0.0,
        suns=[],
        areas=[AreaLightConfig(center=[1.2, 2.0, 2.2], size=[0.3, 0.3], radiance=[60.0] * 3)],
        environment=EnvironmentConfig(kind="studio", strength=0.3, resolution=[32, 64]),
    )
    world = build_lighting(config)
    assert len(world.area_lights) == 1 and len(world.lighting.points) == 1
    mesh = make_shape("sphere", resolution=32)
    mesh.uvs = mesh.uv_faces = None
    cameras = orbit_cameras(2, (40, 40), distance=3.0, elevation_deg=20.0)
    reference = Renderer().render(mesh, cameras, world.lighting)
    images, _ = render_mitsuba(mesh, cameras, world, MitsubaOptions(spp=128, seed=3))
    assert psnr(reference.color, images) >= 30.0
    # Without the stand-in removal the area light would count twice: far brighter.
    torch.testing.assert_close(images.mean(), reference.color.mean(), rtol=0.03, atol=0)


def test_output_is_premultiplied_with_black_background(mitsuba_module) -> None:
    """Constant unit environment, albedo 0.5: radiance 0.5 inside; edge colour = 0.5 * alpha."""
    mesh = make_shape("sphere", resolution=16)
    mesh.uvs = mesh.uv_faces = None
    cameras = orbit_cameras(1, (32, 32), distance=3.0)
    images, alpha = render_mitsuba(mesh, cameras, Lighting.constant(1.0), MitsubaOptions(spp=64))
    background = alpha[..., 0] == 0
    assert bool(background.any())
    assert float(images[background].abs().max()) == 0.0
    edge = (alpha[..., 0] > 0.2) & (alpha[..., 0] < 0.8)
    assert int(edge.sum()) > 10
    # Colour over black: edge colour / coverage is the interior radiance 0.5 (an un-premultiplied
    # image would give colour 0.5 whatever the coverage). Aggregated, as per-pixel ratios carry
    # the environment-sampling noise of a few hits.
    ratio = images[edge].mean(-1).sum() / alpha[..., 0][edge].sum()
    assert abs(float(ratio) - 0.5) < 0.02
    interior = alpha[..., 0] == 1
    assert abs(float(images[interior].mean()) - 0.5) < 0.01


def test_rendering_is_deterministic_per_seed(mitsuba_module) -> None:
    mesh = make_shape("sphere", resolution=16)
    cameras = orbit_cameras(2, (16, 16))
    lighting = Lighting.constant(1.0)
    first, _ = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=4, seed=5))
    second, _ = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=4, seed=5))
    other, _ = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=4, seed=6))
    assert torch.equal(first, second)
    assert not torch.equal(first, other)


def test_samples_split_into_passes_average_like_one_pass(mitsuba_module, monkeypatch) -> None:
    """Large renders split spp into passes (bounded memory); the average is the same estimate."""
    import data_synth.mitsuba_backend as backend

    mesh = make_shape("sphere", resolution=16)
    mesh.uvs = mesh.uv_faces = None
    cameras = orbit_cameras(1, (16, 16))
    lighting = band_limited_lighting()
    single, single_alpha = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=96))
    monkeypatch.setattr(backend, "_MAXIMUM_SAMPLES_PER_PASS", 16 * 16 * 20)  # 5 passes
    split, split_alpha = render_mitsuba(mesh, cameras, lighting, MitsubaOptions(spp=96))
    assert not torch.equal(single, split)  # other samples...
    reference = Renderer().render(mesh, cameras, lighting).color
    assert psnr(reference, split) > 30  # ...the same estimate, with the same noise level
    assert abs(psnr(reference, split) - psnr(reference, single)) < 2
    torch.testing.assert_close(split.mean(), single.mean(), rtol=0.03, atol=0)
    assert float((single_alpha - split_alpha).abs().mean()) < 0.01
    assert float(split_alpha.max()) == 1.0 and float(split_alpha.min()) == 0.0


@pytest.mark.parametrize("albedo", ["texture", "vertex_colors"])
def test_scalar_variant_renders_the_same_scene(albedo: str) -> None:
    """The scalar_rgb fallback builds the same scene (its buffers are other types)."""
    mitsuba = pytest.importorskip("mitsuba")
    if "scalar_rgb" not in mitsuba.variants():
        pytest.skip("this mitsuba build has no scalar_rgb")
    mesh = make_shape("sphere", resolution=16)
    if albedo == "texture":
        mesh.texture = smooth_sphere_texture(16)
    else:
        mesh.uvs = mesh.uv_faces = None
        mesh.vertex_colors = 0.5 + 0.3 * torch.nn.functional.normalize(mesh.verts, dim=-1)
    cameras = orbit_cameras(1, (16, 16))
    lighting = band_limited_lighting()
    reference = Renderer().render(mesh, cameras, lighting)
    try:
        images, alpha = render_mitsuba(
            mesh, cameras, lighting, MitsubaOptions(spp=64, variant="scalar_rgb")
        )
    finally:
        pick_variant()
    assert psnr(reference.color, images) > 28
    assert float((reference.alpha - alpha).abs().mean()) < 0.02


# --------------------------------------------------------------------------------------------
# Area light shadows
# --------------------------------------------------------------------------------------------


def _segment_hits_box(
    starts: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray
) -> np.ndarray:
    """Slab test: does segment start -> end ([..., 3]) cross the box [low, high]? -> [...] bool."""
    direction = ends - starts
    with np.errstate(divide="ignore", invalid="ignore"):
        first = (low - starts) / direction
        second = (high - starts) / direction
    near = np.nanmax(np.minimum(first, second), axis=-1)
    far = np.nanmin(np.maximum(first, second), axis=-1)
    return (near <= far) & (far > 1e-6) & (near < 1 - 1e-6)


@pytest.mark.slow
def test_area_light_casts_an_umbra_of_the_expected_depth(mitsuba_module) -> None:
    """A ground plane, a flat box above it, a square area light above that, no other light.

    Pixel-by-pixel geometry (rays to a grid over the light, slab tests against the box) splits
    the plane into umbra and fully lit. Fully lit pixels match the render without the box
    (same seed, same samples); umbra pixels lose the whole area-light contribution, which the
    no-occluder render gives as albedo / pi * E with E integrated over the rectangle.
    """
    plane = Mesh(
        torch.tensor([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], dtype=torch.float32),
        torch.tensor([[0, 2, 1], [0, 3, 2]]),  # counter-clockwise seen from +y
    )
    box_low, box_high = np.array([-0.25, 0.55, -0.25]), np.array([0.25, 0.65, 0.25])
    occluder = box_mesh(tuple((box_low + box_high) / 2), tuple(box_high - box_low))
    light_center, light_half, radiance = np.array([0.0, 2.0, 0.0]), 0.2, 10.0
    area_light = AreaLight(
        center=torch.tensor(light_center, dtype=torch.float32),
        normal=torch.tensor([0.0, -1.0, 0.0]),  # emits downwards
        edge_u=torch.tensor([2 * light_half, 0.0, 0.0]),
        edge_v=torch.tensor([0.0, 0.0, 2 * light_half]),
        radiance=torch.tensor([radiance] * 3),
    )
    size = 40
    cameras = Cameras(
        look_at(torch.tensor([[0.0, 3.0, 1.5]])),
        intrinsics_from_fov(50, (size, size)),
        (size, size),
        0.1,
        20.0,
    )
    options = MitsubaOptions(spp=64, area_lights=(area_light,), seed=2)
    dark = Lighting(torch.zeros(9, 3))
    shadowed, _ = render_mitsuba([plane, occluder], cameras, dark, options)
    unshadowed, _ = render_mitsuba([plane], cameras, dark, options)

    # Ground point under each pixel corner and centre (5 samples per pixel).
    world_to_cam = cameras.world_to_cam[0].double().numpy()
    rotation, eye = world_to_cam[:3, :3], cameras.centers()[0].double().numpy()
    intrinsics_inverse = np.linalg.inv(cameras.intrinsics[0].double().numpy())
    offsets = [(0.5, 0.5), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
    grid = np.arange(size, dtype=np.float64)
    columns, rows = np.meshgrid(grid, grid, indexing="xy")
    light_samples = np.linspace(-light_half, light_half, 7)
    light_points = np.stack(
        [light_center + np.array([a, 0.0, b]) for a in light_samples for b in light_samples]
    )  # [49, 3]
    blocked_fraction = np.zeros((len(offsets), size, size))
    sees_box = np.zeros((size, size), dtype=bool)
    ground = np.zeros((size, size, 3))
    for index, (du, dv) in enumerate(offsets):
        pixels = np.stack([columns + du, rows + dv, np.ones_like(columns)], axis=-1)
        directions = (pixels @ intrinsics_inverse.T) @ rotation  # camera -> world direction
        distance = -eye[1] / directions[..., 1]
        points = eye + distance[..., None] * directions  # on y = 0
        sees_box |= _segment_hits_box(np.broadcast_to(eye, points.shape), points, box_low, box_high)
        hits = _segment_hits_box(
            np.broadcast_to(points[..., None, :], (*points.shape[:2], 49, 3)),
            np.broadcast_to(light_points, (*points.shape[:2], 49, 3)),
            box_low,
            box_high,
        )
        blocked_fraction[index] = hits.mean(-1)
        if index == 0:
            ground = points
    umbra = (blocked_fraction == 1).all(0) & ~sees_box
    lit = (blocked_fraction == 0).all(0) & ~sees_box
    assert umbra.sum() >= 12 and lit.sum() > 200

    shadow_value = shadowed[0].mean(-1).numpy()
    free_value = unshadowed[0].mean(-1).numpy()
    # Fully lit: the occluder changes nothing.
    np.testing.assert_allclose(shadow_value[lit], free_value[lit], rtol=1e-4, atol=1e-6)
    # Expected contribution of the light: albedo / pi * integral of L cos cos / r^2 over it.
    fine = np.linspace(-light_half, light_half, 41)
    fine = (fine[1:] + fine[:-1]) / 2
    element = (fine[1] - fine[0]) ** 2
    light_grid = np.stack([light_center + np.array([a, 0.0, b]) for a in fine for b in fine])
    to_light = light_grid[None] - ground[umbra][:, None]  # [N, M, 3]
    distance_squared = (to_light**2).sum(-1)
    cosine_surface = to_light[..., 1] / np.sqrt(distance_squared)
    irradiance = (radiance * cosine_surface**2 / distance_squared * element).sum(
        -1
    )  # cos_l = cos_s
    expected_drop = 0.5 / math.pi * irradiance
    measured_drop = free_value[umbra] - shadow_value[umbra]
    np.testing.assert_allclose(measured_drop, expected_drop, rtol=0.1)
    # The umbra receives nothing else (no environment, direct light only).
    assert float(np.abs(shadow_value[umbra]).max()) < 1e-6


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (MitsubaOptions(spp=0), "spp"),
        (MitsubaOptions(max_depth=0), "max_depth"),
        (MitsubaOptions(integrator="volpath"), "integrator"),
        (MitsubaOptions(material="glass"), "material"),
        (MitsubaOptions(sampler="sobol"), "sampler"),
        (MitsubaOptions(integrator="direct", max_depth=5), "direct light only"),
        (MitsubaOptions(roughness=0.0), "roughness"),
        (MitsubaOptions(specular_level=1.5), "specular_level"),
        (MitsubaOptions(albedo_scale=-1.0), "albedo_scale"),
        (MitsubaOptions(material="specular", metalness=1.5), "metalness"),
        (MitsubaOptions(material="roughplastic", metalness=1.0), "roughplastic.*dielectric"),
        (MitsubaOptions(material="roughplastic", specular_level=0.0), "needs a coating"),
        (MitsubaOptions(shadows=False), "recon's own Renderer"),
        (
            MitsubaOptions(
                area_lights=(
                    AreaLight(
                        torch.zeros(3),
                        torch.tensor([0.0, 1.0, 0.0]),
                        torch.zeros(3),
                        torch.tensor([0.0, 0.0, 1.0]),
                        torch.ones(3),
                    ),
                )
            ),
            r"area_lights\[0\]: expected a nonzero normal and non-parallel nonzero edges",
        ),
        (MitsubaOptions(area_lights=("lamp",)), r"area_lights\[0\]: expected an area light"),
        (
            MitsubaOptions(suns=(DiskSun((0, 1, 0), 0.0, (1, 1, 1)),)),
            r"suns\[0\].angular_diameter_deg",
        ),
    ],
)
def test_bad_options_are_rejected(options: MitsubaOptions, message: str) -> None:
    with pytest.raises(ReconError, match=message):
        options.validate()


def test_non_square_pixels_are_rejected(mitsuba_module) -> None:
    intrinsics = intrinsics_from_fov(40, (16, 16), fov_y_deg=30)
    cameras = Cameras(look_at(torch.tensor([[0.0, 0.0, 3.0]])), intrinsics, (16, 16))
    with pytest.raises(ReconError, match="square pixels"):
        render_mitsuba(make_shape("sphere", resolution=8), cameras, Lighting.constant(1.0))


def test_negative_sh_radiance_warns() -> None:
    sh = torch.zeros(9, 3)
    sh[0] = 0.1 * math.sqrt(4 * math.pi)
    sh[1] = 0.5 * _GRADIENT_TO_SH  # radiance 0.1 + 0.5 y < 0 below the horizon
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = environment_bitmap(sh)
    assert any("negative radiance" in str(warning.message) for warning in caught)
    assert float(image.min()) == 0.0


# --------------------------------------------------------------------------------------------
# Glossy materials: a GGX conductor (principled metallic) and roughplastic
# --------------------------------------------------------------------------------------------


def test_plastic_ior_has_the_specular_level_reflectance() -> None:
    assert plastic_ior(0.5) == pytest.approx(1.5)
    for level in (0.1, 0.5, 1.0):
        ior = plastic_ior(level)
        assert ((ior - 1) / (ior + 1)) ** 2 == pytest.approx(0.08 * level)


def _glossy_sphere_views(mitsuba_module, options: MitsubaOptions, base: float):
    """A uniform sphere (albedo base) under a sky with one bright window, 2 views of 32 px:
    Mitsuba's render, its alpha, and recon's split-sum render of the same material."""
    from data_synth.environment import equirect_directions, project_to_sh
    from recon.render.environment import prefilter_environment

    directions, _ = equirect_directions(32, 64)
    window = torch.nn.functional.normalize(torch.tensor([0.3, 0.6, 0.75]), dim=0)
    glow = 8 * torch.exp((directions @ window - 1) / 0.03)
    environment = (0.15 + 0.1 * directions[..., 1:2] + glow[..., None]).expand(32, 64, 3)
    environment = environment.contiguous()
    world = WorldLighting(
        lighting=Lighting(sh_coefficients=project_to_sh(environment)), environment_map=environment
    )
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    eyes = torch.tensor([[0.0, 0.3, 3.0], [2.5, 0.5, 1.5]])
    cameras = Cameras(look_at(eyes), intrinsics_from_fov(30.0, (32, 32)).expand(2, 3, 3), (32, 32))
    # A uniform texture (roughplastic needs a texture with a mean: not vertex colours).
    mesh = Mesh(
        verts,
        faces,
        uvs=torch.full((1, 2), 0.5),
        uv_faces=torch.zeros_like(faces),
        texture=torch.full((4, 4, 3), base),
    )
    traced, alpha = render_mitsuba(mesh, cameras, world, options)
    material = torch.tensor([base] * 3 + [options.roughness, options.metalness]).expand(4, 4, 5)
    renderer = Renderer(texture_filter="linear")
    with torch.no_grad():
        buffers = renderer.surface_buffers(mesh, cameras)
        split_sum = renderer.shade_pbr(
            buffers, cameras.centers(), material.contiguous(), prefilter_environment(environment, 8)
        ).color
    inside = (alpha[..., 0] > 0.999) & (buffers.fragments.mask[..., 0] > 0)
    return traced, split_sum, inside


def test_ggx_conductor_agrees_with_recon_split_sum(mitsuba_module) -> None:
    # metalness 1: no diffuse, a GGX lobe with Schlick F0 = the albedo: recon's pbr model.
    options = MitsubaOptions(spp=64, material="specular", roughness=0.3, metalness=1.0)
    traced, split_sum, inside = _glossy_sphere_views(mitsuba_module, options, base=0.8)
    traced_mean = float(traced[inside].mean())
    assert abs(float(split_sum[inside].mean()) / traced_mean - 1) < 0.05
    relative = (split_sum - traced).abs().mean(-1)[inside].mean() / traced[inside].mean()
    assert float(relative) < 0.12
    # A conductor has no diffuse floor: dark away from the window (a dielectric of albedo 0.8
    # would stay above about 0.25 everywhere under this sky).
    assert float(traced.mean(-1)[inside].quantile(0.2)) < 0.12


def test_roughplastic_adds_a_highlight_over_a_darkened_diffuse(mitsuba_module) -> None:
    diffuse, _, inside = _glossy_sphere_views(
        mitsuba_module, MitsubaOptions(spp=64, material="diffuse"), base=0.5
    )
    plastic, split_sum, _ = _glossy_sphere_views(
        mitsuba_module, MitsubaOptions(spp=64, material="roughplastic", roughness=0.2), base=0.5
    )
    luminance_diffuse, luminance_plastic = diffuse.mean(-1)[inside], plastic.mean(-1)[inside]
    # The highlight: the brightest pixels are far brighter than a Lambertian surface's.
    assert float(luminance_plastic.max()) > 1.5 * float(luminance_diffuse.max())
    # Away from it the coating's transmittance darkens the diffuse base.
    assert float(luminance_plastic.median()) < float(luminance_diffuse.median())
    # recon's split-sum (principled-like) model is within 15 % of it in the mean.
    assert abs(float(split_sum[inside].mean()) / float(plastic[inside].mean()) - 1) < 0.15
