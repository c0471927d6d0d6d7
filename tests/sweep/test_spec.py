"""The sweep file's validation (exit 2, message naming the file and key) and trial expansion."""

from __future__ import annotations

import pytest
import yaml
from sweep_helpers import write_sweep

from recon.cli import main
from recon.sweep.spec import load_sweep
from recon.sweep.trials import expand


@pytest.mark.parametrize(
    "changes, expected",
    [
        ({"grdi": {"seed": [1]}}, "grdi: unknown key (did you mean 'grid'?)"),
        ({"grid": {}}, "grid: empty grid"),
        ({"grid": {"fit.geometry.steps": []}}, "grid.fit.geometry.steps: empty list of values"),
        ({"metrics": ["loss"]}, "metrics[0]: expected 'SOURCE.KEY'"),
        ({"metrics": []}, "metrics: expected at least one metric"),
        ({"seeds": []}, "seeds: expected at least one seed"),
        ({"cases": [["fit.geometry.steps"]]}, "cases[0][0]: expected KEY=VALUE"),
        ({"cpus_per_trial": 0}, "cpus_per_trial: must be >= 1"),
        ({"kind": "diagnosis"}, "withhold: kind: diagnosis needs withhold"),
        ({"base": "missing.yaml"}, "base: config file missing.yaml not found"),
    ],
)
def test_invalid_sweep_files_exit_2_naming_the_key(tmp_path, capsys, changes, expected):
    sweep = write_sweep(tmp_path, tmp_path / "out", **changes)
    assert main(["sweep", str(sweep)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("recon: error: ") and sweep.name in error
    assert expected in error
    assert not (tmp_path / "out").exists()


def test_bad_override_values_are_reported_before_anything_runs(tmp_path, capsys):
    sweep = write_sweep(tmp_path, tmp_path / "out", set=["fit.geometry.stpes=3"])
    # The override is checked when the trial's config is built: the trial fails, recorded.
    assert main(["sweep", str(sweep)]) == 1
    captured = capsys.readouterr()
    assert "fit.geometry.stpes" in captured.out
    text = (tmp_path / "out" / "results.md").read_text()
    assert "4 trials, 4 failed" in text and "did you mean 'steps'" in text


def test_an_existing_sweep_folder_needs_resume(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    sweep = write_sweep(tmp_path, out)
    assert main(["sweep", str(sweep)]) == 2
    assert "holds no sweep" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "mine"
    assert main(["sweep", str(sweep), "--backend", "local", "--address", "x:1"]) == 2
    assert "--address: only with --backend ray" in capsys.readouterr().err
    assert (
        main(["sweep", str(sweep), "--backend", "ray", "--address", "x:1", "--num-cpus", "2"]) == 2
    )
    assert "--num-cpus: only for a local Ray" in capsys.readouterr().err
    assert main(["sweep", str(sweep), "--max-concurrent", "0"]) == 2
    assert "--max-concurrent: expected N >= 1, got 0" in capsys.readouterr().err


def test_trial_ids_are_stable_when_the_grid_grows(tmp_path):
    small = expand(load_sweep(write_sweep(tmp_path, tmp_path / "a")))
    bigger_file = write_sweep(tmp_path, tmp_path / "b", grid={"fit.geometry.steps": [1, 2, 3]})
    bigger = expand(load_sweep(bigger_file))
    assert len(small) == 4 and len(bigger) == 6
    assert {trial.trial_id for trial in small} < {trial.trial_id for trial in bigger}
    assert len({trial.trial_id for trial in bigger}) == 6
    first = small[0]
    assert first.parameters == {"fit.geometry.steps": 1, "seed": 0}
    assert first.overrides[-2:] == ("fit.geometry.steps=1", "seed=0")


def test_grid_values_become_set_overrides(tmp_path):
    sweep = write_sweep(
        tmp_path,
        tmp_path / "out",
        grid={"capture.cameras.resolution": [[32, 32]], "scene.shape.procedural": ["sphere"]},
        withhold=[[], ["exposure", "vignetting"]],
        seeds=[3],
    )
    trials = expand(load_sweep(sweep))
    assert [trial.withhold for trial in trials] == [(), ("exposure", "vignetting")]
    assert trials[1].parameters["withhold"] == "exposure+vignetting"
    assert "capture.cameras.resolution=[32, 32]" in trials[0].overrides
    assert "scene.shape.procedural=sphere" in trials[0].overrides
    # Every override parses with the run config's loader.
    from recon.config import load_config
    from recon.config.run_config import RunConfig

    config = load_config(trials[0].base, RunConfig, overrides=trials[0].overrides)
    assert config.capture.cameras.resolution == [32, 32] and config.seed == 3
    assert yaml.safe_load(sweep.read_text())["seeds"] == [3]


def test_the_ray_backend_without_ray_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    sweep = write_sweep(tmp_path, tmp_path / "out")
    assert main(["sweep", str(sweep), "--backend", "ray"]) == 2
    assert "pip install -e '.[ray]'" in capsys.readouterr().err


def test_the_example_sweep_files_are_valid(monkeypatch):
    from sweep_helpers import REPO_ROOT

    monkeypatch.chdir(REPO_ROOT)  # their paths are relative to the repository root
    sizes = {
        path.name: len(expand(load_sweep(path)))
        for path in sorted((REPO_ROOT / "configs" / "sweeps").glob("*.yaml"))
    }
    assert sizes == {"blind.yaml": 48, "calibration.yaml": 3, "tiny.yaml": 6}
