"""The synth stage end to end, through `recon synth` (recon.cli.main, in-process).

Tiny captures (32 px, 2-4 views) of a sphere, whose geometry is known in closed form: the relight
split, depth and normal buffers, a textured mesh file, every light type, the camera effect chain
and its recorded truth, the automatic switch to Mitsuba for light transport, the no-overwrite
rule, and a round trip of the written dataset through read_nerf_synthetic.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
import torch
import yaml

from data_synth.effects.registry import make_world_effect
from data_synth.effects.world_effect import pixel_grid
from data_synth.rigs import make_cameras
from data_synth.scene import build_lighting, build_mesh
from data_synth.stage import render_views_own
from recon.cli import main
from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.io.datasets import read_nerf_synthetic
from recon.io.images import read_exr_channels, read_image

REPO_ROOT = Path(__file__).resolve().parents[2]
SIZE = 32
DISTANCE = 3.0
RADIUS = 0.9  # data_synth.shapes.sphere's default radius

BASE = {
    "name": "tiny",
    "seed": 0,
    "device": "cpu",
    "stages": ["synth"],
    "scene": {
        "shape": {"procedural": "sphere", "resolution": 24},
        "material": {"albedo": "checker", "texture_size": 32},
        "lighting": {
            "ambient": [0.5, 0.5, 0.5],
            "sky_gradient": 0.0,
            "suns": [{"direction": [0.4, 0.8, 0.5], "irradiance": [1.5, 1.5, 1.5]}],
        },
    },
    "capture": {
        "cameras": {
            "rig": "fibonacci",
            "distance": DISTANCE,
            "fov_deg": 40.0,
            "resolution": [SIZE, SIZE],
        },
        "train_views": 2,
        "val_views": 0,
        "test_views": 0,
        "mitsuba_spp": 16,
        "contact_sheet": False,
    },
}


def _merge(base: dict, changes: dict) -> dict:
    merged = copy.deepcopy(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def _write_config(tmp_path: Path, name: str, changes: dict | None = None) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(_merge(BASE, changes or {})))
    return path


def synth(tmp_path: Path, name: str, changes: dict | None = None, *extra: str) -> Path:
    """`recon synth` of BASE updated with changes into tmp_path/name; returns the run folder."""
    out = tmp_path / name
    config = _write_config(tmp_path, name, changes)
    assert main(["synth", str(config), "--out", str(out), "--device", "cpu", *extra]) == 0
    return out


def read_split(out: Path, split: str = "train", exr: bool = True):
    """The split's linear premultiplied images (EXR, or the PNGs) and cameras."""
    return read_nerf_synthetic(out / "dataset", split, background=None, prefer_exr=exr)


def effects_record(out: Path) -> dict:
    return json.loads((out / "ground_truth" / "effects.json").read_text())


def read_normals(out: Path, split: str, count: int) -> torch.Tensor:
    return torch.stack(
        [read_exr_channels(out / "dataset" / split / f"r_{k}_normal.exr")[0] for k in range(count)]
    )


def mitsuba_or_skip(backend: str) -> None:
    if backend == "mitsuba":
        pytest.importorskip("mitsuba")


# ------------------------------------------------------------------------------------------------
# (a) relight split


