"""The CLI and pipeline: the main job on a tiny config, run folders, config errors."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import yaml

from recon.cli import main
from recon.io.datasets import read_nerf_synthetic

REPO_ROOT = Path(__file__).resolve().parents[2]


def _tiny_config(tmp_path: Path, **capture) -> Path:
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 3, "val_views": 1, "test_views": 1, **capture})
    config["scene"]["shape"]["resolution"] = 24
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_run_writes_a_readable_dataset_and_run_records(tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(_tiny_config(tmp_path)), "--out", str(out), "--device", "cpu"]) == 0
    captures = read_nerf_synthetic(out / "dataset", "train", background=None)
    assert captures.images.shape == (3, 32, 32, 3)
    coverage = captures.masks.mean()
    assert 0.05 < float(coverage) < 0.9  # the torus is in view and not filling the frame
    assert (out / "captures_contact_sheet.png").stat().st_size > 0
    assert (out / "ground_truth" / "reference.obj").exists()
    assert not (out / "dataset" / "ground_truth").exists()  # truth beside, never inside
    environment = json.loads((out / "env.json").read_text())
    assert environment["device"] == "cpu" and len(environment["config_hash"]) == 12
    resolved = yaml.safe_load((out / "config.resolved.yaml").read_text())
    assert resolved["capture"]["train_views"] == 3


def test_same_config_and_seed_give_the_same_images(tmp_path):
    config = _tiny_config(tmp_path, val_views=0, test_views=0)
    for name in ("a", "b"):
        assert main(["run", str(config), "--out", str(tmp_path / name), "--device", "cpu"]) == 0
    first = read_nerf_synthetic(tmp_path / "a" / "dataset", "train", background=None)
    second = read_nerf_synthetic(tmp_path / "b" / "dataset", "train", background=None)
    assert (first.images == second.images).all()


def test_refuses_to_overwrite_a_run_folder(tmp_path, capsys):
    config = _tiny_config(tmp_path, val_views=0, test_views=0)
    out = tmp_path / "run"
    assert main(["run", str(config), "--out", str(out)]) == 0
    marker = out / "keep.txt"
    marker.write_text("precious")
    assert main(["run", str(config), "--out", str(out)]) == 2
    assert "already exists and is not empty; pass --force" in capsys.readouterr().err
    assert marker.read_text() == "precious"
    assert main(["run", str(config), "--out", str(out), "--force"]) == 0
    assert not marker.exists()


def test_config_errors_name_file_key_and_suggestion(tmp_path, capsys):
    config = _tiny_config(tmp_path)
    assert main(["run", str(config), "--set", "capture.train_veiws=3"]) == 2
    error = capsys.readouterr().err
    assert "tiny.yaml" in error and "capture.train_veiws" in error
    assert "did you mean 'train_views'" in error
    assert main(["run", str(config), "--set", "capture.cameras.fov_deg=wide"]) == 2
    assert "capture.cameras.fov_deg: expected float" in capsys.readouterr().err
    assert main(["run", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in capsys.readouterr().err


# The layering of recon's top-level modules and packages, lowest first; a module may import
# its own layer and the layers below. io sits above camera and mesh because its readers build
# Cameras and Meshes; stages (the only modules that read or write a run folder) sit on the
# library packages they call; sweep schedules runs (and scores blind diagnoses, recon.sweep.scoring);
# the CLI modules sit on top. The benchmarks are a package of their own above recon and
# data_synth (test_benchmarks_sit_above_everything_and_scripts_use_public_names).
LAYERS = [
    ["errors"],
    ["config"],
    ["camera", "mesh"],
    ["io"],
    ["render"],
    ["effects"],
    ["optimize", "metrics"],
    ["diagnose", "report"],
    ["stages"],
    ["preflight"],
    ["pipeline"],
    ["sweep"],
    ["cli_info"],
    ["cli"],
    ["__main__"],
]


def _top_level_name(path: Path) -> str:
    return path.relative_to(REPO_ROOT / "recon").with_suffix("").parts[0]


def test_imports_point_one_way():
    """recon never imports data_synth; lower layers never import higher ones; every module of
    recon has a layer (a new one must be placed in LAYERS, there is no skip)."""
    rank = {name: index for index, layer in enumerate(LAYERS) for name in layer}
    for path in (REPO_ROOT / "recon").rglob("*.py"):
        own = _top_level_name(path)
        if own == "__init__":
            continue
        assert own in rank, f"{path}: module {own!r} has no layer in LAYERS"
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
                if node.module == "recon":
                    names = [f"recon.{alias.name}" for alias in node.names]
            for name in names:
                assert not name.startswith("data_synth"), f"{path} imports {name}"
                parts = name.split(".")
                if parts[0] != "recon" or len(parts) < 2 or parts[1] == "__version__":
                    continue
                target = parts[1]
                assert target in rank, f"{path} imports {name}, which has no layer"
                assert rank[target] <= rank[own], f"{path} ({own}) imports {name}"


# The packages whose private names (a leading underscore) scripts/ must not import.
OWN_PACKAGES = ("recon", "data_synth", "benchmarks")


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, imported names) of every absolute import in a file; names is empty for
    `import module`."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.module, [alias.name for alias in node.names]))
    return found


def test_benchmarks_sit_above_everything_and_scripts_use_public_names():
    """benchmarks/ may import anything and nothing imports it: not recon, not data_synth. The
    one-off maintenance scripts in scripts/ use only public names of recon, data_synth and
    benchmarks (a private function a script needs belongs in a public API or in benchmarks)."""
    for package in ("recon", "data_synth"):
        for path in (REPO_ROOT / package).rglob("*.py"):
            for module, _ in _imports(path):
                assert module.split(".")[0] != "benchmarks", f"{path} imports {module}"
    assert (REPO_ROOT / "benchmarks" / "__init__.py").exists()
    scripts = sorted((REPO_ROOT / "scripts").glob("*.py"))
    assert scripts, "scripts/ holds the one-off maintenance scripts"
    for path in scripts:
        for module, names in _imports(path):
            parts = module.split(".")
            if parts[0] not in OWN_PACKAGES:
                continue
            private = [part for part in parts[1:] if part.startswith("_")]
            private += [name for name in names if name.startswith("_")]
            assert not private, f"{path} imports private {private} from {module}"


def test_fit_an_external_dataset_then_compare_with_a_baseline(tmp_path, capsys):
    config = _tiny_config(tmp_path, val_views=0, test_views=2)
    captures = tmp_path / "captures"
    assert main(["synth", str(config), "--out", str(captures)]) == 0
    run = tmp_path / "fitted"
    fit_settings = [
        "--set",
        "fit.geometry.steps=8",
        "--set",
        "fit.geometry.resolutions=[32]",
        "--set",
        "fit.texture.steps=2",
        "--set",
        "fit.texture.texture_size=64",
        "--set",
        "fit.hull_resolution=32",
    ]
    code = main(
        ["fit", str(config), "--data", str(captures / "dataset"), "--out", str(run)] + fit_settings
    )
    assert code == 0
    assert not (run / "dataset").exists()  # the external dataset is read in place
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["image"]["psnr"] > 10
    baseline = tmp_path / "baseline.yaml"
    assert main(["compare", str(run), "--baseline", str(baseline), "--write"]) == 0
    assert main(["compare", str(run), "--baseline", str(baseline)]) == 0
    baseline.write_text("image.psnr: {min: 99.0}\n")
    assert main(["compare", str(run), "--baseline", str(baseline)]) == 1
    assert "REGRESSION" in capsys.readouterr().out
    baseline.write_text("image.psnr: {minimum: 1}\n")
    assert main(["compare", str(run), "--baseline", str(baseline)]) == 2
