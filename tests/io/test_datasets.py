"""NeRF-synthetic and LLFF dataset reader/writer tests for recon.io (16-32 px images).
An LLFF folder's prepared images_N/ downscale is read when dataset.max_resolution allows."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from recon.camera import Cameras, look_at, orbit_cameras, rigid_inverse
from recon.config.run_config import DatasetConfig
from recon.errors import DatasetError, ReconError
from recon.io import (
    read_llff,
    read_nerf_synthetic,
    write_exr,
    write_nerf_synthetic,
    write_png,
)
from recon.io.datasets import llff_downscale_for, read_captures

# Linear error of an 8-bit sRGB round trip (see test_images.py), plus the 8-bit alpha
# rounding that multiplies it when premultiplying: |c a - c' a'| <= |c - c'| + |a - a'|.
BOUND_8 = 2.4 / 1.055 * 0.5 / 255 + 1e-6
BOUND_PREMULTIPLIED = BOUND_8 + 0.5 / 255


def capture(
    count: int = 3, size: tuple[int, int] = (16, 24)
) -> tuple[Cameras, torch.Tensor, torch.Tensor]:
    """Orbit cameras, premultiplied images and masks with fractional coverage."""
    generator = torch.Generator().manual_seed(count)
    cameras = orbit_cameras(count, size)
    masks = torch.rand(count, *size, 1, generator=generator)
    masks[masks < 0.3] = 0.0
    masks[masks > 0.8] = 1.0
    images = torch.rand(count, *size, 3, generator=generator) * masks
    return cameras, images, masks


def write_rgba_png(path: Path, rgba: np.ndarray) -> None:
    """8-bit RGBA PNG via Pillow directly (independent of recon's writer)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgba.astype(np.uint8), mode="RGBA").save(path)


def blender_folder(
    folder: Path, count: int = 2, size: tuple[int, int] = (16, 16), **extra: object
) -> dict:
    """A Blender-style split: './train/r_i' without extension, identity-rotation cameras."""
    frames = []
    for index in range(count):
        rgba = np.zeros((*size, 4), np.uint8)
        rgba[..., 0] = 255
        rgba[..., 3] = 255
        rgba[: size[0] // 2, :, 3] = 0  # top half transparent
        write_rgba_png(folder / "train" / f"r_{index}.png", rgba)
        matrix = np.eye(4)
        matrix[:3, 3] = [0.0, 0.0, 4.0 + index]
        frames.append(
            {
                "file_path": f"./train/r_{index}",
                "rotation": 0.0,
                "transform_matrix": matrix.tolist(),
            }
        )
    settings = {"camera_angle_x": 0.6911112070083618, "frames": frames, **extra}
    (folder / "transforms_train.json").write_text(json.dumps(settings, indent=4))
    return settings


# --------------------------------------------------------------------------------------------
# NeRF-synthetic round trips and conventions
# --------------------------------------------------------------------------------------------


def test_nerf_synthetic_round_trip_exr_and_png(tmp_path: Path) -> None:
    cameras, images, masks = capture()
    json_path = write_nerf_synthetic(tmp_path, "train", cameras, images, masks)
    assert json_path == tmp_path / "transforms_train.json"
    assert sorted(entry.name for entry in (tmp_path / "train").iterdir()) == [
        f"r_{index}.{suffix}" for index in range(3) for suffix in ("exr", "png")
    ]
    settings = json.loads(json_path.read_text())
    assert {"camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h"} <= settings.keys()
    assert settings["frames"][0]["file_path"] == "./train/r_0"

    from_exr = read_nerf_synthetic(tmp_path, "train", background=None, prefer_exr=True)
    assert from_exr.names == ["r_0", "r_1", "r_2"] and from_exr.split == "train"
    assert float((from_exr.cameras.world_to_cam - cameras.world_to_cam).abs().max()) < 1e-6
    assert float((from_exr.cameras.intrinsics - cameras.intrinsics).abs().max()) < 1e-6
    assert from_exr.cameras.image_size == cameras.image_size
    assert (from_exr.cameras.near, from_exr.cameras.far) == pytest.approx(
        (cameras.near, cameras.far)
    )
    assert torch.equal(from_exr.images, images) and torch.equal(from_exr.masks, masks)

    from_png = read_nerf_synthetic(tmp_path, "train", background=None)
    assert from_png.images.shape == (3, 16, 24, 3) and from_png.masks.shape == (3, 16, 24, 1)
    assert float((from_png.masks - masks).abs().max()) <= 0.5 / 255 + 1e-6
    assert float((from_png.images - images).abs().max()) <= BOUND_PREMULTIPLIED
    assert float((from_png.cameras.world_to_cam - cameras.world_to_cam).abs().max()) < 1e-6


def test_nerf_synthetic_white_background_round_trip(tmp_path: Path) -> None:
    cameras, images, masks = capture(2)
    over_white = images + (1 - masks)
    write_nerf_synthetic(
        tmp_path, "val", cameras, over_white, masks, names=["a", "b"], background="white"
    )
    back = read_nerf_synthetic(tmp_path, "val", background="white", prefer_exr=True)
    assert back.names == ["a", "b"]
    assert float((back.images - over_white).abs().max()) < 1e-6
    black = read_nerf_synthetic(tmp_path, "val", background="black")
    assert float((black.images - images).abs().max()) <= BOUND_PREMULTIPLIED


def test_nerf_synthetic_writer_never_overwrites(tmp_path: Path) -> None:
    cameras, images, masks = capture(2)
    write_nerf_synthetic(tmp_path, "train", cameras, images, masks, write_exr=False)
    assert not list((tmp_path / "train").glob("*.exr"))
    with pytest.raises(DatasetError, match=r"transforms_train\.json: already exists .*force=True"):
        write_nerf_synthetic(tmp_path, "train", cameras, images, masks)
    (tmp_path / "transforms_train.json").unlink()
    with pytest.raises(DatasetError, match=r"r_0\.png: already exists"):
        write_nerf_synthetic(tmp_path, "train", cameras, images, masks)
    write_nerf_synthetic(tmp_path, "train", cameras, images * 0.5, masks, force=True)
    assert (tmp_path / "transforms_train.json").is_file()
    # another split next to it is fine
    write_nerf_synthetic(tmp_path, "test", cameras, images, masks)


def test_nerf_synthetic_writer_checks_shapes(tmp_path: Path) -> None:
    cameras, images, masks = capture(2)
    with pytest.raises(
        ReconError, match=r"images: expected shape \[2, 16, 24, 3\].*\(2, 16, 24, 4\)"
    ):
        write_nerf_synthetic(tmp_path, "train", cameras, torch.zeros(2, 16, 24, 4), masks)
    with pytest.raises(ReconError, match=r"masks: expected shape \[2, 16, 24, 1\]"):
        write_nerf_synthetic(tmp_path, "train", cameras, images, masks[:1])
    with pytest.raises(ReconError, match=r"names: expected 2 unique names"):
        write_nerf_synthetic(tmp_path, "train", cameras, images, masks, names=["x", "x"])
    with pytest.raises(ReconError, match=r"names: '../x' is not a plain file name"):
        write_nerf_synthetic(tmp_path, "train", cameras, images, masks, names=["../x", "y"])
    assert not any(tmp_path.iterdir())


def test_nerf_synthetic_per_camera_intrinsics_and_scale(tmp_path: Path) -> None:
    cameras, images, masks = capture(2, (16, 32))
    intrinsics = cameras.intrinsics.clone()
    intrinsics[1, 0, 0] *= 1.5
    intrinsics[1, 0, 2] += 2
    cameras = Cameras(
        cameras.world_to_cam, intrinsics, cameras.image_size, cameras.near, cameras.far
    )
    write_nerf_synthetic(tmp_path, "train", cameras, images, masks)
    assert "fl_x" in json.loads((tmp_path / "transforms_train.json").read_text())["frames"][1]
    back = read_nerf_synthetic(tmp_path, "train", prefer_exr=True, background=None)
    assert float((back.cameras.intrinsics - intrinsics).abs().max()) < 1e-5
    half = read_nerf_synthetic(tmp_path, "train", prefer_exr=True, background=None, scale=0.5)
    assert half.images.shape == (2, 8, 16, 3) and half.cameras.image_size == (8, 16)
    assert torch.allclose(half.cameras.intrinsics[:, :2], intrinsics[:, :2] * 0.5)
    # area averaging: each output pixel is the mean of a 2x2 block
    assert torch.allclose(half.images[0, 0, 0], images[0, :2, :2].mean(dim=(0, 1)), atol=1e-6)


def test_blender_style_json_white_background(tmp_path: Path) -> None:
    blender_folder(tmp_path)
    capture_set = read_nerf_synthetic(tmp_path, "train")  # background='white' by default
    assert capture_set.names == ["r_0", "r_1"]
    assert capture_set.images.shape == (2, 16, 16, 3)
    # transparent top half -> white; opaque red bottom half stays red
    assert capture_set.images[0, 0, 0].tolist() == [1.0, 1.0, 1.0]
    assert capture_set.images[0, 15, 0].tolist() == [1.0, 0.0, 0.0]
    assert capture_set.masks[0, 0, 0, 0] == 0.0 and capture_set.masks[0, 15, 0, 0] == 1.0
    focal = 0.5 * 16 / math.tan(0.5 * 0.6911112070083618)
    assert torch.allclose(
        capture_set.cameras.intrinsics[0], torch.tensor([[focal, 0, 8], [0, focal, 8], [0, 0, 1.0]])
    )
    # near/far from the camera distances 4 and 5
    assert (capture_set.cameras.near, capture_set.cameras.far) == pytest.approx((0.05 * 4, 10 * 5))
    black = read_nerf_synthetic(tmp_path, "train", background="black")
    assert black.images[0, 0, 0].tolist() == [0.0, 0.0, 0.0]


def test_blender_camera_looks_down_minus_z(tmp_path: Path) -> None:
    # A camera at (1, 2, 3) rotated 30 degrees about world y, 60 about its x: its OpenGL axes
    # are the columns of the rotation; it looks along -z_camera.
    def rotation(axis: int, degrees: float) -> np.ndarray:
        cosine, sine = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        other = [index for index in range(3) if index != axis]
        matrix = np.eye(3)
        matrix[other[0], other[0]] = matrix[other[1], other[1]] = cosine
        matrix[other[0], other[1]], matrix[other[1], other[0]] = -sine, sine
        return matrix

    rotation_matrix = rotation(1, 30) @ rotation(0, 60)
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3] = rotation_matrix
    cam_to_world[:3, 3] = [1, 2, 3]
    write_rgba_png(tmp_path / "train" / "r_0.png", np.full((16, 24, 4), 255))
    settings = {
        "camera_angle_x": 0.8,
        "frames": [{"file_path": "./train/r_0", "transform_matrix": cam_to_world.tolist()}],
    }
    (tmp_path / "transforms_train.json").write_text(json.dumps(settings))
    cameras = read_nerf_synthetic(tmp_path).cameras
    centre, right, up, back = cam_to_world[:3, 3], *rotation_matrix.T
    points = torch.tensor(
        np.stack(
            [centre - 3 * back, centre - 3 * back + 0.5 * right, centre - 3 * back + 0.5 * up]
        ),
        dtype=torch.float32,
    )
    pixels = cameras.project_to_pixels(points)[0]
    assert torch.allclose(pixels[0], torch.tensor([12.0, 8.0]), atol=1e-4)  # image centre
    assert pixels[1, 0] > 12 and abs(float(pixels[1, 1]) - 8) < 1e-4  # +x camera: right
    assert pixels[2, 1] < 8 and abs(float(pixels[2, 0]) - 12) < 1e-4  # +y camera: up (row 0 on top)
    assert torch.allclose(cameras.centers()[0], torch.tensor([1.0, 2.0, 3.0]), atol=1e-6)


def test_file_paths_with_extension_and_strict_extras(tmp_path: Path) -> None:
    settings = blender_folder(tmp_path, count=2)
    settings["frames"][1]["file_path"] = "train/r_1.png"
    (tmp_path / "transforms_train.json").write_text(json.dumps(settings))
    write_rgba_png(tmp_path / "train" / "r_0_depth_0000.png", np.zeros((16, 16, 4)))  # auxiliary
    assert read_nerf_synthetic(tmp_path, strict=True).names == ["r_0", "r_1"]
    write_rgba_png(tmp_path / "train" / "r_7.png", np.zeros((16, 16, 4)))
    assert len(read_nerf_synthetic(tmp_path)) == 2  # extra files are ignored unless strict
    with pytest.raises(
        DatasetError,
        match=r"transforms_train\.json: 1 image file\(s\) in .*train are not referenced .*r_7\.png",
    ):
        read_nerf_synthetic(tmp_path, strict=True)


# --------------------------------------------------------------------------------------------
# NeRF-synthetic errors
# --------------------------------------------------------------------------------------------


def test_missing_folder_and_transforms(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"nowhere: NeRF-synthetic folder not found"):
        read_nerf_synthetic(tmp_path / "nowhere")
    blender_folder(tmp_path)
    with pytest.raises(
        DatasetError,
        match=r"transforms_test\.json: transforms file for split 'test' not found .*transforms_train\.json",
    ):
        read_nerf_synthetic(tmp_path, "test")


def test_bad_json_names_the_line(tmp_path: Path) -> None:
    (tmp_path / "transforms_train.json").write_text(
        '{\n  "camera_angle_x": 0.5,\n  "frames": [,]\n}'
    )
    with pytest.raises(
        DatasetError, match=r"transforms_train\.json: invalid JSON at line 3, column"
    ):
        read_nerf_synthetic(tmp_path)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda s: s.pop("camera_angle_x"),
            r"transforms_train\.json: missing key 'camera_angle_x'",
        ),
        (lambda s: s.pop("frames"), r"transforms_train\.json: missing key 'frames'"),
        (lambda s: s.update(frames=[]), r"'frames' must be a non-empty list"),
        (
            lambda s: s["frames"][1].pop("transform_matrix"),
            r"frames\[1\]: missing key 'transform_matrix'",
        ),
        (lambda s: s["frames"][0].pop("file_path"), r"frames\[0\]: missing key 'file_path'"),
        (
            lambda s: s["frames"][1].update(transform_matrix=[[1, 0, 0]]),
            r"frames\[1\]\.transform_matrix: expected a 4x4 matrix, got shape \(1, 3\)",
        ),
        (
            lambda s: s["frames"][1].update(file_path="./train/r_9"),
            r"frames\[1\]: image file .*r_9\.png not found",
        ),
        (
            lambda s: s.update(camera_angle_x=4.0),
            r"camera_angle_x must lie in \(0, pi\) radians, got 4\.0",
        ),
        (
            lambda s: s.update(w=32),
            r"transforms_train\.json: 'w' is 32 but image .*r_0\.png has width 16",
        ),
        (
            lambda s: s["frames"][1].update(transform_matrix=(np.diag([2.0, 2, 2, 1])).tolist()),
            r"frames\[1\]\.transform_matrix: matrix 0 is not rigid",
        ),
    ],
)
def test_transforms_errors(tmp_path: Path, edit, message: str) -> None:
    settings = blender_folder(tmp_path)
    edit(settings)
    (tmp_path / "transforms_train.json").write_text(json.dumps(settings))
    with pytest.raises(DatasetError, match=message):
        read_nerf_synthetic(tmp_path)