def test_relight_split_reuses_the_test_cameras_under_other_light(tmp_path):
    relight_light = {
        "ambient": [0.1, 0.1, 0.1],
        "sky_gradient": 0.0,
        "suns": [{"direction": [-0.6, -0.3, 0.7], "irradiance": [2.0, 1.0, 0.5]}],
    }
    out = synth(
        tmp_path,
        "relight",
        {
            "capture": {
                "train_views": 1,
                "test_views": 3,
                "relight": {"views": 2, "lighting": relight_light},
            }
        },
    )
    dataset = out / "dataset"
    test_json = json.loads((dataset / "transforms_test.json").read_text())
    relight_json = json.loads((dataset / "transforms_relight.json").read_text())
    assert len(relight_json["frames"]) == 2
    for relit, tested in zip(relight_json["frames"], test_json["frames"][:2], strict=True):
        assert relit["transform_matrix"] == tested["transform_matrix"]
    test, relit = read_split(out, "test"), read_split(out, "relight")
    assert torch.equal(relit.cameras.world_to_cam, test.cameras.world_to_cam[:2])
    # The relight light is written beside the views (a known capture condition).
    from recon.io.datasets import RELIGHT_LIGHTING
    from recon.render.shading import Lighting

    light = Lighting.from_json(json.loads((dataset / RELIGHT_LIGHTING).read_text()))
    assert len(light.directional) == 1
    assert light.directional[0].irradiance.tolist() == [2.0, 1.0, 0.5]
    assert not (dataset / "lighting.json").exists()
    assert torch.equal(relit.masks, test.masks[:2])  # same geometry, same coverage
    difference = (relit.images - test.images[:2]).abs().mean(dim=(1, 2, 3))
    assert (difference > 0.02).all(), difference
    assert "relight" in effects_record(out)["realised"]


# ------------------------------------------------------------------------------------------------
# (b) depth and normal buffers


def test_depth_and_normal_exr_match_the_sphere(tmp_path):
    out = synth(tmp_path, "buffers", {"capture": {"write_depth_normals": True}})
    captures = read_split(out)
    for index in range(2):
        folder = out / "dataset" / "train"
        depth, names = read_exr_channels(folder / f"r_{index}_depth.exr")
        normal, _ = read_exr_channels(folder / f"r_{index}_normal.exr")
        assert names == ["Z"] and depth.shape == (SIZE, SIZE, 1) and normal.shape[-1] == 3
        centre = SIZE // 2
        # The ray through the centre meets the sphere head on: depth = distance - radius.
        assert float(depth[centre, centre, 0]) == pytest.approx(DISTANCE - RADIUS, abs=0.01)
        assert float(depth[0, 0, 0]) == 0.0  # background
        covered = normal.norm(dim=-1) > 0
        assert covered.sum() > 100
        lengths = normal[covered].norm(dim=-1)
        assert torch.allclose(lengths, torch.ones_like(lengths), atol=1e-4)
        # The centre normal points back at the camera (world space).
        camera_centre = captures.cameras.centers()[index]
        towards_camera = camera_centre / camera_centre.norm()
        assert float(normal[centre, centre] @ towards_camera) > 0.99
        # Buffers and coverage agree away from the antialiased silhouette.
        mask = captures.masks[index, ..., 0]
        assert bool(covered[mask > 0.99].all()) and not bool(covered[mask == 0].any())


# ------------------------------------------------------------------------------------------------
# (c) a mesh file with its texture


@pytest.mark.shared
@pytest.mark.parametrize("scene", ["spot", "bob"])
def test_mesh_file_scene_renders_with_its_texture(scene, tmp_path, shared_meshes, monkeypatch):
    """The example configs' relative ../shared paths are opened from the repo root."""
    monkeypatch.chdir(REPO_ROOT)
    out = tmp_path / scene
    arguments = [
        "synth",
        str(REPO_ROOT / "configs" / "scenes" / f"{scene}.yaml"),
        "--out",
        str(out),
        "--device",
        "cpu",
        "--set",
        f"capture.cameras.resolution=[{SIZE}, {SIZE}]",
        "--set",
        "capture.train_views=2",
        "--set",
        "capture.val_views=0",
        "--set",
        "capture.test_views=0",
        "--set",
        "capture.contact_sheet=false",
    ]
    assert main(arguments) == 0
    captures = read_split(out)
    covered = captures.masks[..., 0] > 0.99
    assert covered.sum() > 50
    colour = (captures.images / captures.masks.clamp_min(1e-6))[covered].mean(0)
    # White light on a grey (0.5) default albedo would give equal channels: these textures
    # are warm (spot: pinkish white and brown; bob: yellow), red well above blue.
    assert float(colour[0]) > 1.15 * float(colour[2]), colour
    assert float((colour - 0.5).abs().max()) > 0.05, colour


