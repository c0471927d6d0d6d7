"""Real-capture reading (recon.io.datasets.read_captures with a DatasetConfig, recon.io.exif):
masks by file stem in any format, RGB + masks NeRF-synthetic folders, the missing-mask error
and the background key, the size cap on load, EXIF metadata and known exposure gains.
Fixtures are tiny folders the tests write (16-48 px)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from recon.camera import look_at, rigid_inverse
from recon.config.run_config import DatasetConfig
from recon.errors import DatasetError
from recon.io.datasets import held_out_split, read_captures, read_llff, read_nerf_synthetic
from recon.io.exif import exposure_value, read_exif
from recon.io.images import srgb_to_linear

EXIF_IFD = 0x8769


def llff_rows(
    world_to_cam: torch.Tensor, size: tuple[int, int], focal: float, bounds: np.ndarray
) -> np.ndarray:
    """poses_bounds.npy rows [N, 17]: LLFF columns [down, right, back] from OpenCV cameras."""
    cam_to_world = rigid_inverse(world_to_cam.double()).numpy()
    right, down, forward, centre = (cam_to_world[:, :3, column] for column in range(4))
    hwf = np.tile([size[0], size[1], focal], (len(cam_to_world), 1))
    pose = np.stack([down, right, -forward, centre, hwf], axis=-1)
    return np.concatenate([pose.reshape(-1, 15), bounds], axis=1)


def write_jpeg(path: Path, rgb: np.ndarray, exif: dict | None = None) -> None:
    """An 8-bit RGB JPEG (quality 100), with EXIF {exposure_time, f_number, iso, model} and,
    where given, white_balance (the EXIF code: 0 auto, 1 manual)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    image = Image.fromarray(rgb.astype(np.uint8), mode="RGB")
    tags = Image.Exif()
    if exif:
        tags[0x0110] = exif["model"]
        sub = tags.get_ifd(EXIF_IFD)
        sub[0x829A] = exif["exposure_time"]
        sub[0x829D] = exif["f_number"]
        sub[0x8827] = exif["iso"]
        if "white_balance" in exif:
            sub[0xA403] = exif["white_balance"]
    image.save(path, quality=100, exif=tags)