def test_unreadable_and_inconsistent_images(tmp_path: Path) -> None:
    blender_folder(tmp_path)
    (tmp_path / "train" / "r_1.png").write_bytes(b"broken")
    with pytest.raises(
        DatasetError, match=r"frames\[1\]: cannot read image: .*r_1\.png: cannot decode image"
    ):
        read_nerf_synthetic(tmp_path)
    write_rgba_png(tmp_path / "train" / "r_1.png", np.zeros((16, 20, 4)))
    with pytest.raises(
        DatasetError,
        match=r"frames\[1\]: image .*r_1\.png has size \(H, W\) = \(16, 20\), expected \(16, 16\)",
    ):
        read_nerf_synthetic(tmp_path)


# --------------------------------------------------------------------------------------------
# LLFF
# --------------------------------------------------------------------------------------------


def llff_rows(
    world_to_cam: torch.Tensor, size: tuple[int, int], focal: float, bounds: np.ndarray
) -> np.ndarray:
    """poses_bounds.npy rows [N, 17] from OpenCV cameras, converted by hand.

    OpenCV camera-to-world columns are [right, down, forward]; LLFF wants [down, right, back].
    """
    cam_to_world = rigid_inverse(world_to_cam.double()).numpy()
    right, down, forward, centre = (cam_to_world[:, :3, column] for column in range(4))
    hwf = np.tile([size[0], size[1], focal], (len(cam_to_world), 1))
    pose = np.stack([down, right, -forward, centre, hwf], axis=-1)  # [N, 3, 5]
    return np.concatenate([pose.reshape(-1, 15), bounds], axis=1)