# ------------------------------------------------------------------------------------------------
# (d) every light type


DARK = {"ambient": [0.3, 0.3, 0.3], "sky_gradient": 0.0, "suns": []}
LIGHT_POSITION = [2.5, 0.0, 0.0]


def _facing(normals: torch.Tensor, position: list[float]) -> torch.Tensor:
    """cos of the angle between each surface normal and the direction to a light [B, H, W]."""
    points = normals * RADIUS
    to_light = torch.nn.functional.normalize(torch.tensor(position) - points, dim=-1)
    return (normals * to_light).sum(-1)


@pytest.mark.parametrize("backend", ["own", "mitsuba"])
def test_point_and_area_lights_brighten_the_side_facing_them(backend, tmp_path):
    mitsuba_or_skip(backend)
    capture = {"backend": backend, "write_depth_normals": True}
    base = synth(tmp_path, "base", {"scene": {"lighting": DARK}, "capture": capture})
    normals = read_normals(base, "train", 2)
    dark = read_split(base)
    lights = {
        "points": [{"position": LIGHT_POSITION, "intensity": [6.0, 6.0, 6.0]}],
        "areas": [{"center": LIGHT_POSITION, "size": [0.5, 0.5], "radiance": [24.0, 24.0, 24.0]}],
    }
    interior = dark.masks[..., 0] > 0.99
    cosine = _facing(normals, LIGHT_POSITION)
    toward, away = interior & (cosine > 0.3), interior & (cosine < -0.3)
    assert toward.sum() > 20 and away.sum() > 20
    noise = 0.0 if backend == "own" else 0.02
    for kind, entries in lights.items():
        lit = read_split(
            synth(
                tmp_path, kind, {"scene": {"lighting": {**DARK, kind: entries}}, "capture": capture}
            )
        )
        assert torch.equal(lit.masks, dark.masks)
        gain = (lit.images - dark.images).mean(-1)
        assert float(gain[toward].mean()) > 0.05, kind
        assert abs(float(gain[away].mean())) <= noise + 1e-6, kind
        # Brighter the more squarely a pixel faces the light.
        facing_more = interior & (cosine > 0.7)
        assert float(gain[facing_more].mean()) > float(gain[toward].mean()), kind


@pytest.mark.parametrize("backend", ["own", "mitsuba"])
def test_sky_environment_lights_the_top_more_than_the_bottom(backend, tmp_path):
    mitsuba_or_skip(backend)
    capture = {"backend": backend, "write_depth_normals": True}
    uniform = {"ambient": [0.5, 0.5, 0.5], "sky_gradient": 0.0, "suns": []}
    sky = {
        "ambient": [0.0, 0.0, 0.0],
        "sky_gradient": 0.0,
        "suns": [],
        "environment": {"kind": "sky", "sun_irradiance": 0.0, "resolution": [32, 64]},
    }
    base = synth(tmp_path, "uniform", {"scene": {"lighting": uniform}, "capture": capture})
    under_sky = read_split(synth(tmp_path, "sky", {"scene": {"lighting": sky}, "capture": capture}))
    flat = read_split(base)
    normals = read_normals(base, "train", 2)
    interior = flat.masks[..., 0] > 0.99
    # The ratio to a uniform environment cancels the albedo pattern.
    ratio = (under_sky.images.mean(-1) / flat.images.mean(-1).clamp_min(1e-4))[interior]
    up = normals[..., 1][interior]
    top, bottom = ratio[up > 0.5], ratio[up < -0.5]
    assert top.numel() > 20 and bottom.numel() > 20
    assert float(top.mean()) > 1.5 * float(bottom.mean())
    # The full map goes to the ground truth (the path tracer renders it; recon shades its SH).
    assert (tmp_path / "sky" / "ground_truth" / "environment.exr").is_file()


