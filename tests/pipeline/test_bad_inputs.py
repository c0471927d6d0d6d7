"""The bad-input catalogue: every way a user's command can go wrong ends as one `recon: error:`
line naming the file or key, exit code 2, and nothing outside the run folder changed.

Each case runs in a workspace holding a user's own files, a recon run folder and a dataset; the
workspace's files are hashed before and after, so a case that deletes or rewrites anything it
should not fails whatever its exit code.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from recon.cli import main

REPO_ROOT = Path(__file__).resolve().parents[2]


def tiny_config(**capture) -> dict:
    """The quickstart scene at 32 px with a few views: synth takes about a second."""
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth"]
    config["device"] = "cpu"
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 2, "val_views": 1, "test_views": 1, **capture})
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 16
    return config


def snapshot(root: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under root (folders by their files)."""
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """A workspace made once: user files, a synthesised run folder (run/) and its dataset."""
    root = tmp_path_factory.mktemp("workspace")
    (root / "notes.txt").write_text("a user's notes\n")
    (root / "tiny.yaml").write_text(yaml.safe_dump(tiny_config()))
    (root / "notrun").mkdir()
    (root / "notrun" / "thesis.tex").write_text("\\documentclass{article}\n")
    assert main(["synth", str(root / "tiny.yaml"), "--out", str(root / "run")]) == 0
    return root


@pytest.fixture
def workspace(template, tmp_path, monkeypatch) -> Path:
    root = tmp_path / "workspace"
    shutil.copytree(template, root)
    monkeypatch.chdir(root)
    return root


@dataclass
class Case:
    """argv (relative to the workspace), the expected exit code and words of the message;
    prepare(workspace) may add files first; changes: paths allowed to change."""

    argv: list[str]
    words: list[str]
    prepare: Callable[[Path], None] | None = None
    code: int = 2
    changes: list[str] = field(default_factory=list)


def _write(relative: str, text: str) -> Callable[[Path], None]:
    def prepare(root: Path) -> None:
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        (root / relative).write_text(text)

    return prepare


def _config(relative: str, **changes) -> Callable[[Path], None]:
    """A variant of tiny.yaml: changes are dotted keys -> values."""

    def prepare(root: Path) -> None:
        config = tiny_config()
        for dotted, value in changes.items():
            target = config
            *parents, last = dotted.split(".")
            for key in parents:
                target = target.setdefault(key, {})
            target[last] = value
        (root / relative).write_text(yaml.safe_dump(config))

    return prepare


def _binary_obj(root: Path) -> None:
    (root / "scan.obj").write_bytes(b"PK\x03\x04\x00\x00binary payload\x00\xff" * 64)
    _config("binary.yaml", **{"scene.shape": {"procedural": None, "mesh_path": "scan.obj"}})(root)


def _sizes_differ(root: Path) -> None:
    """A dataset whose test split is 48 px while train is 32 px."""
    shutil.copytree(root / "run" / "dataset", root / "mixed")
    config = tiny_config(train_views=1, val_views=0, test_views=1)
    config["capture"]["cameras"]["resolution"] = [48, 48]
    (root / "big.yaml").write_text(yaml.safe_dump(config))
    assert main(["synth", "big.yaml", "--out", "big"]) == 0
    shutil.rmtree(root / "mixed" / "test")
    shutil.copytree(root / "big" / "dataset" / "test", root / "mixed" / "test")
    shutil.copy(root / "big" / "dataset" / "transforms_test.json", root / "mixed")
    shutil.rmtree(root / "big")
    (root / "big.yaml").unlink()


def _tiny_images(root: Path) -> None:
    """A dataset whose views are 8 x 8 pixels: too small to evaluate."""
    from PIL import Image

    shutil.copytree(root / "run" / "dataset", root / "thumbs")
    for path in (root / "thumbs").rglob("*.png"):
        with Image.open(path) as image:
            small = image.resize((8, 8))
        small.save(path)


def _baseline(text: str) -> Callable[[Path], None]:
    def prepare(root: Path) -> None:
        (root / "run" / "metrics.json").write_text(
            json.dumps({"image": {"psnr": 30.0, "ssim": 0.9}, "geometry": {"chamfer_l1": 0.01}})
        )
        (root / "baseline.yaml").write_text(text)

    return prepare