def llff_folder(folder: Path, count: int = 3, size: tuple[int, int] = (16, 24), masks: bool = True):
    generator = torch.Generator().manual_seed(7)
    eyes = torch.tensor([[0.3 * index, 0.1, 4.0] for index in range(count)])
    world_to_cam = look_at(eyes, torch.zeros(count, 3))
    bounds = np.array([[2.0 + index, 6.0 + index] for index in range(count)])
    np.save(folder / "poses_bounds.npy", llff_rows(world_to_cam, size, 20.0, bounds))
    images = torch.rand(count, *size, 3, generator=generator)
    mask_images = (torch.rand(count, *size, 1, generator=generator) > 0.5).float()
    for index in range(count):
        write_png(folder / "images" / f"img_{index:03d}.png", images[index])
        if masks:
            write_png(
                folder / "masks" / f"img_{index:03d}.png", mask_images[index], encode_srgb=False
            )
    return world_to_cam, images, mask_images, bounds


def test_llff_round_trip(tmp_path: Path) -> None:
    world_to_cam, images, masks, bounds = llff_folder(tmp_path)
    capture_set = read_llff(tmp_path)
    assert capture_set.names == ["img_000", "img_001", "img_002"]
    assert float((capture_set.cameras.world_to_cam - world_to_cam).abs().max()) < 1e-6
    expected_intrinsics = torch.tensor([[20.0, 0, 12], [0, 20.0, 8], [0, 0, 1]])
    assert torch.allclose(capture_set.cameras.intrinsics, expected_intrinsics.expand(3, 3, 3))
    assert (capture_set.cameras.near, capture_set.cameras.far) == pytest.approx((0.9 * 2, 1.1 * 8))
    assert float((capture_set.images - images).abs().max()) <= BOUND_8
    assert torch.equal(capture_set.masks, masks)


