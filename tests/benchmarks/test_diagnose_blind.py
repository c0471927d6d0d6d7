"""A small blind benchmark in the suite: withheld effects at 48 px, fit without them, diagnose
blind, score against the truth only afterwards."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from benchmarks.diagnose_blind import run_case, summarise
from recon.config import load_config
from recon.config.run_config import RunConfig
from recon.sweep.scoring import BenchCase

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def tiny_config(tmp_path) -> RunConfig:
    config = yaml.safe_load((REPO_ROOT / "configs" / "bench" / "diagnose.yaml").read_text())
    config["capture"]["cameras"]["resolution"] = [48, 48]
    config["capture"]["train_views"] = 8
    config["capture"]["test_views"] = 4
    config["scene"]["shape"]["resolution"] = 32
    config["fit"] = {
        "hull_resolution": 32,
        "geometry": {"steps": 60, "resolutions": [48], "remesh_every": 30},
        "texture": {"steps": 30, "texture_size": 128},
        "simplify": {"target_faces": 3000},
    }
    path = tmp_path / "blind.yaml"
    path.write_text(yaml.safe_dump(config))
    return load_config(path, RunConfig)


def test_blind_exposure_is_found_and_clean_is_clean(tiny_config, tmp_path):
    torch.set_num_threads(1)
    records = [
        run_case(
            BenchCase(("exposure",), seed=0), tiny_config, tmp_path, torch.device("cpu"), "none"
        ),
        run_case(BenchCase((), seed=100), tiny_config, tmp_path, torch.device("cpu"), "none"),
        run_case(
            BenchCase(("defocus_blur",), seed=0),
            tiny_config,
            tmp_path,
            torch.device("cpu"),
            "none",
        ),
    ]
    summary = summarise(records)
    # A per-view exposure change cannot be absorbed by the texture: it must come out on top.
    assert records[0]["predicted_top"] == "exposure", records[0]
    # A defocus blur of random plausible strength at 48 px is often within what the blur probe
    # reaches on clean fits (their own softness); it may go unnamed but must not be blamed on
    # another effect.
    assert records[2]["predicted_top"] in ("defocus_blur", "none"), records[2]
    assert summary["top1_accuracy"] >= 0.5
    assert summary["false_positive_rate"] == 0.0, records[1]
    # The truth lies outside the run folder, and nothing inside names the withheld effect
    # except the diagnosis' own output.
    run_folder = Path(records[0]["run_folder"])
    # With a ground truth beside the run, the gap carries the fitted geometry's error.
    geometry = json.loads((run_folder / "diagnosis.json").read_text())["gap"]["parameters"]
    assert 0 < geometry["geometry"]["chamfer_l1"] < 0.02
    assert geometry["geometry"]["normal_consistency"] > 0.8
    effects_record = json.loads((run_folder / "ground_truth" / "effects.json").read_text())
    assert effects_record["withheld"] is True and effects_record["effects"] == []
    for path in run_folder.rglob("*.json"):
        if path.name != "diagnosis.json" and "refit" not in path.parts:
            assert '"exposure"' not in path.read_text(), path


def test_blind_vignetting_is_measured_out_to_the_corners(tiny_config, tmp_path):
    """The bench config's flat-field frames: vignetting is named from them, and its corner
    falloff, which the object's pixels never reach, is the frames' measurement."""
    torch.set_num_threads(1)
    record = run_case(
        BenchCase(("vignetting",), seed=1), tiny_config, tmp_path, torch.device("cpu"), "none"
    )
    assert record["predicted_top"] == "vignetting", record
    assert record["parameter_error"]["vignetting_corner_falloff"] < 0.05, record
    diagnosis = json.loads((Path(record["run_folder"]) / "diagnosis.json").read_text())
    vignetting = next(item for item in diagnosis["candidates"] if item["name"] == "vignetting")
    assert vignetting["decided_by"] == "flat_field"
    assert vignetting["parameters"]["falloff_source"] == "flat_field"
    assert diagnosis["gap"]["flat_field"]["frames"] == 2


def test_blind_lens_is_measured_on_the_line_target(tiny_config, tmp_path):
    """The bench config's line-target frames: a withheld lens distortion, which a 48 px view of
    a centred object shows as little more than a zoom, is named from the frames' bent lines, with
    the coefficients that made them."""
    torch.set_num_threads(1)
    record = run_case(
        BenchCase(("lens_distortion",), seed=0), tiny_config, tmp_path, torch.device("cpu"), "none"
    )
    assert record["predicted_top"] == "lens_distortion", record
    diagnosis = json.loads((Path(record["run_folder"]) / "diagnosis.json").read_text())
    lens = next(item for item in diagnosis["candidates"] if item["name"] == "lens_distortion")
    assert lens["decided_by"] == "line_target" and lens["status"] == "significant"
    truth = json.loads((tmp_path / "truth" / "lens_distortion_seed0.json").read_text())
    true_k1 = truth["withheld"][0]["parameters"]["k1"]
    assert lens["parameters"]["k1"] == pytest.approx(true_k1, rel=0.15, abs=0.02)
    assert diagnosis["gap"]["line_target"]["frames"] == 4


# ---------------------------------------------------------------------------------------------
# The broadened check (issue 20): worlds, scenes, leave-one-scene-out calibration.
# ---------------------------------------------------------------------------------------------


def _tiny_worlds_config(tmp_path: Path) -> Path:
    config = yaml.safe_load(
        (REPO_ROOT / "configs" / "bench" / "diagnose_blind_48.yaml").read_text()
    )
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"]["train_views"] = 6
    config["capture"]["test_views"] = 3
    config["capture"]["relight"]["views"] = 0
    config["capture"]["flat_field"]["views"] = 0
    config["scene"]["shape"]["resolution"] = 24
    config["fit"] = {
        "hull_resolution": 32,
        "geometry": {"steps": 16, "resolutions": [32], "remesh_every": 0},
        "texture": {"steps": 8, "texture_size": 64},
        "simplify": {"target_faces": 1500},
    }
    path = tmp_path / "tiny_worlds.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_tiny_broadened_benchmark_writes_every_metric(tmp_path):
    """Two procedural scenes of the own world, two effects and a clean case each, fitted in a
    few steps at 32 px: the harness collects, calibrates leave-one-scene-out and writes the
    metrics, the confusion matrix, the page and an engine-ready calibration (not accuracy)."""
    from benchmarks.diagnose_blind import diagnose_blind_worlds

    torch.set_num_threads(1)
    out = tmp_path / "bench"
    doc = tmp_path / "docs" / "blind.md"
    doc.parent.mkdir()
    summary = diagnose_blind_worlds(
        _tiny_worlds_config(tmp_path),
        out,
        torch.device("cpu"),
        worlds=["own"],
        scenes=["torus", "blob"],
        effects=["exposure", "vignetting"],
        seeds=[0],
        pairs=[],
        doc=doc,
        command="test",
        candidates=["exposure", "vignetting", "pose_error"],
    )
    result = json.loads((out / "blind.json").read_text())
    cases = result["loso"]["cases"]
    assert len(cases) == 6 and not result["provenance"]["skipped"]
    for record in cases:
        assert record["scene"] not in record["calibrated_on"] and record["calibrated_on"]
    own = summary["loso"]["own"]
    assert own["cases"] == {"single": 4, "pair": 0, "clean": 2}
    for key in ("top1_accuracy", "exact_set_accuracy", "false_positive_rate"):
        assert 0.0 <= own[key] <= 1.0
    assert own["median_fit_seconds"] > 0 and own["median_diagnose_seconds"] > 0
    matrix = result["loso"]["confusion"]["own"]["matrix"]
    assert sum(map(sum, matrix)) == 6
    calibration = json.loads((out / "calibration.json").read_text())
    assert calibration["provenance"]["scenes"] == ["blob", "torus"]
    assert calibration["thresholds"]["probe.exposure"] >= 0.02
    page = doc.read_text()
    assert "leave-one-scene-out" in page and "| own |" in page
    assert (doc.parent / "blind_confusion.png").stat().st_size > 0
    assert json.loads((doc.parent / "blind_calibration.json").read_text()) == calibration
    # Collected once: a second call re-scores the stored evidence without fitting again.
    started = json.loads((out / "collected.json").read_text())["cases"][0]
    again = diagnose_blind_worlds(
        _tiny_worlds_config(tmp_path),
        out,
        torch.device("cpu"),
        worlds=["own"],
        scenes=["torus", "blob"],
        effects=["exposure", "vignetting"],
        seeds=[0],
        pairs=[],
        command="test",
        candidates=["exposure", "vignetting", "pose_error"],
    )
    assert again["loso"] == summary["loso"]
    assert json.loads((out / "collected.json").read_text())["cases"][0] == started


def test_the_real_world_takes_its_size_views_and_fit_config_from_the_command_line(tmp_path):
    from benchmarks.blind.collect import RealOptions
    from benchmarks.diagnose_blind import build_parser, real_options

    base = ["configs/bench/diagnose_blind_48.yaml", "--out", str(tmp_path), "--worlds", "real"]
    default = real_options(build_parser().parse_args(base))
    assert default == RealOptions()
    assert default.config.name == "blind_real.yaml" and default.config.exists()
    chosen = real_options(
        build_parser().parse_args(
            base
            + ["--real-resolution", "192", "--real-view-every", "3"]
            + ["--real-config", str(tmp_path / "blind_real_192.yaml")]
        )
    )
    assert (chosen.max_resolution, chosen.view_every) == (192, 3)
    assert chosen.config == tmp_path / "blind_real_192.yaml"
