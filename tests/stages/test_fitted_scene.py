"""The fitted scene's files in a run folder: a `pbr` fit's mesh, maps, environment and light
written and read back (recon.stages.fitted_scene); the fitted effects record read back."""

from __future__ import annotations

import json

import pytest
import torch

from recon.errors import ReconError
from recon.io.images import read_exr
from recon.io.meshes import load_material_maps
from recon.io.run_folder import RunPaths
from recon.optimize.material_stage import PbrTextureResult, light_from_environment
from recon.render.environment import latlong_directions
from recon.render.shading import DirectionalLight
from recon.stages.fitted_scene import load_fitted_effects, load_pbr_fit, write_pbr_fit
from tests.material_scenes import textured_quad


def test_write_pbr_fit_writes_mesh_maps_environment_and_light(tmp_path):
    mesh, maps = textured_quad()
    environment = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(1))
    result = PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4)
    paths = RunPaths(tmp_path)
    summary = write_pbr_fit(paths, result)
    assert summary["material"] == "pbr" and summary["faces"] == 2
    torch.testing.assert_close(read_exr(paths.fitted_environment), environment)
    record = json.loads(paths.fitted_light.read_text())
    assert record["material"] == "pbr" and record["environment_file"] == "environment.exr"
    assert len(record["sh_coefficients"]) == 9
    assert load_material_maps(paths.fitted_mesh) is not None
    assert load_material_maps(paths.fitted_glb) is not None


def test_a_pbr_run_with_its_environment_missing_is_named(tmp_path):
    mesh, maps = textured_quad()
    environment = torch.ones(4, 8, 3)
    paths = RunPaths(tmp_path)
    write_pbr_fit(
        paths,
        PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4),
    )
    loaded = load_pbr_fit(paths)
    torch.testing.assert_close(loaded.environment, environment)
    assert loaded.prefilter_levels == 4 and loaded.material.shape == (8, 8, 2)
    (paths.fitted_environment).unlink()
    with pytest.raises(ReconError, match=r"light.json: names the pbr material, but .*environment"):
        load_pbr_fit(paths)


def test_a_camera_frame_environment_keeps_its_frame(tmp_path):
    mesh, maps = textured_quad()
    environment = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(2))
    light = light_from_environment(environment, "camera")
    result = PbrTextureResult(mesh, maps, environment, light, 0.5, 4, light_frame="camera")
    paths = RunPaths(tmp_path)
    write_pbr_fit(paths, result)
    assert json.loads(paths.fitted_light.read_text())["frame"] == "camera"
    loaded = load_pbr_fit(paths)
    assert loaded.light_frame == "camera" and loaded.light.frame == "camera"


def test_a_normal_map_is_written_and_read_back(tmp_path):
    mesh, maps = textured_quad()
    normal = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, 1.0]), dim=0)
    maps = torch.cat([maps, normal.expand(8, 8, 3)], dim=-1)
    environment = torch.ones(4, 8, 3)
    result = PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4)
    paths = RunPaths(tmp_path)
    write_pbr_fit(paths, result)
    loaded = load_pbr_fit(paths)
    assert loaded.material.shape == (8, 8, 5)
    torch.testing.assert_close(loaded.material[..., 2:], maps[..., 2:], atol=1 / 255, rtol=0)
    assert loaded.material_texture().shape[-1] == 8


def test_a_normalised_fit_is_written_in_the_dataset_frame(tmp_path):
    from recon.optimize.normalize import SceneTransform

    mesh, maps = textured_quad()
    environment = torch.ones(4, 8, 3)
    result = PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4)
    transform = SceneTransform(scale=2.0, centre=[1.0, -2.0, 0.5], up=[0.0, 1.0, 0.0])
    paths = RunPaths(tmp_path)
    write_pbr_fit(paths, result, transform)
    loaded = load_pbr_fit(paths)
    torch.testing.assert_close(loaded.mesh.verts, transform.to_dataset(mesh.verts))
    assert load_material_maps(paths.normalized_mesh) is not None


def test_no_effects_file_means_no_effects_and_a_broken_one_is_named(tmp_path) -> None:
    paths = RunPaths(tmp_path)
    assert load_fitted_effects(paths, torch.device("cpu")) == []
    paths.fitted_effects.write_text("{not json")
    with pytest.raises(ReconError, match="effects.json"):
        load_fitted_effects(paths, torch.device("cpu"))


def test_a_fit_with_suns_writes_a_combined_environment_and_reads_back_the_plain_one(tmp_path):
    mesh, maps = textured_quad()
    environment = torch.full((8, 16, 3), 0.25)
    sun = DirectionalLight(torch.tensor([0.3, 0.8, -0.5]), torch.tensor([3.0, 2.5, 2.0]))
    result = PbrTextureResult(
        mesh, maps, environment, light_from_environment(environment), 0.5, 4, suns=[sun]
    )
    paths = RunPaths(tmp_path)
    write_pbr_fit(paths, result)
    combined = read_exr(paths.fitted_environment_with_suns)[..., :3]
    _, solid_angle = latlong_directions(8, 16)
    added = ((combined - environment) * solid_angle[..., None]).sum(dim=(0, 1))
    torch.testing.assert_close(added, sun.irradiance, rtol=1e-4, atol=1e-4)
    # The plain map is what the fit reads back: the suns come from light.json, not twice.
    loaded = load_pbr_fit(paths)
    torch.testing.assert_close(loaded.environment, environment)
    assert len(loaded.suns) == 1


def test_a_fit_without_suns_writes_no_combined_environment(tmp_path):
    mesh, maps = textured_quad()
    environment = torch.ones(4, 8, 3)
    paths = RunPaths(tmp_path)
    write_pbr_fit(
        paths,
        PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4),
    )
    assert not paths.fitted_environment_with_suns.exists()