def test_llff_known_camera_axes(tmp_path: Path) -> None:
    # LLFF columns [down, right, back] of a camera at the origin looking down world -z, y up.
    pose = np.zeros((3, 5))
    pose[:, 0] = [0, -1, 0]  # down
    pose[:, 1] = [1, 0, 0]  # right
    pose[:, 2] = [0, 0, 1]  # back
    pose[:, 4] = [16, 24, 20]  # hwf
    np.save(
        tmp_path / "poses_bounds.npy", np.concatenate([pose.reshape(1, 15), [[1.0, 10.0]]], axis=1)
    )
    write_png(tmp_path / "images" / "a.png", torch.zeros(16, 24, 3))
    cameras = read_llff(tmp_path).cameras
    pixels = cameras.project_to_pixels(torch.tensor([[0.0, 0, -5], [1.0, 0, -5], [0.0, 1, -5]]))[0]
    assert torch.allclose(pixels[0], torch.tensor([12.0, 8.0]), atol=1e-5)
    assert torch.allclose(pixels[1], torch.tensor([12.0 + 20 / 5, 8.0]), atol=1e-5)  # right
    assert torch.allclose(pixels[2], torch.tensor([12.0, 8.0 - 20 / 5]), atol=1e-5)  # up


def test_llff_factor_downsamples_and_scales_intrinsics(tmp_path: Path) -> None:
    _, images, masks, _ = llff_folder(tmp_path, size=(16, 32))
    half = read_llff(tmp_path, factor=2)
    assert half.images.shape == (3, 8, 16, 3) and half.masks.shape == (3, 8, 16, 1)
    assert torch.allclose(
        half.cameras.intrinsics[0], torch.tensor([[10.0, 0, 8], [0, 10.0, 4], [0, 0, 1]])
    )
    # a prepared images_2/ folder is used as it is
    for index in range(3):
        write_png(tmp_path / "images_2" / f"img_{index:03d}.png", torch.full((8, 16, 3), 0.25))
    prepared = read_llff(tmp_path, factor=2)
    assert float((prepared.images - 0.25).abs().max()) <= BOUND_8
    assert prepared.masks.shape == (3, 8, 16, 1)  # full-size masks/ shrunk to match