CASES = {
    # --force and the folders it must never replace.
    "force on the working directory": Case(
        ["synth", "tiny.yaml", "--out", ".", "--force"], ["working directory"]
    ),
    "force on a folder recon did not create": Case(
        ["synth", "tiny.yaml", "--out", "notrun", "--force"], ["not created by recon", "notrun"]
    ),
    "force on the folder holding the input dataset": Case(
        ["fit", "tiny.yaml", "--data", "run/dataset", "--out", "run", "--force"],
        ["holds this run's input", "run/dataset"],
    ),
    "force with a mistyped mesh path keeps the old run": Case(
        ["synth", "typo.yaml", "--out", "run", "--force"],
        ["scene.shape.mesh_path", "spot.obj: file not found"],
        prepare=_config(
            "typo.yaml", **{"scene.shape": {"procedural": None, "mesh_path": "meshes/spot.obj"}}
        ),
    ),
    "force on a symbolic link": Case(
        ["synth", "tiny.yaml", "--out", "link", "--force"],
        ["symbolic link"],
        prepare=lambda root: (root / "link").symlink_to(root / "run"),
    ),
    "an existing run folder without --force": Case(
        ["synth", "tiny.yaml", "--out", "run"], ["already exists and is not empty", "--force"]
    ),
    # Files recon must not overwrite.
    "truth-out names an existing file": Case(
        ["synth", "tiny.yaml", "--out", "new", "--withhold", "1", "--truth-out", "tiny.yaml"],
        ["--truth-out tiny.yaml", "already exists"],
    ),
    "truth-out with force names a file recon did not write": Case(
        ["synth", "tiny.yaml", "--out", "new", "--withhold", "1", "--truth-out", "notes.txt"]
        + ["--force"],
        ["notes.txt", "not a truth file recon wrote"],
    ),
    "truth-out inside the run folder": Case(
        ["synth", "tiny.yaml", "--out", "new", "--withhold", "1", "--truth-out", "new/t.json"],
        ["must lie outside the run folder"],
    ),
    "compare --write over an existing baseline": Case(
        ["compare", "run", "--baseline", "baseline.yaml", "--write"],
        ["baseline.yaml", "already exists", "--force"],
        prepare=_baseline("image.psnr: {min: 20}\n"),
    ),
    # Inputs that used to fail late or with a traceback.
    "baseline bound that is not a number": Case(
        ["compare", "run", "--baseline", "baseline.yaml"],
        ["image.psnr.min", "expected a number", "'abc'"],
        prepare=_baseline("image.psnr: {min: abc}\n"),
    ),
    "baseline naming a metric the run does not have": Case(
        ["compare", "run", "--baseline", "baseline.yaml"],
        ["image.psrn", "did you mean image.psnr"],
        prepare=_baseline("image.psrn: {min: 20}\n"),
    ),
    "empty list of fit resolutions": Case(
        ["run", "tiny.yaml", "--out", "new", "--set", "fit.geometry.resolutions=[]"],
        ["fit.geometry.resolutions", "at least one resolution"],
    ),
    "a view too small to evaluate": Case(
        ["run", "tiny.yaml", "--out", "new", "--set", "capture.cameras.resolution=[4,4]"],
        ["capture.cameras.resolution", "must be in [16, 8192], got 4"],
    ),
    "a binary file named .obj": Case(
        ["synth", "binary.yaml", "--out", "new"],
        ["scan.obj", "expected a text OBJ file", "binary data"],
        prepare=_binary_obj,
    ),
    "image sizes that differ between splits": Case(
        ["fit", "tiny.yaml", "--data", "mixed", "--out", "new"],
        ["image sizes differ", "train 32x32", "test 48x48"],
        prepare=_sizes_differ,
    ),
    "a dataset with views too small to evaluate": Case(
        ["fit", "tiny.yaml", "--data", "thumbs", "--out", "new"],
        ["thumbs", "8x8", "at least 16 px"],
        prepare=_tiny_images,
    ),
    "a dataset folder that is not one": Case(
        ["fit", "tiny.yaml", "--data", "notrun", "--out", "new"],
        ["notrun", "not a dataset recon reads"],
    ),
    # Flags and keys that cannot apply are errors, not silently ignored.
    "withhold on a given dataset": Case(
        ["run", "tiny.yaml", "--data", "run/dataset", "--out", "new", "--withhold", "1"]
        + ["--truth-out", "truth.json"],
        ["--withhold 1", "fits the given dataset"],
    ),
    "truth-out without withhold": Case(
        ["synth", "tiny.yaml", "--out", "new", "--truth-out", "truth.json"],
        ["--truth-out truth.json", "only with --withhold"],
    ),
    "resume with a config and overrides": Case(
        ["run", "tiny.yaml", "--resume", "run", "--set", "seed=3"],
        ["--resume run", "CONFIG tiny.yaml", "--set", "cannot apply"],
    ),
    "texture_path on a procedural shape": Case(
        ["synth", "textured.yaml", "--out", "new"],
        ["scene.shape.texture_path", "applies only to a mesh_path shape"],
        prepare=_config(
            "textured.yaml", **{"scene.shape": {"procedural": "torus", "texture_path": "x.png"}}
        ),
    ),
    "resume of a folder that is no run": Case(
        ["run", "--resume", "notrun"], ["notrun", "config.resolved.yaml"]
    ),
    "evaluate a folder that is no run": Case(["evaluate", "notrun"], ["notrun"]),
    "a missing config file": Case(["run", "missing.yaml"], ["missing.yaml"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_a_clear_error_that_changes_nothing(name, workspace, capsys):
    case = CASES[name]
    if case.prepare is not None:
        case.prepare(workspace)
    before = snapshot(workspace)
    capsys.readouterr()
    code = main(case.argv)
    error = capsys.readouterr().err
    assert code == case.code, error
    message = [line for line in error.splitlines() if line.startswith("recon: error: ")]
    assert len(message) == 1, error
    for word in case.words:
        assert word in message[0], f"{word!r} not in {message[0]!r}"
    assert "Traceback" not in error
    after = snapshot(workspace)
    assert after == before, "files changed: " + ", ".join(
        sorted(set(before.items()) ^ set(after.items()), key=str)[:5].__repr__()
    )
    # A failed check leaves no run folder and no replaced run aside.
    assert not (workspace / "new").exists()
    assert not list(workspace.glob(".*.replaced-*"))


def test_force_replaces_a_recon_run_only_after_its_checks(workspace, capsys):
    """The one case --force is for: a run folder recon made is replaced by the new run."""
    (workspace / "run" / "scratch.txt").write_text("inside a recon run folder")
    assert main(["synth", "tiny.yaml", "--out", "run", "--force"]) == 0
    assert not (workspace / "run" / "scratch.txt").exists()
    assert (workspace / "run" / ".recon-run").is_file()
    assert (workspace / "run" / "dataset" / "transforms_train.json").is_file()
    assert not list(workspace.glob(".*.replaced-*"))
    assert (workspace / "notes.txt").read_text() == "a user's notes\n"


def test_truth_out_with_force_replaces_recon_own_truth(workspace):
    truth = workspace / "truth.json"
    argv = ["synth", "tiny.yaml", "--withhold", "1", "--truth-out", str(truth)]
    assert main(argv + ["--out", "first"]) == 0
    written = json.loads(truth.read_text())
    assert written["withheld"]
    assert main(argv + ["--out", "second"]) == 2  # exists: refused without --force
    assert main(argv + ["--out", "second", "--force"]) == 0


def test_later_stage_overrides_never_rewrite_the_fit_record(tiny_run, tmp_path):
    """report/evaluate --set: recorded beside the run, config.resolved.yaml and env.json's hash
    untouched."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    resolved = (run / "config.resolved.yaml").read_bytes()
    config_hash = json.loads((run / "env.json").read_text())["config_hash"]
    assert main(["report", str(run), "--set", "name=renamed", "--device", "cpu"]) == 0
    assert (run / "config.resolved.yaml").read_bytes() == resolved
    assert json.loads((run / "env.json").read_text())["config_hash"] == config_hash
    records = [
        json.loads(line) for line in (run / "stage_overrides.jsonl").read_text().splitlines()
    ]
    assert [(record["stage"], record["overrides"]) for record in records] == [
        ("report", ["name=renamed"])
    ]
    assert records[0]["config_hash"] != config_hash


def test_diagnose_refreshes_the_report(tiny_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "diagnosis.json").unlink(missing_ok=True)  # other tests diagnose tiny_run in place
    assert main(["report", str(run), "--device", "cpu"]) == 0
    assert "Gap diagnosis" not in (run / "report.md").read_text()
    assert main(["diagnose", str(run), "--refit", "none", "--device", "cpu"]) == 0
    verdict = json.loads((run / "diagnosis.json").read_text())["verdict"]
    for report in ("report.md", "report.html"):
        text = (run / report).read_text()
        assert "Gap diagnosis" in text and verdict.split(" ")[0] in text
    assert "report:" in capsys.readouterr().out