# ------------------------------------------------------------------------------------------------
# (e) camera effect chain and its recorded truth


def test_effect_chain_is_recorded_and_applied(tmp_path):
    views = 3
    capture = {"train_views": views, "write_depth_normals": False}
    chain = [
        {"name": "exposure", "parameters": {"spread_stops": 0.5}},
        {"name": "vignetting", "parameters": {"strength": 0.4}},
        {"name": "noise", "parameters": {"full_well_photons": 1000.0, "read_noise": 0.003}},
    ]
    clean_out = synth(tmp_path, "clean", {"capture": capture})
    exposed_out = synth(tmp_path, "exposed", {"capture": {**capture, "effects": chain[:1]}})
    chain_out = synth(tmp_path, "chain", {"capture": {**capture, "effects": chain}})
    clean, exposed, noisy = (read_split(out) for out in (clean_out, exposed_out, chain_out))
    assert torch.equal(clean.cameras.world_to_cam, noisy.cameras.world_to_cam)
    assert torch.equal(clean.masks, noisy.masks)  # none of these changes coverage

    # Recorded in physical order with per-view realised values.
    record = effects_record(chain_out)
    assert record["effects"] == ["exposure", "vignetting", "noise"] and not record["withheld"]
    realised = {item["name"]: item["parameters"] for item in record["realised"]["train"]}
    assert [item["name"] for item in record["realised"]["train"]] == [
        "vignetting",
        "exposure",
        "noise",
    ]
    ratios = torch.tensor(realised["exposure"]["ratios"], dtype=torch.float64)
    assert ratios.shape == (views,) and len(set(ratios.tolist())) == views
    assert len(realised["vignetting"]["corner_falloff"]) == views
    assert all(0 < value < 1 for value in realised["vignetting"]["corner_falloff"])
    assert realised["noise"]["a"] == pytest.approx(1e-3) and realised["noise"]["b"] > 0
    # An effect's draws do not depend on the others switched on.
    alone = effects_record(exposed_out)["realised"]["train"][0]["parameters"]
    assert alone["ratios"] == realised["exposure"]["ratios"]

    # Exposure alone scales each view's linear radiance by its realised ratio, exactly.
    interior = clean.masks[..., 0] > 0.99
    for view in range(views):
        measured = exposed.images[view][interior[view]].double().mean() / (
            clean.images[view][interior[view]].double().mean()
        )
        assert float(measured) == pytest.approx(float(ratios[view]), rel=0.01)

    # The chain: the clean image x ratio x vignetting falloff, plus zero-mean sensor noise of
    # variance a * I + b.
    vignetting = make_world_effect("vignetting", chain[1]["parameters"])
    u, v = pixel_grid(SIZE, SIZE, torch.empty(0, dtype=torch.float64))
    natural, mechanical = vignetting.falloff(clean.cameras, u, v)
    expected = (
        clean.images.double() * ratios[:, None, None, None] * (natural * mechanical)[..., None]
    )
    residual = (noisy.images.double() - expected)[interior]
    signal = expected[interior]
    assert float(residual.mean()) == pytest.approx(0.0, abs=0.01)
    predicted_std = math.sqrt(float((signal * 1e-3 + 0.003**2).mean()))
    assert float(residual.std()) == pytest.approx(predicted_std, rel=0.1)
    assert float((noisy.images - exposed.images).abs().mean()) > 1e-3


# ------------------------------------------------------------------------------------------------
# (f) light transport selects Mitsuba; the own backend refuses it


