"""benchmarks/blind/collect.py: a stored fit is kept when only defaulted fields joined the
config, and --rediagnose never fits."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import yaml

from benchmarks.blind.cases import BlindCase
from benchmarks.blind.collect import (
    _stored,
    finished_case,
    fit_config_difference,
    same_fit_config,
    truth_path,
)
from recon.config import dump_resolved
from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.run_folder import RunPaths


def _stored_config(tmp_path, edit) -> tuple:
    """A resolved config written as a stored fit had it, edited by edit(dict), and the config."""
    config = replace(RunConfig(), seed=3)
    path = tmp_path / "config.resolved.yaml"
    dump_resolved(config, path)
    stored = yaml.safe_load(path.read_text())
    edit(stored)
    path.write_text(yaml.safe_dump(stored))
    return path, config


def test_a_field_added_at_its_default_is_the_same_fit(tmp_path):
    path, config = _stored_config(tmp_path, lambda stored: stored["dataset"].pop("sfm"))
    assert same_fit_config(path, config)
    path, config = _stored_config(tmp_path, lambda stored: stored["diagnose"].clear())
    assert same_fit_config(path, config)  # the diagnose section never changes the fit


def test_a_changed_value_is_another_fit_and_named(tmp_path):
    def edit(stored):
        stored["seed"] = 4

    path, config = _stored_config(tmp_path, edit)
    assert fit_config_difference(path, config) == "seed: stored 4, now 3"
    assert same_fit_config(path, config, ignore=("seed",))


def test_pbr_settings_do_not_change_a_lambertian_fit(tmp_path):
    def edit(stored):
        stored["fit"]["pbr"]["environment_size"] = [8, 16]

    path, config = _stored_config(tmp_path, edit)
    assert config.fit.material == "lambert"
    assert same_fit_config(path, config)
    pbr_config = replace(config, fit=replace(config.fit, material="pbr"))
    path, _ = _stored_config(
        tmp_path, lambda stored: (edit(stored), stored["fit"].update(material="pbr"))
    )
    assert fit_config_difference(path, pbr_config) == (
        f"fit.pbr.environment_size: stored [8, 16], now {pbr_config.fit.pbr.environment_size!r}"
    )


def test_rediagnose_refuses_to_refit(tmp_path):
    def edit(stored):
        stored["seed"] = 4

    path, config = _stored_config(tmp_path, edit)
    paths = RunPaths(tmp_path)
    record = tmp_path / "bench_case.json"
    record.write_text('{"config_hash": "old"}')
    paths.fitted_mesh.parent.mkdir(parents=True)
    paths.fitted_mesh.write_text("")
    assert _stored(record, "new", "none", paths, config, "cpu") is None  # refit
    with pytest.raises(ReconError, match=r"--rediagnose: .*\(seed: stored 4, now 3\)"):
        _stored(record, "new", "none", paths, config, "cpu", rediagnose=True)


def test_a_copied_benchmark_folder_is_scored_from_itself(tmp_path):
    # The records of a copied folder still name the original: scoring must read the copy.
    case = BlindCase("own", "torus", ("exposure",), 0)
    folder = tmp_path / "copy" / "cases" / case.folder_name
    folder.mkdir(parents=True)
    (folder / "diagnosis.json").write_text("{}")
    stale = {"run_folder": "/original/cases/x", "truth_file": "/original/truth/x.json"}
    (folder / "bench_case.json").write_text(json.dumps(stale))
    record = finished_case(case, tmp_path / "copy")
    assert record["run_folder"] == str(folder)
    assert record["truth_file"] == str(truth_path(tmp_path / "copy", case))


def test_a_score_reads_stored_cases_whose_scene_inputs_are_absent(tmp_path, monkeypatch):
    """--score-only needs the stored evidence only: cases collected where ../shared was, scored
    where it is not, are read; a case never collected is noted with why it could not be."""
    from benchmarks.blind import cases as blind_cases
    from benchmarks.diagnose_blind import stored_cases

    monkeypatch.setattr(blind_cases, "missing_inputs", lambda scene: "../shared/meshes absent")
    stored = BlindCase("own", "spot", ("exposure",), 0)
    folder = tmp_path / "cases" / stored.folder_name
    folder.mkdir(parents=True)
    (folder / "diagnosis.json").write_text("{}")
    (folder / "bench_case.json").write_text("{}")
    absent = BlindCase("own", "spot", ("exposure",), 1)
    collected, skipped = stored_cases([stored, absent], tmp_path)
    assert [record["run_folder"] for record in collected] == [str(folder)]
    assert skipped == [{"case": absent.to_json(), "reason": "../shared/meshes absent"}]
