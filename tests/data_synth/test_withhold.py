"""Withheld mode end to end: the truth goes only to --truth-out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from data_synth.withhold import choose_withheld_effects
from recon.cli import main
from recon.errors import ReconError

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_choice_is_seeded_distinct_and_respects_exclusions():
    first = choose_withheld_effects(3, seed=5)
    assert [e.name for e in first] == [e.name for e in choose_withheld_effects(3, seed=5)]
    assert len({e.name for e in first}) == 3 and "noise" not in {e.name for e in first}
    excluded = choose_withheld_effects(10, seed=5, exclude=["exposure"])
    assert "exposure" not in {e.name for e in excluded}
    with pytest.raises(ReconError, match="asked for 12 effects but only 11"):
        choose_withheld_effects(12, seed=0)


def _config(tmp_path: Path) -> Path:
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 3, "val_views": 0, "test_views": 1})
    config["scene"]["shape"]["resolution"] = 24
    path = tmp_path / "blind.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_withheld_effects_are_written_only_to_the_truth_file(tmp_path):
    out = tmp_path / "run"
    truth = tmp_path / "truth.json"
    code = main(
        [
            "synth",
            str(_config(tmp_path)),
            "--out",
            str(out),
            "--withhold",
            "2",
            "--truth-out",
            str(truth),
            "--set",
            "seed=3",
        ]
    )
    assert code == 0
    record = json.loads(truth.read_text())
    names = [item["name"] for item in record["withheld"]]
    assert len(names) == 2
    ground_truth = json.loads((out / "ground_truth" / "effects.json").read_text())
    assert ground_truth["withheld"] is True and ground_truth["effects"] == []
    # No file of the run folder names a withheld effect.
    for path in out.rglob("*"):
        if path.suffix in (".json", ".yaml", ".md", ".html"):
            text = path.read_text()
            for name in names:
                assert f'"{name}"' not in text, f"{path} reveals {name}"


def test_withhold_without_truth_out_is_an_error(tmp_path, capsys):
    assert (
        main(["synth", str(_config(tmp_path)), "--out", str(tmp_path / "r"), "--withhold", "1"])
        == 2
    )
    assert "--withhold needs --truth-out" in capsys.readouterr().err