def test_light_transport_effect_switches_to_mitsuba(tmp_path, monkeypatch):
    pytest.importorskip("mitsuba")
    import data_synth.mitsuba_backend as backend

    calls = []
    original = backend.render_mitsuba

    def spy(mesh, cameras, lighting, options=None):
        calls.append(options)
        return original(mesh, cameras, lighting, options)

    monkeypatch.setattr(backend, "render_mitsuba", spy)
    effects = [{"name": "specular", "parameters": {"roughness": 0.2}}]
    out = synth(tmp_path, "specular", {"capture": {"effects": effects, "mitsuba_spp": 8}})
    assert len(calls) == 1 and calls[0].material == "specular" and calls[0].spp == 8
    assert calls[0].roughness == pytest.approx(0.2)
    captures = read_split(out)
    assert captures.images.shape == (2, SIZE, SIZE, 3) and float(captures.images.max()) > 0.05
    assert float(captures.masks.mean()) > 0.1
    record = effects_record(out)
    assert record["effects"] == ["specular"] and "specular" in record["light_transport"]


def test_own_backend_refuses_light_transport(tmp_path, capsys):
    config = _write_config(
        tmp_path,
        "own",
        {"capture": {"backend": "own", "effects": [{"name": "shadows"}]}},
    )
    code = main(["synth", str(config), "--out", str(tmp_path / "own"), "--device", "cpu"])
    assert code == 2
    error = capsys.readouterr().err
    assert "'own'" in error and "shadows" in error


# ------------------------------------------------------------------------------------------------
# (g) never overwrite


def test_second_synth_into_the_same_folder_needs_force(tmp_path, capsys):
    config = _write_config(tmp_path, "again")
    out = tmp_path / "again"
    arguments = ["synth", str(config), "--out", str(out), "--device", "cpu"]
    assert main(arguments) == 0
    first = (out / "dataset" / "transforms_train.json").read_bytes()
    marker = out / "dataset" / "train" / "r_0.png"
    stamp = marker.stat().st_mtime_ns
    assert main(arguments) == 2
    assert "already exists" in capsys.readouterr().err
    assert marker.stat().st_mtime_ns == stamp
    assert (out / "dataset" / "transforms_train.json").read_bytes() == first
    assert main([*arguments, "--force"]) == 0


# ------------------------------------------------------------------------------------------------
# (h) round trip through read_nerf_synthetic


def test_dataset_round_trips_through_the_reader(tmp_path):
    changes = {"capture": {"train_views": 3, "val_views": 1, "test_views": 2}}
    out = synth(tmp_path, "roundtrip", changes)
    config = load_config(tmp_path / "roundtrip.yaml", RunConfig)
    mesh = build_mesh(config.scene)
    world = build_lighting(config.scene.lighting)
    generator = torch.Generator().manual_seed(config.seed)
    for offset, (split, count) in enumerate((("train", 3), ("val", 1), ("test", 2))):
        cameras = make_cameras(config.capture.cameras, count, generator, offset=offset)
        from_exr, from_png = read_split(out, split), read_split(out, split, exr=False)
        for captures in (from_exr, from_png):
            assert captures.cameras.image_size == (SIZE, SIZE)
            assert torch.allclose(
                captures.cameras.world_to_cam, cameras.world_to_cam, atol=1e-6, rtol=0
            )
            assert torch.allclose(captures.cameras.intrinsics, cameras.intrinsics, atol=1e-6)
            assert captures.cameras.near == pytest.approx(cameras.near)
            assert captures.cameras.far == pytest.approx(cameras.far)
        rendered = render_views_own(mesh, cameras, world, "reference")
        # EXR: float32, bit for bit what the renderer gave (no effects configured).
        assert torch.allclose(from_exr.images, rendered.colors, atol=1e-6, rtol=0)
        assert torch.allclose(from_exr.masks, rendered.alphas, atol=1e-6, rtol=0)
        # PNG: 8-bit sRGB straight colour and alpha; compare where nothing was clipped at 1.
        assert torch.allclose(from_png.masks, from_exr.masks, atol=0.5 / 255 + 1e-6)
        straight = from_exr.images / from_exr.masks.clamp_min(1e-6)
        unclipped = ((straight <= 1.0).all(-1, keepdim=True) & (from_exr.masks > 0)).expand_as(
            straight
        )
        difference = (from_png.images - from_exr.images)[unclipped].abs()
        assert float(difference.max()) < 0.008
    png = read_image(out / "dataset" / "train" / "r_0.png")
    assert png.shape == (SIZE, SIZE, 4)


