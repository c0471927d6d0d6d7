"""recon.io.datasets: an LLFF folder's prepared `images_N/` downscales are read instead of the
full-size photos when dataset.max_resolution allows it (a large capture loads from its small
copies), with intrinsics of the size read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from recon.camera import look_at, rigid_inverse
from recon.config.run_config import DatasetConfig
from recon.io.datasets import llff_downscale_for, read_captures
from recon.io.images import write_png


def llff_capture(folder: Path, size: tuple[int, int], count: int = 3) -> None:
    """poses_bounds.npy (focal 40 px at size) + images/ + masks/ of count views."""
    eyes = torch.tensor([[0.3 * index, 0.1, 4.0] for index in range(count)])
    cam_to_world = rigid_inverse(look_at(eyes, torch.zeros(count, 3)).double()).numpy()
    right, down, forward, centre = (cam_to_world[:, :3, column] for column in range(4))
    hwf = np.tile([size[0], size[1], 40.0], (count, 1))
    pose = np.stack([down, right, -forward, centre, hwf], axis=-1)
    np.save(
        folder / "poses_bounds.npy", np.concatenate([pose.reshape(-1, 15), [[2.0, 6.0]] * count], 1)
    )
    for index in range(count):
        write_png(folder / "images" / f"v{index}.png", torch.full((*size, 3), 0.5))
        write_png(folder / "masks" / f"v{index}.png", torch.ones(*size, 1), encode_srgb=False)


def test_prepared_downscales_are_read_when_large_enough(tmp_path: Path) -> None:
    llff_capture(tmp_path, (128, 192))
    for factor, value in ((2, 0.25), (4, 0.75)):
        for index in range(3):
            write_png(
                tmp_path / f"images_{factor}" / f"v{index}.png",
                torch.full((128 // factor, 192 // factor, 3), value),
            )
    # images_4 (48 px wide) is too small for 80 px; images_2 (96 px) is the one to read
    assert llff_downscale_for(tmp_path, 80) == 2
    assert llff_downscale_for(tmp_path, 48) == 4
    assert llff_downscale_for(tmp_path, 100) is None and llff_downscale_for(tmp_path, None) is None
    captures = read_captures(tmp_path, "train", DatasetConfig(max_resolution=80, holdout_every=3))
    # read from images_2 (value 0.25), shrunk from 96 to 80 px, intrinsics of that size
    assert captures.images.shape[1:3] == (53, 80)
    assert abs(float(captures.images.mean()) - 0.25) < 0.02
    focal = captures.cameras.intrinsics[0, 0, 0]
    assert torch.allclose(focal, torch.tensor(40.0 * 80 / 192), rtol=0.02)


def test_a_downscale_with_missing_photos_is_ignored(tmp_path: Path) -> None:
    llff_capture(tmp_path, (128, 192))
    write_png(tmp_path / "images_2" / "v0.png", torch.full((64, 96, 3), 0.25))
    assert llff_downscale_for(tmp_path, 80) is None
