"""The report's gap-diagnosis section: verdict, ranking with its evidence, and the refit, in both
report.md and report.html, from whatever diagnosis.json the run folder holds."""

from __future__ import annotations

import json

import torch

from recon.config.run_config import RunConfig
from recon.diagnose.records import Candidate, Evidence
from recon.io.run_folder import prepare_run_folder
from recon.stages.report import report_stage


def candidate(name, decided_by, probe, absorption=None, void=None, parameters=None) -> dict:
    """A candidate's diagnosis.json record: probe (reduction, low, high), absorption reduction."""
    result = Candidate(
        name,
        significant=bool(decided_by),
        status="significant" if decided_by else "not_significant",
        decided_by=decided_by,
        why=f"{name}: why",
        parameters=parameters or {},
    )
    reduction, low, high = probe
    details = {"reduction": reduction, "interval": [low, high]}
    result.add(Evidence("probe", name, low, 0.02, low > 0.02, "probe", details))
    if absorption is not None:
        details = {"reduction": absorption, "interval": [absorption - 0.01, absorption + 0.01]}
        if void:
            details["discounted_by"] = void
        result.add(
            Evidence(
                "absorption",
                name,
                absorption - 0.01,
                0.01,
                True,
                "absorption",
                details,
                void=f"void beside {void}" if void else "",
            )
        )
    return result.to_json()


def test_report_carries_the_diagnosis(tmp_path):
    paths = prepare_run_folder(tmp_path / "run")
    diagnosis = {
        "verdict": "significant unmodelled effects: vignetting",
        "candidates": [
            candidate(
                "vignetting",
                "absorption",
                probe=(0.035, 0.012, 0.06),
                absorption=0.104,
                parameters={"corner_falloff": 0.7, "radius_unit": "half image diagonal ..."},
            ),
            candidate("pose_error", "", probe=(0.05, -0.01, 0.09)),
            candidate(
                "lens_distortion",
                "",
                probe=(0.01, -0.02, 0.03),
                absorption=0.25,
                void="defocus_blur",
            ),
        ],
        "refits": [
            {
                "effects": ["vignetting"],
                "before_rmse": 0.0304,
                "after_rmse": 0.0251,
                "floor": 0.0077**2,
                "closed_fraction": 0.23,
                "relight_closed_fraction": 0.41,
                "parameters": {"vignetting": {"corner_falloff": 0.6543, "covered_radius": 0.57}},
            },
            {
                "effects": ["vignetting", "pose_error"],
                "before_rmse": 0.0251,
                "after_rmse": 0.0249,
                "floor": 0.0077**2,
                "closed_fraction": 0.01,
            },
        ],
        "figures": {},
    }
    paths.diagnosis.write_text(json.dumps(diagnosis))
    report_stage(RunConfig(), paths, torch.device("cpu"))
    markdown = paths.report_markdown.read_text()
    assert "Verdict: significant unmodelled effects: vignetting" in markdown
    assert (
        "| vignetting | absorption | 0.035 | [0.012, 0.060] | 0.104 |  | yes | vignetting: why |"
        in markdown
    )
    assert "| pose_error |  | 0.050 | [-0.010, 0.090] |  |  |  | pose_error: why |" in markdown
    # The recovered parameters: the refit's (training views) over the evidence's; explanations
    # stay in diagnosis.json.
    assert "| vignetting | refit | corner_falloff 0.654, covered_radius 0.57 |" in markdown
    # An absorption voided beside the conditioning effect says so instead of looking decisive.
    assert "| 0.250 (void beside defocus_blur) |  |  | lens_distortion: why |" in markdown
    assert "| vignetting | 0.0304 | 0.0251 | 0.0077 | 23 % | 41 % |" in markdown
    # Without a relight split the refit has no relight figures and the cell stays empty.
    assert "| vignetting + pose_error | 0.0251 | 0.0249 | 0.0077 | 1 % |  |" in markdown
    page = paths.report_html.read_text()
    assert "<h2>Gap diagnosis</h2>" in page
    assert "<td>absorption</td><td>0.035</td>" in page and "<td>23 %</td>" in page