def test_a_relight_split_moves_the_shadows_sun_to_its_own_light():
    # The shadows effect replaces the scene's suns by its disk sun; under the relight split's
    # light that sun must be the relight light's (the one lighting_relight.json tells the
    # diagnosis), or the "relight" views would be lit as the training views were.
    from data_synth.effects.light_transport import Shadows
    from data_synth.stage import relit_effects
    from recon.config.run_config import EffectConfig, LightingConfig, SunConfig

    shadows = EffectConfig(
        "shadows", {"elevation_deg": 40.0, "azimuth_deg": 10.0, "angular_diameter_deg": 6.0}
    )
    exposure = EffectConfig("exposure", {"spread": 0.2})
    lighting = LightingConfig(suns=[SunConfig(direction=[-0.7, 0.5, -0.3], irradiance=[3.0] * 3)])
    relit = relit_effects([shadows, exposure], lighting)
    assert relit[1] == exposure
    assert relit[0].parameters["angular_diameter_deg"] == 6.0
    assert relit[0].parameters["irradiance"] == 3.0
    direction = torch.tensor(Shadows(relit[0].parameters).direction_to_light())
    expected = torch.nn.functional.normalize(torch.tensor([-0.7, 0.5, -0.3]), dim=0)
    torch.testing.assert_close(direction, expected, atol=1e-6, rtol=0)
    assert relit_effects([shadows], LightingConfig(suns=[]))[0] == shadows


# ------------------------------------------------------------------------------------------------
# (h) a glossy world with a spatially varying roughness


def test_a_roughness_texture_is_rendered_by_both_backends_and_written_as_truth(tmp_path):
    """scene.material.roughness_texture with the specular effect: recon's split-sum shading
    ('own') and Mitsuba's principled BSDF render the same glossy sphere, and the reference mesh
    carries the true roughness map (map_Pr) for a benchmark to compare a fit with."""
    pytest.importorskip("mitsuba")
    from data_synth.material import roughness_pattern
    from recon.config.run_config import MaterialConfig
    from recon.io.meshes import load_material_maps

    material = {
        "albedo": "checker",
        "texture_size": 32,
        "roughness_texture": "stripes",
        "roughness_range": [0.1, 0.6],
    }
    sky = {
        "ambient": [0.05, 0.05, 0.05],
        "sky_gradient": 0.0,
        "suns": [],
        "environment": {"kind": "studio", "resolution": [32, 64]},
    }
    images = {}
    for backend in ("own", "mitsuba"):
        changes = {
            "scene": {"material": material, "lighting": sky},
            "capture": {
                "backend": backend,
                "mitsuba_spp": 128,
                "effects": [{"name": "specular", "parameters": {"specular_level": 0.5}}],
            },
        }
        out = synth(tmp_path, backend, changes)
        maps = load_material_maps(out / "ground_truth" / "reference.obj")
        expected = roughness_pattern(MaterialConfig(**material), (32, 32))
        assert maps is not None and maps.shape == (32, 32, 2)
        torch.testing.assert_close(maps[..., 0], expected, atol=0.5 / 255 + 1e-6, rtol=0)
        assert float(maps[..., 1].abs().max()) == 0.0  # a dielectric
        images[backend] = read_split(out)
    own, traced = images["own"], images["mitsuba"]
    inside = (own.masks[..., 0] > 0.99) & (traced.masks[..., 0] > 0.99)
    assert inside.sum() > 200
    # The same glossy world in both: the split-sum model against the path tracer (measured
    # 8.8 % mean absolute difference relative to the mean at 128 spp; 14 % at 32 spp: noise).
    difference = (own.images - traced.images).abs().mean(-1)[inside].mean()
    assert float(difference / traced.images.mean(-1)[inside].mean()) < 0.13
