"""The diagnose stage on real (tiny) run folders: the fitted model is loaded as the fit left it
(its own effects and material included), diagnosis.json is written as a typed Diagnosis with a
schema version, and `recon diagnose` prints it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import yaml

import recon.stages.diagnose as stage
from recon.cli import main
from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.diagnose.gap import gap_summary
from recon.diagnose.records import SCHEMA_VERSION, Candidate, Diagnosis, Evidence
from recon.effects import make_effect
from recon.errors import ReconError
from recon.io.run_folder import open_run_folder
from recon.metrics.evaluate import render_scene
from recon.stages.fitted_scene import load_fitted_scene

REPO_ROOT = Path(__file__).resolve().parents[2]


def config_of(paths) -> RunConfig:
    return load_config(paths.resolved_config, RunConfig)


def test_load_diagnosis_data_renders_the_fitted_scene(tiny_run, device):
    paths = open_run_folder(tiny_run)
    data = stage.load_diagnosis_data(paths, "test", config_of(paths), device)
    assert data.observed.shape == (2, 32, 32, 3) and data.split == "test"
    assert len(data.names) == 2 and data.observed.device.type == "cpu"
    # The same render as the evaluate stage's.
    scene = load_fitted_scene(paths, device)
    colors, alphas = render_scene(scene.mesh, scene.lighting, scene.pbr, data.cameras, device)
    assert torch.allclose(data.rendered, colors, atol=1e-5)
    assert torch.allclose(data.rendered_alpha, alphas, atol=1e-5)
    covered = data.rendered_mask
    assert bool((data.texel_uv[covered] >= 0).all()) and bool((data.depth[covered] > 0).all())
    assert gap_summary(data)["rmse"] > 0


def test_load_diagnosis_data_applies_model_effects(tiny_run):
    paths = open_run_folder(tiny_run)
    config = config_of(paths)
    plain = stage.load_diagnosis_data(paths, "test", config)
    vignetting = make_effect("vignetting")
    at_identity = stage.load_diagnosis_data(paths, "test", config, effects=[vignetting])
    assert torch.allclose(at_identity.rendered, plain.rendered, atol=1e-6)
    with torch.no_grad():
        vignetting.coefficients.fill_(-0.5)
    darkened = stage.load_diagnosis_data(paths, "test", config, effects=[vignetting])
    assert not torch.allclose(darkened.rendered, plain.rendered, atol=1e-4)
    assert torch.equal(darkened.triangle_id, plain.triangle_id)


def test_a_missing_fit_is_named(tmp_path):
    (tmp_path / "config.resolved.yaml").write_text("name: x\n")
    with pytest.raises(ReconError, match="no fitted mesh"):
        stage.load_fitted_model(open_run_folder(tmp_path), RunConfig(), torch.device("cpu"))


def test_diagnose_command_writes_the_typed_diagnosis(tiny_run, capsys):
    code = main(
        ["diagnose", str(tiny_run), "--refit", "top", "--effects", "exposure,vignetting,shadows"]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "verdict:" in printed and "visibility fingerprint:" in printed and "why:" in printed
    stored = json.loads((tiny_run / "diagnosis.json").read_text())
    assert stored["schema_version"] == SCHEMA_VERSION
    diagnosis = Diagnosis.from_json(stored)
    assert diagnosis.to_json() == stored
    assert diagnosis.model == {"material": "lambert", "light_frame": "world", "effects": []}
    assert {item.name for item in diagnosis.candidates} == {"exposure", "vignetting", "shadows"}
    assert diagnosis.settings["refit"] == "top"
    for candidate in diagnosis.candidates:
        assert candidate.evidence_of("probe") is not None and candidate.why
        assert candidate.significant == bool(candidate.decided_by)
        assert candidate.decided_by in ("", "probe", "absorption", "fingerprint")
    # Vignetting is absorbable: it carries the absorption regression's evidence, and its
    # falloff says how far out the object's pixels measured it.
    vignetting = diagnosis.candidate("vignetting")
    assert len(vignetting.evidence_of("absorption").interval) == 2
    assert 0.1 < vignetting.evidence_of("probe").details["parameters"]["covered_radius"] < 1.0
    assert diagnosis.candidate("shadows").evidence_of("fingerprint") is not None
    assert set(diagnosis.gap["visibility_fingerprint"]) >= {"share", "interval", "names"}
    for refit in diagnosis.refits:
        assert refit["confirmed"] == (refit["closed_fraction"] >= 0.05)
    assert diagnosis.confirmed_by_refit == [
        refit["effects"][-1] for refit in diagnosis.refits if refit["confirmed"]
    ]
    assert all((tiny_run / path).exists() for path in diagnosis.figures.values())


def test_diagnose_command_prints_parameters_and_voided_evidence(tiny_run, capsys, monkeypatch):
    """The command's lines for a significant effect's recovered parameters (the first refit's
    over the evidence's) and for an absorption voided beside the conditioning effect."""
    exposure = Candidate(
        "exposure", significant=True, status="significant", decided_by="probe", why="clears"
    )
    exposure.parameters = {"ratios": [0.9, 1.2]}
    exposure.add(
        Evidence(
            "probe",
            "exposure",
            0.5,
            0.02,
            True,
            "probe",
            {"reduction": 0.6, "interval": [0.5, 0.7]},
        )
    )
    lens = Candidate("lens_distortion", why="does not clear")
    lens.add(
        Evidence(
            "probe",
            "lens_distortion",
            -0.02,
            0.056,
            False,
            "probe",
            {"reduction": 0.01, "interval": [-0.02, 0.03]},
        )
    )
    lens.add(
        Evidence(
            "absorption",
            "lens_distortion",
            0.2,
            0.043,
            True,
            "absorption",
            {"reduction": 0.3, "interval": [0.2, 0.4], "discounted_by": "exposure"},
            void="void beside exposure",
        )
    )
    diagnosis = Diagnosis(
        candidates=[exposure, lens],
        refits=[
            {
                "effects": ["exposure"],
                "before_rmse": 0.1,
                "after_rmse": 0.05,
                "closed_fraction": 0.8,
                "parameters": {"exposure": {"ratios": [0.8, 1.25]}},
            }
        ],
        verdict="significant unmodelled effects: exposure",
        confirmed_by_refit=["exposure"],
        model={"material": "lambert", "light_frame": "world", "effects": ["vignetting"]},
    )
    monkeypatch.setattr(stage, "run_diagnosis", lambda *arguments, **options: diagnosis)
    assert main(["diagnose", str(tiny_run)]) == 0
    printed = capsys.readouterr().out
    assert "  exposure (refit): ratios 0.8..1.25 (2)" in printed
    assert "absorption  0.300 (void beside exposure)" in printed
    assert "  lens_distortion (" not in printed  # not significant: no parameter line
    assert "fit effects vignetting (part of the model, not candidates)" in printed
    diagnosis.gap = {"flat_field_error": "dataset/flat_field: flat_field.frames[0]: no light"}
    assert main(["diagnose", str(tiny_run)]) == 0
    assert "flat field not used: dataset/flat_field: flat_field.frames[0]: no light" in (
        capsys.readouterr().out
    )
    diagnosis.gap = {
        "line_target": {
            "corner_shift_pixels": 2.5,
            "standard_error": 0.04,
            "allowance": 0.3,
            "z": 4.0,
            "frames": 4,
            "lines": 31,
            "straightness_before_pixels": 0.21,
            "straightness_after_pixels": 0.07,
        }
    }
    assert main(["diagnose", str(tiny_run)]) == 0
    assert (
        "line target (4 frames, 31 edges): corners moved 2.50 px (standard error 0.04 px; "
        "lens distortion; edges off straight 0.210 -> 0.070 px RMS)"
    ) in capsys.readouterr().out


def _fit_with_exposure(folder: Path, fit_effects: list[str]) -> Path:
    """A tiny run on data with a strong per-view exposure, fitted with fit_effects."""
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 8, "val_views": 0, "test_views": 6})
    config["capture"]["effects"] = [{"name": "exposure", "parameters": {"spread_stops": 1.0}}]
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 32
    config["fit"] = {
        "hull_resolution": 16,
        "geometry": {"steps": 20, "resolutions": [32], "remesh_every": 0},
        "texture": {"steps": 20, "texture_size": 64},
        "effects": fit_effects,
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "exposure.yaml"
    path.write_text(yaml.safe_dump(config))
    out = folder / "run"
    assert main(["run", str(path), "--out", str(out), "--device", "cpu"]) == 0
    return out


def test_the_fits_own_effects_are_part_of_the_model(tmp_path):
    """The same data with a per-view exposure, fitted with and without fit.effects: [exposure].
    Without it, the diagnosis names exposure; with it, exposure is the model's (not a
    candidate), its held-out gains are fitted per view, and its look-alike (white balance)
    finds nothing left to explain."""
    candidates = ["exposure", "white_balance"]
    plain = open_run_folder(_fit_with_exposure(tmp_path / "plain", []))
    found = stage.run_diagnosis(plain, config_of(plain), torch.device("cpu"), "none", candidates)
    assert found.significant[:1] == ["exposure"], found.verdict
    modelled = open_run_folder(_fit_with_exposure(tmp_path / "modelled", ["exposure"]))
    config = config_of(modelled)
    config = replace(config, diagnose=replace(config.diagnose, absorption=False))
    diagnosis = stage.run_diagnosis(modelled, config, torch.device("cpu"), "none", candidates)
    assert diagnosis.model["effects"] == ["exposure"]
    assert [item.name for item in diagnosis.candidates] == ["white_balance"]
    # White balance may add "not identifiable from this data" (this tiny fit's colour noise
    # hides a small cast, decision 0202), but it must not be significant.
    assert diagnosis.significant == [], diagnosis.candidates
    assert diagnosis.verdict.startswith("no significant unmodelled effect"), diagnosis.verdict
    # The model's render holds the per-view gains (fitted on each held-out view's first half):
    # its held-out gap is below that of the same fit rendered without its effects.
    without = stage.load_diagnosis_data(modelled, "test", config)
    assert diagnosis.gap["rmse"] < 0.95 * gap_summary(without)["rmse"]


def test_a_pbr_fit_is_diagnosed_with_its_material(tiny_run, tmp_path):
    """With fit.material: pbr the baseline is the pbr render (the held-out render equals the
    evaluate stage's), specular is modelled by the material (not a candidate), and the how-far
    step is not skipped (its refits refit the pbr material, recon.diagnose.refit)."""
    config = yaml.safe_load((tiny_run.parent / "tiny.yaml").read_text())
    config["fit"]["material"] = "pbr"
    path = tmp_path / "pbr.yaml"
    path.write_text(yaml.safe_dump(config))
    assert main(["run", str(path), "--out", str(tmp_path / "run"), "--device", "cpu"]) == 0
    paths = open_run_folder(tmp_path / "run")
    run_config = config_of(paths)
    data = stage.load_diagnosis_data(paths, "test", run_config)
    scene = load_fitted_scene(paths, torch.device("cpu"))
    colors, _ = render_scene(scene.mesh, scene.lighting, scene.pbr, data.cameras, "cpu")
    assert torch.allclose(data.rendered, colors, atol=1e-5)
    diagnosis = stage.run_diagnosis(
        paths, run_config, torch.device("cpu"), "top", ["exposure", "specular"]
    )
    assert diagnosis.model["material"] == "pbr"
    assert [item.name for item in diagnosis.candidates] == ["exposure"]
    assert "how_far_skipped" not in diagnosis.gap
    assert all(record["effects"] == ["exposure"] for record in diagnosis.refits)


def test_the_stage_table_names_the_stage_module():
    from recon.stages import find_stage

    assert find_stage("diagnose") is stage.diagnose_stage


# --------------------------------------------------------------------------------------------
# every dataset layout recon reads: the tiny run's NeRF-synthetic views rewritten as LLFF, a
# COLMAP model (sparse/) and a plain photo folder with cached structure-from-motion poses
# (sparse/0/), each fitted from that folder in a few steps and diagnosed
# --------------------------------------------------------------------------------------------


def _all_views(tiny_run: Path):
    """The tiny run's train and test captures, concatenated (linear, premultiplied, masks)."""
    from recon.io.datasets import read_captures

    parts = [read_captures(tiny_run / "dataset", split) for split in ("train", "test")]
    world_to_cam = torch.cat([part.cameras.world_to_cam for part in parts])
    intrinsics = torch.cat([part.cameras.intrinsics for part in parts])
    images = torch.cat([part.images for part in parts])
    masks = torch.cat([part.masks for part in parts])
    return world_to_cam, intrinsics, images, masks, parts[0].cameras.image_size


def _write_photos(folder: Path, images: torch.Tensor, masks: torch.Tensor) -> list[str]:
    from recon.io.images import write_png

    names = []
    for index in range(len(images)):
        name = f"view_{index:02d}.png"
        write_png(folder / "images" / name, images[index])
        write_png(folder / "masks" / name, masks[index], encode_srgb=False)
        names.append(name)
    return names


def _llff(folder: Path, tiny_run: Path) -> Path:
    """poses_bounds.npy rows: OpenCV camera-to-world [right, down, forward] as LLFF's
    [down, right, back], then the image size and focal, then near/far bounds."""
    import numpy as np

    from recon.camera import rigid_inverse

    world_to_cam, intrinsics, images, masks, size = _all_views(tiny_run)
    _write_photos(folder, images, masks)
    cam_to_world = rigid_inverse(world_to_cam.double()).numpy()
    right, down, forward, centre = (cam_to_world[:, :3, column] for column in range(4))
    focal = float(intrinsics[0, 0, 0])
    hwf = np.tile([size[0], size[1], focal], (len(cam_to_world), 1))
    pose = np.stack([down, right, -forward, centre, hwf], axis=-1)
    bounds = np.tile([1.0, 6.0], (len(cam_to_world), 1))
    np.save(folder / "poses_bounds.npy", np.concatenate([pose.reshape(-1, 15), bounds], axis=1))
    return folder


def _colmap(folder: Path, tiny_run: Path, model: str) -> Path:
    """A COLMAP text model (one PINHOLE camera) in folder/model with images/ and masks/."""
    from scipy.spatial.transform import Rotation

    world_to_cam, intrinsics, images, masks, size = _all_views(tiny_run)
    names = _write_photos(folder, images, masks)
    for name in names:  # COLMAP's mask naming: NAME.png.png
        (folder / "masks" / name).rename(folder / "masks" / f"{name}.png")
    target = folder / model
    target.mkdir(parents=True)
    fx, fy = float(intrinsics[0, 0, 0]), float(intrinsics[0, 1, 1])
    cx, cy = float(intrinsics[0, 0, 2]), float(intrinsics[0, 1, 2])
    (target / "cameras.txt").write_text(f"1 PINHOLE {size[1]} {size[0]} {fx} {fy} {cx} {cy}\n")
    lines = []
    for index, matrix in enumerate(world_to_cam.double().numpy()):
        x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
        t = matrix[:3, 3]
        lines += [f"{index + 1} {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} 1 {names[index]}", ""]
    (target / "images.txt").write_text("\n".join(lines) + "\n")
    (target / "points3D.txt").write_text("1 0.1 0.0 -0.1 200 10 10 0.3\n2 -0.1 0 0.1 1 2 3 0.4\n")
    return folder


LAYOUTS = {
    "llff": (_llff, "llff"),
    "colmap": (lambda folder, run: _colmap(folder, run, "sparse"), "colmap"),
    "cached_sfm": (lambda folder, run: _colmap(folder, run, "sparse/0"), "colmap"),
}


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_every_dataset_layout_is_diagnosed(layout, tiny_run, tmp_path, capsys):
    """The tiny run's 6 views in another layout (view 0 held out: every 8th),
    fitted from that folder and diagnosed: diagnosis.json is written, typed, with a verdict."""
    if layout != "llff":
        pytest.importorskip("pycolmap")
    from recon.io.datasets import dataset_layout

    write, expected = LAYOUTS[layout]
    data = write(tmp_path / "data", tiny_run)
    assert dataset_layout(data) == expected
    run = tmp_path / "run"
    settings = [
        # The synthetic frame is already centred and scaled (as the NeRF-synthetic run is).
        "dataset.normalize.enabled=false",
        "fit.hull_resolution=16",
        "fit.geometry.steps=3",
        "fit.geometry.resolutions=[32]",
        "fit.geometry.remesh_every=0",
        "fit.texture.steps=1",
        "fit.texture.texture_size=64",
    ]
    overrides = [item for setting in settings for item in ("--set", setting)]
    config = str(tiny_run.parent / "tiny.yaml")
    code = main(
        ["fit", config, "--data", str(data), "--out", str(run), "--device", "cpu", *overrides]
    )
    assert code == 0, capsys.readouterr().err
    code = main(["diagnose", str(run), "--refit", "none", "--effects", "exposure,vignetting"])
    assert code == 0, capsys.readouterr().err
    diagnosis = Diagnosis.from_json(json.loads((run / "diagnosis.json").read_text()))
    assert diagnosis.verdict and diagnosis.gap["pixels"] > 0
    assert {item.name for item in diagnosis.candidates} == {"exposure", "vignetting"}
    assert len(diagnosis.gap["per_view_rmse"]) == 1  # view 0


def test_only_the_stage_touches_the_run_folder():
    """No module of recon/diagnose imports the run folder's layout or reads a dataset from a
    path: they take captures, the fitted model and config sections (the stage loads them)."""
    import ast

    forbidden = {"recon.io.run_folder", "recon.io.meshes", "recon.optimize.fit"}
    readers = {"read_captures", "load_mesh", "load_fitted_light", "open_run_folder"}
    for path in sorted((REPO_ROOT / "recon" / "diagnose").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert node.module not in forbidden, f"{path.name} imports {node.module}"
                names = {alias.name for alias in node.names}
                assert not names & readers, f"{path.name} imports {names & readers}"


def test_diagnose_settings_can_be_set_and_are_recorded(tiny_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    strict = "diagnose.decision.minimum_share=0.9"
    arguments = ["diagnose", str(run), "--refit", "none", "--effects", "exposure", "--set", strict]
    assert main([*arguments, "--set", "diagnose.absorption=false"]) == 0
    diagnosis = Diagnosis.from_json(json.loads((run / "diagnosis.json").read_text()))
    assert diagnosis.settings["decision"]["minimum_share"] == 0.9
    assert diagnosis.candidate("exposure").evidence_of("probe").threshold == 0.9
    assert diagnosis.verdict == "no significant unmodelled effect"
    capsys.readouterr()
    assert main(["diagnose", str(run), "--set", "fit.texture.steps=3"]) == 2
    assert "only diagnose.* settings can change after the fit" in capsys.readouterr().err