def test_a_pbr_run_turns_with_its_material_and_shows_its_channels(tmp_path):
    """A `pbr` fit's turntable renders its material under its environment (a highlight the
    Lambertian stand-in cannot make), and both reports carry the material figure."""
    import numpy as np
    import trimesh
    from PIL import Image
    from scipy.ndimage import binary_erosion

    from recon.mesh.mesh import Mesh
    from recon.optimize.material_stage import PbrTextureResult, light_from_environment
    from recon.render.environment import latlong_directions
    from recon.stages.fitted_scene import write_pbr_fit

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    # A uniform material: every corner looks up the same texel.
    mesh = Mesh(
        torch.tensor(sphere.vertices, dtype=torch.float32),
        faces,
        uvs=torch.full((1, 2), 0.5),
        uv_faces=torch.zeros_like(faces),
        texture=torch.full((4, 4, 3), 0.3),
    )
    maps = torch.tensor([0.15, 0.0]).expand(4, 4, 2).contiguous()  # glossy dielectric
    directions, _ = latlong_directions(16, 32)
    window = torch.nn.functional.normalize(torch.tensor([0.3, 0.8, 0.5]), dim=0)
    environment = (0.2 + 60 * torch.exp((directions @ window - 1) / 0.003))[..., None]
    environment = environment.expand(16, 32, 3).contiguous()
    result = PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 6)
    paths = prepare_run_folder(tmp_path / "run")
    write_pbr_fit(paths, result)
    report_stage(RunConfig(), paths, torch.device("cpu"))

    def sheet(path) -> np.ndarray:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB")).astype(float) / 255

    found = sheet(paths.figure("turntable"))
    from recon.report.report import turntable
    from recon.stages.fitted_scene import load_fitted_light

    lambert_path = tmp_path / "lambert.png"
    turntable(mesh, load_fitted_light(paths, "cpu"), lambert_path, torch.device("cpu"))
    lambert = sheet(lambert_path)
    # The background is white (1) in both: compare the object's inner pixels (no edges).
    inside = binary_erosion(found.mean(-1) < 0.98, iterations=3)
    assert inside.mean() > 0.3
    # The glossy sphere mirrors the window: a highlight (measured 0.89 in sRGB) that diffuse
    # shading of the same light (its order-2 SH, measured at most 0.44) cannot make; the rest
    # is about as bright in both (medians 0.35 and 0.32).
    assert found[inside].mean(-1).max() > 0.8 and lambert[inside].mean(-1).max() < 0.6
    medians = np.median(found[inside].mean(-1)), np.median(lambert[inside].mean(-1))
    assert abs(medians[0] / medians[1] - 1) < 0.15
    markdown = paths.report_markdown.read_text()
    assert "## Fitted mesh, turntable (pbr material)" in markdown
    assert "## Fitted material and environment (pbr)" in markdown
    assert "figures/material.png" in markdown and paths.figure("material").stat().st_size > 0
    page = paths.report_html.read_text()
    assert "Fitted material and environment (pbr)" in page and "figures/material.png" in page


def test_a_pbr_run_on_a_synthetic_world_compares_its_roughness_with_the_truth(tmp_path):
    from tests.material_scenes import material_run

    paths = material_run(tmp_path / "pbr", "pbr", roughness_offset=0.1)
    report_stage(RunConfig(), paths, torch.device("cpu"))
    markdown = paths.report_markdown.read_text()
    title = "## Fitted against true roughness, first test view"
    assert title in markdown and paths.figure("roughness_truth").stat().st_size > 0
    # In the material section: right after the fitted material's figure.
    assert markdown.index("## Fitted material and environment (pbr)") < markdown.index(title)
    assert markdown.index(title) < markdown.index("## Distance to the reference")
    assert "figures/roughness_truth.png" in paths.report_html.read_text()
    lambert = material_run(tmp_path / "lambert", "lambert")
    report_stage(RunConfig(), lambert, torch.device("cpu"))
    assert "true roughness" not in lambert.report_markdown.read_text()
    assert not lambert.figure("roughness_truth").exists()
