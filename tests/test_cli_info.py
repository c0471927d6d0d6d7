"""Tests for recon.cli_info: `recon config keys|show` and `recon effects` (exit codes, output)."""

from __future__ import annotations

from pathlib import Path

import yaml

from recon.cli import main
from recon.config import load_config, to_dict
from recon.config.reference import config_keys
from recon.config.run_config import EFFECT_NAMES, RunConfig
from recon.effects.registry import MODEL_EFFECTS

REPO_ROOT = Path(__file__).resolve().parents[1]
QUICKSTART = REPO_ROOT / "configs" / "quickstart.yaml"


def test_config_keys_lists_every_key_with_its_doc(capsys):
    assert main(["config", "keys"]) == 0
    output = capsys.readouterr().out
    for item in config_keys(RunConfig):
        assert f"{item.key}  {item.type} = {item.default}" in output
        assert item.doc in output
    assert "(undocumented)" not in output


def test_config_keys_markdown_is_docs_config_md(capsys):
    assert main(["config", "keys", "--markdown"]) == 0
    assert capsys.readouterr().out == (REPO_ROOT / "docs" / "config.md").read_text()


def test_config_show_prints_the_resolved_config_with_overrides(capsys):
    overrides = ["fit.geometry.steps=7", "capture.cameras.resolution=[32, 48]"]
    arguments = ["config", "show", str(QUICKSTART)]
    for override in overrides:
        arguments += ["--set", override]
    assert main(arguments) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown == to_dict(load_config(QUICKSTART, RunConfig, overrides=overrides))
    assert shown["fit"]["geometry"]["steps"] == 7
    assert shown["capture"]["cameras"]["resolution"] == [32, 48]
    assert shown["fit"]["texture"]["steps"] == RunConfig().fit.texture.steps  # a default


def test_config_show_reports_a_bad_key_and_a_missing_file(tmp_path, capsys):
    assert main(["config", "show", str(QUICKSTART), "--set", "fit.geometry.stpes=7"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("recon: error: ")
    assert "fit.geometry.stpes" in error and "did you mean 'steps'" in error
    assert main(["config", "show", str(tmp_path / "absent.yaml")]) == 2
    assert "absent.yaml: config file not found" in capsys.readouterr().err


def test_effects_lists_the_catalogue_in_order_with_where_each_acts(capsys):
    assert main(["effects"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [line.split() for line in lines[1 : 1 + len(EFFECT_NAMES)]]
    assert [row[0] for row in rows] == list(EFFECT_NAMES)
    by_name = {row[0]: " ".join(row[1:]) for row in rows}
    for name, effect in MODEL_EFFECTS.items():
        assert by_name[name].startswith(effect.stage)
        assert ("per view" in by_name[name]) == effect.per_view
    assert by_name["noise"].startswith("none")


def test_scenes_lists_every_config_with_its_summary(tmp_path, capsys):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.yaml").write_text("# A first scene: with detail.\n# More.\nname: a\n")
    (tmp_path / "sub" / "b.yaml").write_text("name: b\n")
    long = "# " + "word " * 40 + "\nname: c\n"
    (tmp_path / "c.yaml").write_text(long)
    assert main(["scenes", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == [str(tmp_path / "a.yaml"), "A", "first", "scene"]
    assert lines[1].endswith("...") and len(lines[1].split("  ", 1)[1].strip()) <= 90
    assert lines[2].strip() == str(tmp_path / "sub" / "b.yaml")  # no comment, no summary


def test_scenes_of_the_repository_include_the_quickstart(capsys, monkeypatch):
    monkeypatch.chdir(REPO_ROOT)
    assert main(["scenes"]) == 0
    output = capsys.readouterr().out
    for path in sorted((REPO_ROOT / "configs").rglob("*.yaml")):
        assert str(path.relative_to(REPO_ROOT)) in output
    assert "configs/quickstart.yaml" in output


def test_scenes_reports_a_missing_or_empty_folder(tmp_path, capsys):
    assert main(["scenes", str(tmp_path / "absent")]) == 2
    assert "absent is not a folder" in capsys.readouterr().err
    assert main(["scenes", str(tmp_path)]) == 2
    assert f"no .yaml configs under {tmp_path}" in capsys.readouterr().err
