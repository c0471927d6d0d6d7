"""benchmarks/blind/real.py: real photos with known camera effects injected in linear space."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.blind.real import derive_real_dataset, split_realised
from recon.errors import ReconError
from recon.io.datasets import read_llff
from recon.io.images import write_png

SHARED_CAPTURE = Path(__file__).resolve().parents[3].parent / "shared" / "captures"


def _llff_folder(folder: Path, views: int = 6, size: int = 16) -> Path:
    """A tiny LLFF folder: identity-rotation cameras along x, a grey ramp per view, full masks."""
    (folder / "images").mkdir(parents=True)
    (folder / "masks").mkdir()
    table = np.zeros((views, 17))
    for index in range(views):
        pose = np.zeros((3, 5))
        pose[:, :3] = np.eye(3)
        pose[:, 3] = [0.1 * index, 0.0, 3.0]
        pose[:, 4] = [size, size, size]
        table[index, :15] = pose.reshape(-1)
        table[index, 15:] = [1.0, 5.0]
        ramp = torch.linspace(0.05, 0.3, size)[None, :, None].expand(size, size, 3).clone()
        write_png(folder / "images" / f"view_{index:02d}.png", ramp)
        write_png(folder / "masks" / f"view_{index:02d}.png", torch.ones(size, size, 1))
    np.save(folder / "poses_bounds.npy", table)
    return folder


def test_exposure_is_injected_in_linear_space_and_split_like_recon(tmp_path):
    source = _llff_folder(tmp_path / "photos")
    truth = derive_real_dataset(
        source,
        tmp_path / "derived",
        tmp_path / "truth.json",
        ["exposure"],
        seed=3,
        max_resolution=None,
        view_every=1,
        holdout_every=4,
    )
    before = read_llff(source)
    after = read_llff(tmp_path / "derived")
    # Per view, the linear ratio of the derived to the original photo is the injected ratio
    # (up to 8-bit quantisation of both).
    measured = (after.images.mean(dim=(1, 2, 3)) / before.images.mean(dim=(1, 2, 3))).tolist()
    realised = truth["realised"]
    # recon's LLFF split: index % holdout_every == 0 is test (views 0 and 4 of 6).
    assert len(realised["test"][0]["parameters"]["ratios"]) == 2
    assert len(realised["train"][0]["parameters"]["ratios"]) == 4
    ratios = [None] * 6
    for position, index in enumerate([0, 4]):
        ratios[index] = realised["test"][0]["parameters"]["ratios"][position]
    for position, index in enumerate([1, 2, 3, 5]):
        ratios[index] = realised["train"][0]["parameters"]["ratios"][position]
    assert measured == pytest.approx(ratios, rel=0.03)
    assert max(ratios) / min(ratios) > 1.1  # the effect is really there
    assert json.loads((tmp_path / "truth.json").read_text())["withheld"][0]["name"] == "exposure"
    assert not any(
        "exposure" in path.read_bytes().decode("latin-1")
        for path in (tmp_path / "derived").rglob("*.npy")
    )


def test_untouched_photos_and_view_subset(tmp_path):
    source = _llff_folder(tmp_path / "photos")
    truth = derive_real_dataset(
        source, tmp_path / "clean", tmp_path / "truth.json", [], 0, None, 2, 8
    )
    assert truth["withheld"] == [] and truth["views"] == ["view_00", "view_02", "view_04"]
    before, after = read_llff(source), read_llff(tmp_path / "clean")
    assert torch.allclose(after.images, before.images[[0, 2, 4]], atol=1 / 255)
    assert torch.allclose(after.cameras.world_to_cam, before.cameras.world_to_cam[[0, 2, 4]])


def test_truth_inside_the_derived_dataset_is_refused(tmp_path):
    source = _llff_folder(tmp_path / "photos")
    with pytest.raises(ReconError, match="truth must lie outside"):
        derive_real_dataset(
            source, tmp_path / "derived", tmp_path / "derived" / "t.json", [], 0, None, 1, 8
        )
    with pytest.raises(ReconError, match="must not go inside"):
        derive_real_dataset(source, source / "sub", tmp_path / "t.json", [], 0, None, 1, 8)


def test_split_realised_keeps_scalars_and_splits_per_view_lists():
    from data_synth.effects.base import AppliedEffect

    applied = [AppliedEffect("white_balance", {"gains": [1, 2, 3], "spread": 0.1})]
    split = split_realised(applied, 3, holdout_every=2)
    assert split["test"][0]["parameters"] == {"gains": [1, 3], "spread": 0.1}
    assert split["train"][0]["parameters"] == {"gains": [2], "spread": 0.1}


@pytest.mark.skipif(not SHARED_CAPTURE.is_dir(), reason="../shared/captures is absent")
def test_the_shared_capture_derives_at_a_small_size(tmp_path):
    truth = derive_real_dataset(
        SHARED_CAPTURE / "ethiopian_head",
        tmp_path / "head",
        tmp_path / "truth.json",
        ["vignetting"],
        0,
        32,
        8,
        8,
    )
    derived = read_llff(tmp_path / "head")
    assert derived.images.shape[1:3] == (32, 32) and len(derived.names) == len(truth["views"])
    assert derived.mask_source == "masks"
