"""Every config in configs/ loads and validates; the example scenes say what their names promise.

Loading never reads a mesh file, so configs that point into ../shared/meshes are checked for
structure even where that folder is absent; building their scene needs it (skipped without).
Relative paths in configs are opened relative to the current directory (recon.io.meshes.load_mesh
takes them as they are), so the example configs are written for running from the repo root.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from data_synth.effects.base import LIGHT_TRANSPORT
from data_synth.effects.light_transport import make_light_transport_effect
from data_synth.effects.registry import make_world_effect
from data_synth.scene import build_lighting, build_mesh
from recon.config import load_config
from recon.config.run_config import RunConfig

REPO_ROOT = Path(__file__).resolve().parents[2]
# Run configs; configs/sweeps/ holds sweep files (another schema, checked in tests/sweep/).
CONFIGS = sorted(
    path
    for path in (REPO_ROOT / "configs").rglob("*.yaml")
    if "sweeps" not in path.relative_to(REPO_ROOT / "configs").parts
)
SCENES = REPO_ROOT / "configs" / "scenes"
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"
EXAMPLE_SCENES = (
    "spot",
    "bob",
    "torus_sky",
    "studio_box",
    "blind_camera_effects",
    "relight",
)


def _load(path: Path) -> RunConfig:
    return load_config(path, RunConfig)


def _mesh_configs() -> list[Path]:
    """Configs with a mesh_path (one that fails to load is reported by the loading test)."""
    found = []
    for path in CONFIGS:
        try:
            if _load(path).scene.shape.mesh_path is not None:
                found.append(path)
        except Exception:
            continue
    return found


def test_the_example_scenes_exist():
    assert len(CONFIGS) >= len(EXAMPLE_SCENES) + 1
    for name in EXAMPLE_SCENES:
        assert (SCENES / f"{name}.yaml").is_file(), name


@pytest.mark.parametrize("path", CONFIGS, ids=lambda path: str(path.relative_to(REPO_ROOT)))
def test_every_config_loads_and_validates(path):
    config = _load(path)
    assert config.name and config.seed >= 0
    shape = config.scene.shape
    assert (shape.procedural is None) != (shape.mesh_path is None)
    capture = config.capture
    assert capture.train_views >= 1
    if capture.backend == "own":
        # recon's rasterizer cannot render light transport: such a config would fail at run time.
        assert not [effect.name for effect in capture.effects if effect.name in LIGHT_TRANSPORT]
    for effect in capture.effects:  # every parameter known and in range
        if effect.name in LIGHT_TRANSPORT:
            make_light_transport_effect(effect.name, effect.parameters)
        else:
            make_world_effect(effect.name, effect.parameters)


@pytest.mark.parametrize("path", _mesh_configs(), ids=lambda path: str(path.relative_to(REPO_ROOT)))
def test_mesh_paths_point_into_shared_from_the_repo_root(path):
    """mesh_path / texture_path are relative to the repo root (the current directory when run
    as README shows), and name files of ../shared/meshes."""
    shape = _load(path).scene.shape
    for value in (shape.mesh_path, shape.texture_path):
        if value is None:
            continue
        assert not Path(value).is_absolute(), value
        resolved = (REPO_ROOT / value).resolve()
        assert resolved.parent == SHARED_MESHES.resolve(), value
        if SHARED_MESHES.is_dir():
            assert resolved.is_file(), value


def test_scene_configs_have_their_features():
    spot = _load(SCENES / "spot.yaml")
    assert spot.scene.shape.mesh_path.endswith("spot_triangulated.obj")
    assert spot.scene.shape.texture_path.endswith("spot_texture.png")
    assert spot.scene.material.albedo == "file"
    bob = _load(SCENES / "bob.yaml")
    assert bob.scene.shape.mesh_path.endswith("bob_tri.obj")
    assert bob.scene.material.albedo == "file"

    sky = _load(SCENES / "torus_sky.yaml")
    assert sky.scene.shape.procedural == "torus"
    assert sky.scene.lighting.environment.kind == "sky"

    studio = _load(SCENES / "studio_box.yaml")
    assert studio.scene.shape.procedural == "rounded_box"
    assert studio.scene.lighting.environment.kind == "studio"
    assert len(studio.scene.lighting.areas) >= 1

    blind = _load(SCENES / "blind_camera_effects.yaml")
    names = [effect.name for effect in blind.capture.effects]
    assert len(names) >= 3 and not set(names) & set(LIGHT_TRANSPORT)
    assert {"exposure", "vignetting", "noise"} <= set(names)

    relight = _load(SCENES / "relight.yaml")
    assert 0 < relight.capture.relight.views <= relight.capture.test_views
    assert relight.capture.relight.lighting != relight.scene.lighting


@pytest.mark.parametrize("name", ["torus_sky", "studio_box", "blind_camera_effects", "relight"])
def test_procedural_scenes_build(name):
    config = _load(SCENES / f"{name}.yaml")
    mesh = build_mesh(config.scene)
    assert mesh.faces.shape[0] > 100
    assert mesh.texture is not None or mesh.vertex_colors is not None
    world = build_lighting(config.scene.lighting)
    environment = config.scene.lighting.environment.kind
    assert (world.environment_map is not None) == (environment != "none")
    assert len(world.area_lights) == len(config.scene.lighting.areas)


@pytest.mark.shared
@pytest.mark.parametrize("name", ["spot", "bob"])
def test_mesh_scenes_build_from_the_repo_root(name, shared_meshes, monkeypatch):
    monkeypatch.chdir(REPO_ROOT)  # relative paths are opened relative to the current directory
    config = _load(SCENES / f"{name}.yaml")
    mesh = build_mesh(config.scene)
    assert mesh.texture is not None and mesh.uvs is not None
    assert float(mesh.verts.norm(dim=-1).max()) == pytest.approx(0.9, abs=1e-4)
