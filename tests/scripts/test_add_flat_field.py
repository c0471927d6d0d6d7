"""scripts/add_flat_field.py, run as a script: it completes a run made before the config asked
for flat-field frames with the frames a fresh synth writes."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import pytest
import torch

from tests.data_synth.test_stage import read_split, synth

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "add_flat_field.py"


def _run_script(monkeypatch, arguments: list[str]) -> int:
    """The script as `python scripts/add_flat_field.py ARGS` runs it (its __main__ block, which
    exits with main's code), in this process."""
    monkeypatch.setattr("sys.argv", [str(SCRIPT), *arguments])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    return exit_info.value.code


def _withheld_runs(tmp_path: Path, split: str) -> tuple[Path, Path]:
    """Two synth runs of seed 2 with two effects withheld: one without the split (its truth in
    tmp_path/truth/case.json, where the script looks), one whose config asks for two frames of
    it (its truth in tmp_path/fresh_truth.json)."""
    runs = []
    for name, capture, truth in (
        ("case", {"train_views": 2}, tmp_path / "truth" / "case.json"),
        ("fresh", {"train_views": 2, split: {"views": 2}}, tmp_path / "fresh_truth.json"),
    ):
        runs.append(
            synth(
                tmp_path,
                name,
                {"seed": 2, "capture": capture},
                "--withhold",
                "2",
                "--truth-out",
                str(truth),
            )
        )
    return runs[0], runs[1]


def test_added_frames_are_the_frames_a_fresh_synth_writes(tmp_path, monkeypatch, capsys):
    """Withheld effects come from the truth file (seed 2 withholds vignetting, which darkens the
    card, and lens distortion, which does not); the config hash of a bench fit follows."""
    from recon.config import config_hash, load_config
    from recon.config.run_config import RunConfig

    before, fresh = _withheld_runs(tmp_path, "flat_field")
    (before / "bench_fit.json").write_text(json.dumps({"config_hash": "old", "fit_seconds": 1.0}))
    assert _run_script(monkeypatch, [str(before)]) == 0
    added = read_split(before, "flat_field").images
    assert torch.equal(added, read_split(fresh, "flat_field").images)
    truth = json.loads((tmp_path / "truth" / "case.json").read_text())
    fresh_truth = json.loads((tmp_path / "fresh_truth.json").read_text())
    assert [item["name"] for item in truth["realised"]["flat_field"]] == ["vignetting"]
    assert truth["realised"]["flat_field"] == fresh_truth["realised"]["flat_field"]
    assert float(added[:, 0, 0].mean()) < 0.95 * float(added[:, 15:17, 15:17].mean())
    config = load_config(before / "config.resolved.yaml", RunConfig)
    assert config.capture.flat_field.views == 2
    assert json.loads((before / "bench_fit.json").read_text())["config_hash"] == config_hash(config)
    # A second time only with --force; a folder that is no run is refused by name.
    capsys.readouterr()
    assert _run_script(monkeypatch, [str(before)]) == 2
    assert "already has a flat_field split (pass --force)" in capsys.readouterr().err
    assert _run_script(monkeypatch, [str(before), "--force"]) == 0
    assert _run_script(monkeypatch, [str(tmp_path / "nowhere")]) == 2
    assert f"{tmp_path / 'nowhere'}: not a synthetic run folder" in capsys.readouterr().err


def test_added_line_target_frames_are_the_frames_a_fresh_synth_writes(tmp_path, monkeypatch):
    """--split line_target: the stripes go through the withheld lens distortion and vignetting
    (seed 2) exactly as a fresh synth with the frames in its config renders them."""
    from recon.config import load_config
    from recon.config.run_config import RunConfig

    before, fresh = _withheld_runs(tmp_path, "line_target")
    assert _run_script(monkeypatch, [str(before), "--split", "line_target"]) == 0
    added = read_split(before, "line_target").images
    assert torch.equal(added, read_split(fresh, "line_target").images)
    truth = json.loads((tmp_path / "truth" / "case.json").read_text())
    fresh_truth = json.loads((tmp_path / "fresh_truth.json").read_text())
    names = sorted(item["name"] for item in truth["realised"]["line_target"])
    assert names == ["lens_distortion", "vignetting"]
    assert truth["realised"]["line_target"] == fresh_truth["realised"]["line_target"]
    config = load_config(before / "config.resolved.yaml", RunConfig)
    assert config.capture.line_target.views == 2 and config.capture.flat_field.views == 0
