"""The checks end to end: `recon diagnose` on a run whose held-out views show a glossy object
at constant exposure. The diffuse fit's per-view gains absorb the highlight, so the exposure
probe alone calls exposure significant; with the checks the verdict names view-dependent
reflectance (the base model's mismatch) and not exposure. Also: the producers read their
config sections, and the metadata check's reference (EXIF gains, or equal gains when the images
were divided by them on load)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from diagnose_scenes import glossy_torus_views
from PIL import Image

from recon.camera import look_at, orbit_cameras, rigid_inverse
from recon.cli import main
from recon.config.run_config import DatasetConfig, DiagnoseConfig, IdentifiabilityConfig
from recon.diagnose.checks import CHECK_PRODUCERS, identifiability_producer, metadata_producer
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.decision import decide
from recon.diagnose.metadata_check import exif_exposure_gains, metadata_evidence
from recon.diagnose.pixel_table import dominant_light_direction, view_directions
from recon.diagnose.producers import PRODUCERS
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.which import rank_candidates
from recon.errors import ReconError
from recon.io.datasets import read_captures, write_nerf_synthetic
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


def test_the_producers_read_their_sections_from_the_diagnose_config():
    data, _ = glossy_torus_views(size=32, views=8)
    inputs = SimpleNamespace(data=data, relight=None, heldout=SimpleNamespace(metadata=None))
    candidates = [Candidate("motion_blur")]
    strict = DiagnoseConfig(identifiability=IdentifiabilityConfig(maximum_edge_coherence=0.0))
    lax = DiagnoseConfig(identifiability=IdentifiabilityConfig(maximum_edge_coherence=1.0))
    (refused,) = identifiability_producer(inputs, candidates, strict)
    (accepted,) = identifiability_producer(inputs, candidates, lax)
    assert not refused.passed and accepted.passed
    assert refused.threshold == 0.0 and accepted.threshold == 1.0


def exif_photo_folder(
    folder: Path, exposure_times: list[float], white_balance: list[int] | None = None
) -> None:
    """An LLFF folder of tiny JPEG photos (a grey square on white) whose EXIF (written by
    Pillow) holds the given exposure times at f/8, ISO 400, and where given the white-balance
    modes (EXIF codes: 0 auto, 1 manual)."""
    count = len(exposure_times)
    eyes = torch.tensor([[0.5 * index - 1.0, 0.2, 4.0] for index in range(count)])
    cam_to_world = rigid_inverse(look_at(eyes, torch.zeros(count, 3)).double()).numpy()
    right, down, forward, centre = (cam_to_world[:, :3, column] for column in range(4))
    hwf = np.tile([24, 32, 30.0], (count, 1))
    rows = np.stack([down, right, -forward, centre, hwf], axis=-1).reshape(-1, 15)
    np.save(folder / "poses_bounds.npy", np.concatenate([rows, [[2.0, 6.0]] * count], 1))
    (folder / "images").mkdir()
    for index, exposure_time in enumerate(exposure_times):
        photo = np.full((24, 32, 3), 255, np.uint8)
        photo[6:16, 8:20] = 96
        tags = Image.Exif()
        sub = tags.get_ifd(0x8769)  # the EXIF sub-IFD
        sub[0x829A], sub[0x829D], sub[0x8827] = exposure_time, 8.0, 400
        if white_balance is not None:
            sub[0xA403] = white_balance[index]
        Image.fromarray(photo).save(folder / "images" / f"IMG_{index}.jpg", exif=tags)


@pytest.mark.parametrize("exposure", ["none", "exif"])
def test_metadata_compares_with_equal_gains_when_the_images_were_divided(tmp_path, exposure):
    times = [0.01, 0.02, 0.01, 0.005, 0.01, 0.016, 0.008, 0.0125, 0.01]
    exif_photo_folder(tmp_path, times)
    dataset = DatasetConfig(background_key=[1.0, 1.0, 1.0], exposure=exposure)
    heldout = read_captures(tmp_path, "train", dataset)
    gains = exif_exposure_gains(heldout.metadata).float()
    assert (heldout.known_gains is not None) == (exposure == "exif")

    # The held-out views as the fit sees them: raw photos carry the EXIF gains; divided ones
    # carry none (the exposure left to recover is equal in every view).
    def as_seen(observed, output):
        return observed * gains[:, None, None, None] if exposure == "none" else observed

    data, _ = glossy_torus_views(views=len(heldout), size=32, specular=0.0, transform=as_seen)
    candidates = rank_candidates(data, ["exposure"])
    inputs = SimpleNamespace(data=data, heldout=heldout)
    (evidence,) = metadata_producer(inputs, candidates, DiagnoseConfig())
    assert evidence.kind == "metadata" and evidence.passed, evidence.reason
    assert evidence.details["median_ratio_error"] < 0.01
    divided = exposure == "exif"
    assert ("divided by their EXIF exposure" in evidence.reason) == divided
    assert evidence.details["compared_with"] == (
        "equal gains (images divided by EXIF exposure)" if divided else "EXIF exposure"
    )
    # The same recovered gains against the other reference disagree: the reference matters.
    ratios = evidence_ratios(candidates)
    other = torch.ones_like(gains) if exposure == "none" else gains
    assert not metadata_evidence(ratios, other, options=DiagnoseConfig().metadata).passed


def evidence_ratios(candidates) -> list[float]:
    probe = next(item for item in candidates if item.name == "exposure").evidence_of("probe")
    return probe.details["parameters"]["ratios"]


def test_vignetting_short_of_the_corners_and_distortion_against_pose_are_registered():
    # The torus covers the image centre only (radius about 0.64 of the half diagonal).
    data, _ = glossy_torus_views(size=32, views=8)
    inputs = SimpleNamespace(data=data, relight=None, heldout=SimpleNamespace(metadata=None))
    distortion = Candidate("lens_distortion", significant=True, status="significant")
    parameters = {"parameters": {"corner_shift_px": 20.0}}
    distortion.add(Evidence("probe", "lens_distortion", 0.2, 0.05, True, "probe", parameters))
    falloff, judged = identifiability_producer(
        inputs, [Candidate("vignetting"), distortion], DiagnoseConfig()
    )
    assert falloff.candidate == "vignetting" and not falloff.passed
    assert "corner falloff is an extrapolation" in falloff.reason
    assert falloff.details["capture"].startswith("flat-field frames")
    # A cleared distortion is judged at its recovered size: 20 px at the corners leaves flow
    # over the object that no per-view zoom, shift and rotation makes.
    assert judged.passed and judged.details["corner_shift_pixels"] == 20.0
    # One that did not clear is judged at the reference strength (a tenth of the half
    # diagonal, 2.3 px at 32 px): it would hide in a pose correction.
    distortion.significant, distortion.status = False, "not_significant"
    (reference,) = identifiability_producer(inputs, [distortion], DiagnoseConfig())
    assert not reference.passed and reference.details["corner_shift_pixels"] < 2.5
    assert reference.details["confused_with"] == ["pose_error"]
    assert not reference.details["capture"].endswith(",")


def test_metadata_compares_the_gains_the_exposure_reports(tmp_path):
    # The exposure reports the gains read apart from the highlight (the gain evidence) where
    # they were measured; the EXIF check must judge those, not the probe's, which a highlight
    # moves.
    times = [0.01, 0.02, 0.01, 0.005, 0.01, 0.016, 0.008, 0.0125, 0.01]
    exif_photo_folder(tmp_path, times)
    heldout = read_captures(tmp_path, "train", DatasetConfig(background_key=[1.0, 1.0, 1.0]))
    gains = exif_exposure_gains(heldout.metadata)
    data, _ = glossy_torus_views(views=len(heldout), size=32, specular=0.0)
    exposure = Candidate("exposure")
    flat = {"parameters": {"ratios": [1.0] * len(heldout)}}
    exposure.add(Evidence("probe", "exposure", 0.1, 0.02, True, "probe", flat))
    inputs = SimpleNamespace(data=data, heldout=heldout)
    (from_probe,) = metadata_producer(inputs, [exposure], DiagnoseConfig())
    assert not from_probe.passed and from_probe.details["recovered_from"] == "probe"
    measured = {"parameters": {"ratios": (1.03 * gains).tolist()}}
    exposure.add(Evidence("gain", "exposure", 0.3, 0.0, True, "gain", measured))
    (from_gain,) = metadata_producer(inputs, [exposure], DiagnoseConfig())
    assert from_gain.passed and from_gain.details["recovered_from"] == "gain"
    assert from_gain.details["median_ratio_error"] < 1e-6


def test_metadata_with_fewer_held_out_views_than_the_minimum_is_no_evidence(tmp_path):
    # A small capture's held-out split can be one or two views: no correlation across views is
    # possible, so there is no metadata evidence, and the diagnosis goes on (not an error).
    exif_photo_folder(tmp_path, [0.01, 0.02])
    heldout = read_captures(tmp_path, "train", DatasetConfig(background_key=[1.0, 1.0, 1.0]))
    data, _ = glossy_torus_views(views=len(heldout), size=32, specular=0.0)
    candidates = rank_candidates(data, ["exposure"])
    inputs = SimpleNamespace(data=data, heldout=heldout)
    assert metadata_producer(inputs, candidates, DiagnoseConfig()) == []
    with pytest.raises(ReconError, match="minimum_views"):
        metadata_evidence([1.1, 0.9], [1.0, 1.0], options=DiagnoseConfig().metadata)


def test_a_falloff_the_flat_field_measured_is_not_vetoed_by_its_residual_signature():
    # Flat-field frames measure the falloff itself (the decision's overrule row): a residual
    # signature check says nothing about it, so the specificity producer leaves it alone, and a
    # candidate without such a measurement is still checked.
    from recon.diagnose.checks import specificity_producer

    data, _ = glossy_torus_views(size=32, views=8)
    inputs = SimpleNamespace(data=data)
    measured = Candidate("vignetting")
    details = {"corner_falloff": 0.6, "half_radius_falloff": 0.9, "frames": 2}
    measured.add(Evidence("flat_field", "vignetting", 0.4, 0.02, True, "flat field", details))
    assert specificity_producer(inputs, [measured], DiagnoseConfig()) == []
    (checked,) = specificity_producer(inputs, [Candidate("vignetting")], DiagnoseConfig())
    assert checked.kind == "specificity" and checked.candidate == "vignetting"


def test_a_distortion_whose_null_passed_is_judged_not_the_reference():
    # The probe did not clear its allowance, but removes more than placebo fields of its size:
    # it measured a distortion (7.4 px at the corners), and that one is judged, not 3.4 px.
    from recon.diagnose.checks import _recovered_distortion

    def lens(null_passed):
        parameters = {"k1": -0.22, "k2": 3.9, "corner_shift_px": 7.4}
        result = Candidate("lens_distortion")
        result.add(
            Evidence(
                "probe", "lens_distortion", 0.036, 0.087, False, "probe", {"parameters": parameters}
            )
        )
        result.add(Evidence("null", "lens_distortion", 0.036, 0.006, null_passed, "placebo"))
        return result

    assert _recovered_distortion(lens(True)) == (7.4, (-0.22, 3.9))
    assert _recovered_distortion(lens(False)) == (None, None)


@pytest.mark.parametrize("modes", [[1] * 10, [1, 1, 1, 0, 1, 1, 1, 1, 1, 1], None])
def test_a_white_balance_under_a_recorded_manual_white_balance_is_vetoed(tmp_path, modes):
    # A per-view colour change that clears its probe: under a manual white balance recorded in
    # every held-out view it is not the camera's (on a glossy real object, the reflected
    # surroundings); one automatic view, or no record at all, leaves the probe's verdict.
    exif_photo_folder(tmp_path, [0.01] * 10, modes)
    heldout = read_captures(tmp_path, "train", DatasetConfig(background_key=[1.0, 1.0, 1.0]))
    views = len(heldout)  # the train split stands in for held-out views here
    colour = Candidate("white_balance")
    gains = {"parameters": {"gains": [[1.1, 1.0, 0.9]] * len(heldout)}}
    colour.add(Evidence("probe", "white_balance", 0.1, 0.02, True, "probe", gains))
    inputs = SimpleNamespace(data=None, heldout=heldout)
    found = metadata_producer(inputs, [colour], DiagnoseConfig())
    if modes is None:
        assert found == []
        assert decide(colour, DiagnoseConfig().decision).significant
        return
    (record,) = found
    assert record.kind == "metadata" and record.candidate == "white_balance"
    all_manual = all(modes)
    assert record.passed == (not all_manual)
    assert record.details["manual_views"] == (views if all_manual else views - 1)
    for item in found:
        colour.add(item)
    decide(colour, DiagnoseConfig().decision)
    if all_manual:
        assert colour.status == "vetoed" and not colour.significant
        assert colour.why.startswith(
            f"the capture's EXIF records a manual white balance in all {views} held-out views"
        )
    else:
        assert colour.significant and f"automatic white balance in 1 of {views}" in record.reason