def test_llff_without_masks_uses_ones(tmp_path: Path) -> None:
    llff_folder(tmp_path, masks=False)
    assert torch.equal(read_llff(tmp_path).masks, torch.ones(3, 16, 24, 1))


def test_llff_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"nowhere: LLFF folder not found"):
        read_llff(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy: poses file not found"):
        read_llff(tmp_path)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(
        DatasetError, match=r"poses_bounds\.npy: expected shape \[N, 17\] .*got \(3, 15\)"
    ):
        read_llff(tmp_path)

    world_to_cam, images, masks, bounds = llff_folder(tmp_path)
    write_png(tmp_path / "images" / "img_999.png", images[0])
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy: 3 poses but 4 images in .*images"):
        read_llff(tmp_path)
    (tmp_path / "images" / "img_999.png").unlink()
    (tmp_path / "masks" / "img_002.png").unlink()
    with pytest.raises(DatasetError, match=r"masks: no mask for 1 of 3 images .*img_002"):
        read_llff(tmp_path)
    write_png(tmp_path / "masks" / "img_002.png", torch.ones(8, 8, 1))
    with pytest.raises(
        DatasetError, match=r"img_002\.png: mask size \(H, W\) = \(8, 8\), expected \(16, 24\)"
    ):
        read_llff(tmp_path)
    write_png(tmp_path / "masks" / "img_002.png", torch.ones(16, 24, 1))
    (tmp_path / "images" / "img_001.png").write_bytes(b"broken")
    with pytest.raises(DatasetError, match=r"img_001\.png: cannot read image"):
        read_llff(tmp_path)
    write_png(tmp_path / "images" / "img_001.png", torch.zeros(16, 20, 3))
    with pytest.raises(
        DatasetError, match=r"img_001\.png: image size \(H, W\) = \(16, 20\), expected \(16, 24\)"
    ):
        read_llff(tmp_path)
    write_png(tmp_path / "images" / "img_001.png", images[1])
    rows = np.load(tmp_path / "poses_bounds.npy")
    rows[1, :15] = (rows[1, :15].reshape(3, 5) * np.array([2.0, 2, 2, 1, 1])).reshape(15)
    np.save(tmp_path / "poses_bounds.npy", rows)
    with pytest.raises(
        DatasetError, match=r"poses_bounds\.npy: pose 1 \(img_001\.png\): matrix 0 is not rigid"
    ):
        read_llff(tmp_path)


def test_exr_frames_without_alpha_use_full_coverage(tmp_path: Path) -> None:
    blender_folder(tmp_path, count=1)
    write_exr(tmp_path / "train" / "r_0.exr", torch.full((16, 16, 3), 2.5))
    capture_set = read_nerf_synthetic(tmp_path, prefer_exr=True)
    assert torch.equal(capture_set.images, torch.full((1, 16, 16, 3), 2.5))  # HDR kept
    assert torch.equal(capture_set.masks, torch.ones(1, 16, 16, 1))


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