def photo_folder(
    folder: Path,
    count: int = 4,
    size: tuple[int, int] = (24, 32),
    masks: str | None = "png1",
    exposures: list[float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """An LLFF folder of JPEG photos (a grey square on a white background) and masks in
    masks/ named by stem but listed in another order than the images (suffix .png/.jpg)."""
    eyes = torch.tensor([[0.5 * index - 1.0, 0.2, 4.0] for index in range(count)])
    world_to_cam = look_at(eyes, torch.zeros(count, 3))
    bounds = np.array([[2.0, 6.0]] * count)
    np.save(folder / "poses_bounds.npy", llff_rows(world_to_cam, size, 30.0, bounds))
    photos = np.full((count, *size, 3), 255, np.uint8)
    coverage = np.zeros((count, *size), np.uint8)
    for index in range(count):
        top, left = 4 + index, 6 + 2 * index
        photos[index, top : top + 10, left : left + 12] = 64 + 30 * index
        coverage[index, top : top + 10, left : left + 12] = 255
        exif = None
        if exposures is not None:
            exif = {"exposure_time": exposures[index], "f_number": 8.0, "iso": 400, "model": "X1"}
            exif["white_balance"] = index % 2  # auto and manual in turn
        write_jpeg(folder / "images" / f"IMG_{index}.jpg", photos[index], exif)
        # Mask stems in reverse: sorted order would pair IMG_0 with the last mask.
        name = f"IMG_{index}"
        (folder / "masks").mkdir(exist_ok=True)
        if masks == "png1":
            Image.fromarray(coverage[index]).save(folder / "masks" / f"{name}.png")
        elif masks == "png3":
            Image.fromarray(np.repeat(coverage[index][..., None], 3, -1)).save(
                folder / "masks" / f"{name}.png"
            )
        elif masks == "jpg":
            Image.fromarray(coverage[index]).save(folder / "masks" / f"{name}.jpg", quality=100)
    return photos, coverage


@pytest.mark.parametrize("kind", ["png1", "png3", "jpg"])
def test_llff_masks_by_stem_in_any_format(tmp_path: Path, kind: str) -> None:
    _, coverage = photo_folder(tmp_path, masks=kind)
    captures = read_llff(tmp_path)
    assert captures.mask_source == "masks"
    expected = torch.from_numpy(coverage / 255.0).float()[..., None]
    # JPEG ringing at the mask's edges stays small; PNG masks are exact.
    tolerance = 0.1 if kind == "jpg" else 1e-6
    assert float((captures.masks - expected).abs().mean()) < tolerance / 4
    assert float((captures.masks - expected).abs().max()) < (0.5 if kind == "jpg" else 1e-6)


def test_mask_missing_for_one_image_names_it(tmp_path: Path) -> None:
    photo_folder(tmp_path)
    (tmp_path / "masks" / "IMG_2.png").rename(tmp_path / "masks" / "other.png")
    with pytest.raises(DatasetError, match=r"no mask for 1 of 4 images .*IMG_2"):
        read_llff(tmp_path)


def test_photos_without_masks_or_alpha_are_an_error_unless_keyed(tmp_path: Path) -> None:
    photos, coverage = photo_folder(tmp_path, masks=None)
    (tmp_path / "masks").rmdir()
    with pytest.raises(
        DatasetError, match=r"no masks/ folder and no alpha channel.*background_key"
    ):
        read_captures(tmp_path, "train", DatasetConfig())
    keyed = read_captures(tmp_path, "train", DatasetConfig(background_key=[1.0, 1.0, 1.0]))
    assert keyed.mask_source == "key"
    # train = every image but the 0th (holdout_every 8)
    expected = torch.from_numpy(coverage[1:] / 255.0).float()[..., None]
    assert float((keyed.masks - expected).abs().max()) == 0.0
    # the background is removed: premultiplied colour is 0 outside the object
    assert float(keyed.images[keyed.masks[..., 0] == 0].abs().max()) == 0.0


def test_max_resolution_shrinks_on_load_with_filtering_and_scales_intrinsics(
    tmp_path: Path, capsys
) -> None:
    photos, coverage = photo_folder(tmp_path, size=(24, 32))
    full = read_captures(tmp_path, "train", DatasetConfig(max_resolution=None))
    half = read_captures(tmp_path, "train", DatasetConfig(max_resolution=16))
    assert "reading them at 12 x 16" in capsys.readouterr().err
    assert tuple(half.images.shape) == (3, 12, 16, 3)
    assert tuple(half.cameras.image_size) == (12, 16)
    assert torch.allclose(
        half.cameras.intrinsics, full.cameras.intrinsics * torch.tensor([[0.5], [0.5], [1.0]])
    )
    # Antialiased: every pixel is the mean of its 2 x 2 block of the full-size image (box), of
    # the premultiplied colour (what a coarser sensor integrates) and of the masks.
    blocks = full.images.reshape(3, 12, 2, 16, 2, 3).mean((2, 4))
    mask_blocks = full.masks.reshape(3, 12, 2, 16, 2, 1).mean((2, 4))
    assert float((half.masks - mask_blocks).abs().max()) < 1e-6
    assert float((half.images - blocks).abs().max()) < 1e-5
    # A point projects to the same place in relative image coordinates.
    point = torch.tensor([[0.1, -0.2, 0.3]])
    ratio = half.cameras.project_to_pixels(point) / full.cameras.project_to_pixels(point)
    assert torch.allclose(ratio, torch.full_like(ratio, 0.5), atol=1e-5)


def test_llff_test_split_and_holdout(tmp_path: Path) -> None:
    photo_folder(tmp_path, count=5)
    assert held_out_split(tmp_path) == "test"
    test = read_captures(tmp_path, "test", DatasetConfig(holdout_every=2))
    assert test.names == ["IMG_0", "IMG_2", "IMG_4"]
    with pytest.raises(DatasetError, match="only 'train' and 'test' splits, got 'val'"):
        read_captures(tmp_path, "val", DatasetConfig())


def test_nerf_synthetic_rgb_with_masks_folder(tmp_path: Path) -> None:
    size = (16, 16)
    frames = []
    rgb = np.zeros((*size, 3), np.uint8)
    rgb[...] = 200
    coverage = np.zeros(size, np.uint8)
    coverage[4:12, 4:12] = 255
    for index in range(2):
        (tmp_path / "train").mkdir(exist_ok=True)
        Image.fromarray(rgb).save(tmp_path / "train" / f"r_{index}.png")
        folder = tmp_path / "masks" / ("train" if index == 0 else "")
        folder.mkdir(parents=True, exist_ok=True)
        Image.fromarray(coverage).save(folder / f"r_{index}.png")
        matrix = np.eye(4)
        matrix[2, 3] = 4.0
        frames.append({"file_path": f"./train/r_{index}", "transform_matrix": matrix.tolist()})
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": 0.6, "frames": frames})
    )
    captures = read_nerf_synthetic(tmp_path, "train", background=None)
    assert captures.mask_source == "masks"
    mask = torch.from_numpy(coverage / 255.0).float()
    assert torch.equal(captures.masks[..., 0], mask.expand(2, *size))
    colour = srgb_to_linear(torch.tensor(200 / 255.0))
    assert torch.allclose(captures.images[..., 0], colour * mask.expand(2, *size), atol=1e-5)
    # without the masks folder: no coverage, an error for a fit
    for path in sorted((tmp_path / "masks").rglob("*.png")):
        path.unlink()
    with pytest.raises(DatasetError, match="no masks/ folder and no alpha channel"):
        read_captures(tmp_path, "train", DatasetConfig())


def test_exif_is_read_per_image_and_gives_known_gains(tmp_path: Path) -> None:
    exposures = [0.1, 0.2, 0.05, 0.1, 0.1]
    photo_folder(tmp_path, count=5, exposures=exposures)
    metadata = read_exif(tmp_path / "images" / "IMG_1.jpg")
    assert metadata == {
        "exposure_time": pytest.approx(0.2),
        "f_number": pytest.approx(8.0),
        "iso": pytest.approx(400.0),
        "white_balance": "manual",
        "camera_model": "X1",
    }
    assert read_exif(tmp_path / "images" / "IMG_2.jpg")["white_balance"] == "auto"
    assert exposure_value(metadata) == pytest.approx(0.2 * 400 / 64)
    plain = read_captures(tmp_path, "train", DatasetConfig())
    assert [m["exposure_time"] for m in plain.metadata] == pytest.approx(exposures[1:])
    known = read_captures(tmp_path, "train", DatasetConfig(exposure="exif"))
    # gains relative to the median exposure (0.1): the images are divided by them
    gains = torch.tensor(exposures[1:]) / 0.1
    assert torch.allclose(known.images * gains[:, None, None, None], plain.images, atol=1e-6)
    assert read_exif(tmp_path / "poses_bounds.npy")["iso"] is None


def test_exposure_exif_without_exif_is_an_error(tmp_path: Path) -> None:
    photo_folder(tmp_path)
    with pytest.raises(DatasetError, match=r"exposure is 'exif' but image 'IMG_1' has no EXIF"):
        read_captures(tmp_path, "train", DatasetConfig(exposure="exif"))
