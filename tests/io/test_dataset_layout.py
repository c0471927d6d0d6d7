"""DatasetLayout: a dataset's kind, splits, held-out split and extra captures, for every layout."""

from __future__ import annotations

import pytest

from recon.errors import DatasetError
from recon.io.dataset_layout import DatasetLayout
from recon.io.run_folder import RunPaths


def _nerf_synthetic(folder, *splits):
    folder.mkdir(parents=True, exist_ok=True)
    for split in splits:
        (folder / f"transforms_{split}.json").write_text('{"frames": []}')
    return DatasetLayout(folder)


def test_nerf_synthetic_splits_held_out_split_and_extras(tmp_path):
    layout = _nerf_synthetic(tmp_path / "a", "train", "val", "test", "relight", "flat_field")
    assert layout.kind == "nerf_synthetic"
    assert layout.has_split("train") and layout.has_split("test")
    assert layout.held_out_split == "test"
    assert layout.has_relight and layout.has_flat_field
    assert layout.relight_lighting == tmp_path / "a" / "lighting_relight.json"
    assert [path.name for path in layout.split_files()][:2] == [
        "transforms_flat_field.json",
        "transforms_relight.json",
    ]
    without_test = _nerf_synthetic(tmp_path / "b", "train", "val")
    assert without_test.held_out_split == "val" and not without_test.has_relight


def test_llff_has_train_and_test_by_index_and_no_extras(tmp_path):
    (tmp_path / "poses_bounds.npy").write_bytes(b"")
    layout = DatasetLayout.of(tmp_path)
    assert layout.kind == "llff"
    assert layout.has_split("train") and layout.held_out_split == "test"
    assert not layout.has_split("val") and not layout.has_relight and not layout.has_flat_field
    assert layout.split_files() == []


def test_a_missing_folder_has_no_splits_and_an_unknown_one_is_named(tmp_path):
    assert not DatasetLayout(tmp_path / "missing").has_split("train")
    with pytest.raises(DatasetError, match="not a dataset recon reads"):
        _ = DatasetLayout(tmp_path).kind


def test_run_paths_ask_their_dataset_layout(tmp_path):
    _nerf_synthetic(tmp_path / "run" / "dataset", "train", "test")
    assert RunPaths(tmp_path / "run").dataset_layout.held_out_split == "test"
    external = RunPaths(tmp_path / "run", tmp_path / "elsewhere")
    assert external.dataset_layout.folder == tmp_path / "elsewhere"
