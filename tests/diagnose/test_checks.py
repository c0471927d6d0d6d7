"""The checks end to end: `recon diagnose` on a run whose held-out views show a glossy object
at constant exposure. The diffuse fit's per-view gains absorb the highlight, so the exposure
probe alone calls exposure significant; with the checks the verdict names view-dependent
reflectance (the base model's mismatch) and not exposure."""

from __future__ import annotations

import json
import shutil

from recon.camera import orbit_cameras
from recon.cli import main
from recon.diagnose.checks import CHECK_PRODUCERS
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.pixel_table import dominant_light_direction, view_directions
from recon.diagnose.producers import PRODUCERS
from recon.io.datasets import write_nerf_synthetic
from recon.io.meshes import load_mesh
from recon.io.run_folder import RunPaths
from recon.render.renderer import Renderer
from recon.stages.fitted_scene import load_fitted_light

VIEWS = 12


def glossy_test_split(run) -> None:
    """Replace the run's test split by VIEWS orbit views of its own fitted scene plus a white
    Blinn-Phong highlight toward the fitted light (constant exposure)."""
    paths = RunPaths(run)
    mesh = load_mesh(paths.fitted_mesh)
    lighting = load_fitted_light(paths, "cpu")
    cameras = orbit_cameras(VIEWS, (32, 32), distance=3.0, fov_x_deg=40, elevation_deg=25)
    output = Renderer(texture_filter="linear").render(mesh, cameras, lighting)
    data = build_diagnosis_data(output.color, output.alpha, output, cameras, lighting, mesh)
    light, _ = dominant_light_direction(data)
    _, to_camera = view_directions(data)
    halfway = to_camera + light
    halfway = halfway / halfway.norm(dim=-1, keepdim=True)
    normals = output.normals / output.normals.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    highlight = 0.6 * (normals * halfway).sum(-1).clamp_min(0) ** 3
    observed = (output.color + highlight[..., None] * output.alpha).clamp(0, 1)
    shutil.rmtree(paths.dataset / "test")
    write_nerf_synthetic(paths.dataset, "test", cameras, observed, output.alpha, force=True)


def test_a_glossy_object_at_constant_exposure_is_not_named_exposure(tiny_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    glossy_test_split(run)
    code = main(["diagnose", str(run), "--refit", "none", "--effects", "exposure,white_balance"])
    assert code == 0
    printed = capsys.readouterr().out
    diagnosis = json.loads((run / "diagnosis.json").read_text())
    candidates = {item["name"]: item for item in diagnosis["candidates"]}
    exposure = candidates["exposure"]
    kinds = {item["kind"]: item for item in exposure["evidence"]}
    # The probe alone would name it: its held-out reduction clears the allowance.
    assert kinds["probe"]["passed"]
    assert exposure["status"] == "vetoed" and not exposure["significant"]
    assert not kinds["specificity"]["passed"]
    assert kinds["specificity"]["details"]["instead"] == "view_dependent_reflectance"
    mismatch = candidates["view_dependent_reflectance"]
    assert mismatch["significant"] and mismatch["decided_by"] == "specificity"
    assert "exposure" not in diagnosis["verdict"]
    assert "view_dependent_reflectance" in diagnosis["verdict"]
    assert "view_dependent_reflectance" in printed


def test_the_checks_are_registered_producers():
    assert set(CHECK_PRODUCERS) <= set(PRODUCERS)
