"""COLMAP sparse models (recon.io.colmap): a tiny text model the test writes (PINHOLE and
OPENCV cameras), its binary copy, poses and intrinsics as given, masks in COLMAP's naming, and
the OPENCV distortion undone on load, checked against the distortion formula written out here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from recon.camera import look_at
from recon.config.run_config import DatasetConfig
from recon.io.datasets import dataset_layout, read_captures

pycolmap = pytest.importorskip("pycolmap")
from recon.io.colmap import read_colmap  # noqa: E402

SIZE = (20, 30)  # H, W
OPENCV = [28.0, 26.0, 15.5, 9.5, 0.12, -0.03, 0.004, -0.006]  # fx fy cx cy k1 k2 p1 p2


def write_model(folder: Path, world_to_cam: torch.Tensor, ramp: bool = False) -> None:
    """cameras.txt (1: PINHOLE, 2: OPENCV), images.txt (alternating cameras), points3D.txt,
    the photos (16-bit-free 8-bit PNG ramps or random) and masks named 'NAME.png.png'."""
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    height, width = SIZE
    (model / "cameras.txt").write_text(
        f"# camera list\n1 PINHOLE {width} {height} 28 26 15.5 9.5\n"
        f"2 OPENCV {width} {height} " + " ".join(str(v) for v in OPENCV) + "\n"
    )
    lines = []
    for index, matrix in enumerate(world_to_cam.double().numpy()):
        x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
        t = matrix[:3, 3]
        camera = 1 + index % 2
        lines.append(f"{index + 1} {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} {camera} v{index}.png")
        lines.append("")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("1 0.2 0.1 -0.1 200 10 10 0.3\n2 -0.3 0 0.2 1 2 3 0.4\n")
    (folder / "images").mkdir()
    (folder / "masks").mkdir()
    generator = np.random.default_rng(0)
    for index in range(len(world_to_cam)):
        if ramp:
            columns = (np.arange(width) + 0.5) / width
            rows = (np.arange(height) + 0.5) / height
            pixels = np.zeros((height, width, 3))
            pixels[..., 0] = columns[None, :]
            pixels[..., 1] = rows[:, None]
            # 16-bit PNG keeps the ramps exact enough for the check (read without sRGB).
            photo = (pixels * 65535).round().astype(np.uint16)
            for channel, name in ((0, "x"), (1, "y")):
                Image.fromarray(photo[..., channel]).save(folder / f"ramp_{name}.png")
            pixels8 = (pixels * 255).round().astype(np.uint8)
        else:
            pixels8 = generator.integers(0, 256, (height, width, 3), dtype=np.uint8)
        Image.fromarray(pixels8).save(folder / "images" / f"v{index}.png")
        mask = np.zeros((height, width), np.uint8)
        mask[4:16, 5 + index : 20 + index] = 255
        Image.fromarray(mask).save(folder / "masks" / f"v{index}.png.png")


def cameras(count: int = 4) -> torch.Tensor:
    angles = torch.arange(count) * 0.6
    eyes = torch.stack([3 * torch.sin(angles), 0.5 + 0 * angles, 3 * torch.cos(angles)], -1)
    return look_at(eyes, torch.zeros(count, 3))


def test_text_and_binary_models_give_the_cameras_as_written(tmp_path: Path) -> None:
    world_to_cam = cameras()
    write_model(tmp_path / "text", world_to_cam)
    assert dataset_layout(tmp_path / "text") == "colmap"
    captures = read_colmap(tmp_path / "text")
    assert captures.names == ["v0", "v1", "v2", "v3"]
    assert torch.allclose(captures.cameras.world_to_cam, world_to_cam, atol=1e-5)
    pinhole = torch.tensor([[28.0, 0, 15.5], [0, 26.0, 9.5], [0, 0, 1]])
    assert torch.allclose(captures.cameras.intrinsics, pinhole.expand(4, 3, 3))
    assert captures.mask_source == "masks"
    assert float(captures.masks[0, 10, 10]) == 1.0 and float(captures.masks[0, 1, 1]) == 0.0
    # the points (depths about 2.6 to 3.4) lie between near and far
    assert 0 < captures.cameras.near < 2.5 and captures.cameras.far > 3.5
    assert [m["colmap_model"] for m in captures.metadata] == ["PINHOLE", "OPENCV"] * 2
    # PINHOLE photos pass through untouched (up to the 8-bit sRGB decode)
    photo = np.asarray(Image.open(tmp_path / "text" / "images" / "v0.png")) / 255.0
    from recon.io.images import srgb_to_linear

    expected = srgb_to_linear(torch.from_numpy(photo).float())
    assert float((captures.images[0] - expected).abs().max()) < 1e-5

    # The same model written by COLMAP in binary reads the same.
    model = pycolmap.Reconstruction(str(tmp_path / "text" / "sparse" / "0"))
    binary = tmp_path / "binary"
    (binary / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(binary / "sparse" / "0"))
    assert (binary / "sparse" / "0" / "cameras.bin").is_file()
    for name in ("images", "masks"):
        (binary / name).symlink_to(tmp_path / "text" / name)
    again = read_colmap(binary)
    assert torch.allclose(again.cameras.world_to_cam, captures.cameras.world_to_cam, atol=1e-6)
    assert torch.equal(again.images, captures.images)

    # splits for a fit: every holdout_every-th image is the test split
    test = read_captures(tmp_path / "text", "test", DatasetConfig(holdout_every=3))
    assert test.names == ["v0", "v3"]


def opencv_distort(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's radial-tangential model (k1, k2, p1, p2) in normalised coordinates."""
    _, _, _, _, k1, k2, p1, p2 = OPENCV
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return (
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def test_opencv_distortion_is_undone_on_load(tmp_path: Path) -> None:
    write_model(tmp_path, cameras(2), ramp=True)
    # Linear ramps (value = pixel position / size) in the photo, read as coverage-free colour:
    # bilinear resampling of a linear function is exact, so the undistorted image's value at
    # each pixel says where in the photo it was taken from.
    for name in ("images",):
        for index in range(2):
            ramp_x = np.asarray(Image.open(tmp_path / "ramp_x.png"), dtype=np.float64) / 65535
            ramp_y = np.asarray(Image.open(tmp_path / "ramp_y.png"), dtype=np.float64) / 65535
            stacked = np.stack([ramp_x, ramp_y, ramp_x], -1).astype(np.float32)
            from recon.io.images import write_exr

            (tmp_path / name / f"v{index}.png").unlink()
            write_exr(tmp_path / name / f"v{index}.exr", torch.from_numpy(stacked))
    (tmp_path / "sparse" / "0" / "images.txt").write_text(
        (tmp_path / "sparse" / "0" / "images.txt").read_text().replace(".png", ".exr")
    )
    for index in range(2):
        (tmp_path / "masks" / f"v{index}.png.png").rename(tmp_path / "masks" / f"v{index}.png")
    captures = read_colmap(tmp_path)
    height, width = SIZE
    fx, fy, cx, cy = OPENCV[:4]
    columns, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    xd, yd = opencv_distort((columns - cx) / fx, (rows - cy) / fy)
    expected_x = (xd * fx + cx) / width
    expected_y = (yd * fy + cy) / height
    inside = (expected_x > 1.0 / width) & (expected_x < 1 - 1.0 / width)
    inside &= (expected_y > 1.0 / height) & (expected_y < 1 - 1.0 / height)
    assert inside.sum() > 0.6 * inside.size
    undistorted = captures.images[1].numpy()  # v1 uses the OPENCV camera
    assert np.abs(undistorted[..., 0][inside] - expected_x[inside]).max() < 2e-3
    assert np.abs(undistorted[..., 1][inside] - expected_y[inside]).max() < 2e-3
    assert np.abs(expected_x * width - columns).max() > 0.5  # not a negligible distortion
    # the PINHOLE view is untouched
    assert np.abs(captures.images[0].numpy()[..., 0] - (columns / width)).max() < 1e-3
    assert captures.metadata[1]["undistorted"] and not captures.metadata[0]["undistorted"]
