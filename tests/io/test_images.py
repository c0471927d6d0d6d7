"""PNG / EXR / contact sheet / atomic write tests for recon.io (tiny images, CPU only)."""

from __future__ import annotations

import json
import os
import stat
import struct
import zlib
from pathlib import Path

import kornia
import numpy as np
import OpenEXR
import pytest
import torch
from PIL import Image

from recon.errors import ReconError
from recon.io import (
    atomic_path,
    atomic_write_json,
    atomic_write_text,
    linear_to_srgb,
    read_exr,
    read_exr_channels,
    read_image,
    read_png,
    read_png_pixels,
    save_contact_sheet,
    srgb_to_linear,
    write_exr,
    write_png,
)
from recon.io.images import _decode_png, _encode_png

# The steepest slope of srgb_to_linear is at 1: 2.4 / 1.055 = 2.275. Rounding the sRGB code to the
# nearest of 2^bits - 1 steps moves it by at most half a step, so the linear error is at most
# 2.275 * 0.5 / 255 = 4.46e-3 for 8 bits and 1.74e-5 for 16 bits (plus float32 rounding).
SLOPE = 2.4 / 1.055
BOUND_8 = SLOPE * 0.5 / 255 + 1e-6
BOUND_16 = SLOPE * 0.5 / 65535 + 1e-6


def test_srgb_matches_kornia_and_inverts() -> None:
    values = torch.linspace(0, 1, 1001)
    image = values.reshape(1, 1, -1).expand(3, 1, -1)  # kornia wants [3, H, W]
    assert torch.allclose(
        srgb_to_linear(values), kornia.color.rgb_to_linear_rgb(image)[0, 0], atol=1e-6
    )
    assert torch.allclose(
        linear_to_srgb(values), kornia.color.linear_rgb_to_rgb(image)[0, 0], atol=1e-6
    )
    assert torch.allclose(linear_to_srgb(srgb_to_linear(values)), values, atol=1e-6)
    assert abs(float(linear_to_srgb(torch.tensor(0.5))) - 0.735357) < 1e-5


def test_srgb_gradients_are_finite_at_zero() -> None:
    values = torch.tensor([0.0, 1e-8, 0.5, 1.0], requires_grad=True)
    (srgb_to_linear(values).sum() + linear_to_srgb(values).sum()).backward()
    assert bool(torch.isfinite(values.grad).all())


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png_8bit_round_trip_within_quantisation(tmp_path: Path, channels: int) -> None:
    image = torch.rand(16, 20, channels, generator=torch.Generator().manual_seed(channels))
    path = tmp_path / "image.png"
    write_png(path, image)
    back = read_png(path)
    assert back.shape == image.shape and back.dtype == torch.float32
    colour = 1 if channels in (1, 2) else 3
    assert float((back[..., :colour] - image[..., :colour]).abs().max()) <= BOUND_8
    if channels in (2, 4):  # alpha is stored linearly: half an 8-bit step
        assert float((back[..., -1] - image[..., -1]).abs().max()) <= 0.5 / 255 + 1e-6


def test_png_stores_srgb_codes_and_alpha_as_is(tmp_path: Path) -> None:
    path = tmp_path / "gray_alpha.png"
    write_png(path, torch.tensor([[[0.5, 0.5]]]))  # linear gray 0.5, alpha 0.5
    pixels = read_png_pixels(path)
    assert pixels.dtype == np.uint8 and pixels.tolist() == [[[188, 128]]]  # 0.7354 * 255 = 187.5
    assert read_png(path, decode_srgb=False)[0, 0, 0] == pytest.approx(188 / 255)


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png_16bit_round_trip(tmp_path: Path, channels: int) -> None:
    image = torch.rand(17, 23, channels, generator=torch.Generator().manual_seed(10 + channels))
    path = tmp_path / "image16.png"
    write_png(path, image, bits=16)
    assert read_png_pixels(path).dtype == np.uint16
    back = read_png(path)
    assert back.shape == image.shape
    assert float((back - image).abs().max()) <= BOUND_16


def test_16bit_gray_agrees_with_pillow(tmp_path: Path) -> None:
    # Pillow reads 16-bit gray correctly (unlike 16-bit RGB), so it can check our encoder.
    pixels = np.random.default_rng(0).integers(0, 65536, (19, 31, 1), dtype=np.uint16)
    path = tmp_path / "gray16.png"
    path.write_bytes(_encode_png(pixels))
    with Image.open(path) as image:
        assert np.array_equal(np.asarray(image).astype(np.uint16), pixels[..., 0])
    assert np.array_equal(read_png_pixels(path), pixels)


def test_decoder_undoes_every_row_filter_like_pillow(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    smooth = np.cumsum(rng.integers(0, 3, (40, 50, 3)), axis=1).astype(np.uint8)
    pixels = np.concatenate([smooth, rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)])
    path = tmp_path / "pillow.png"
    Image.fromarray(pixels).save(path)
    data = path.read_bytes()
    assert np.array_equal(_decode_png(data, path), pixels)
    # Our own encoder picks a filter per row; all five must decode.
    encoded = _encode_png(pixels.astype(np.uint16) * 257)
    raw = zlib.decompress(encoded[8 + 25 + 8 : -12 - 4])
    filters = np.frombuffer(raw, dtype=np.uint8).reshape(80, -1)[:, 0]
    assert len(set(filters.tolist())) >= 2
    assert np.array_equal(_decode_png(encoded, path), pixels.astype(np.uint16) * 257)


def test_read_png_palette_and_jpeg_via_pillow(tmp_path: Path) -> None:
    palette = Image.new("P", (4, 3))
    palette.putpalette([255, 0, 0, 0, 0, 255] + [0] * 762)
    palette.putpixel((1, 1), 1)
    palette.save(tmp_path / "palette.png")
    image = read_png(tmp_path / "palette.png")
    assert image.shape == (3, 4, 3)
    assert image[0, 0].tolist() == [1.0, 0.0, 0.0] and image[1, 1].tolist() == [0.0, 0.0, 1.0]
    Image.new("RGB", (5, 4), (128, 128, 128)).save(tmp_path / "photo.jpg")
    assert read_image(tmp_path / "photo.jpg").shape == (4, 5, 3)


def test_png_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ReconError, match=r"missing\.png: image file not found"):
        read_png(tmp_path / "missing.png")
    (tmp_path / "garbage.png").write_bytes(b"not an image at all")
    with pytest.raises(ReconError, match=r"garbage\.png: cannot decode image"):
        read_png(tmp_path / "garbage.png")
    write_png(tmp_path / "deep.png", torch.rand(8, 8, 3), bits=16)
    data = (tmp_path / "deep.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ReconError, match=r"truncated\.png: PNG is truncated"):
        read_png(tmp_path / "truncated.png")
    corrupt = bytearray(data)
    corrupt[45] ^= 0xFF  # inside the IDAT payload: the CRC no longer matches
    (tmp_path / "corrupt.png").write_bytes(bytes(corrupt))
    with pytest.raises(ReconError, match=r"corrupt\.png: PNG chunk b'IDAT' .* bad CRC"):
        read_png(tmp_path / "corrupt.png")


def test_write_png_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ReconError, match=r"bad\.png: expected 1 to 4 channels.*\(4, 4, 5\)"):
        write_png(tmp_path / "bad.png", torch.zeros(4, 4, 5))
    with pytest.raises(ReconError, match=r"bad\.png: expected an image of shape \[H, W, C\]"):
        write_png(tmp_path / "bad.png", torch.zeros(2, 4, 4, 3))
    with pytest.raises(ReconError, match=r"bad\.png: image contains NaN"):
        write_png(tmp_path / "bad.png", torch.full((2, 2, 3), float("nan")))
    with pytest.raises(ReconError, match=r"bad\.png: bits must be 8 or 16, got 12"):
        write_png(tmp_path / "bad.png", torch.zeros(2, 2, 3), bits=12)
    assert not any(tmp_path.iterdir())


def test_write_png_clamps(tmp_path: Path) -> None:
    write_png(tmp_path / "clamped.png", torch.tensor([[[-1.0, 2.0, float("inf")]]]))
    assert read_png_pixels(tmp_path / "clamped.png").tolist() == [[[0, 255, 255]]]


def test_exr_round_trip_is_bit_exact(tmp_path: Path) -> None:
    image = torch.randn(16, 24, 4, generator=torch.Generator().manual_seed(3)) * 100
    image[0, 0] = torch.tensor([float("inf"), -float("inf"), 1e-40, -0.0])
    write_exr(tmp_path / "rgba.exr", image)
    back, names = read_exr_channels(tmp_path / "rgba.exr")
    assert names == ["R", "G", "B", "A"]
    assert back.dtype == torch.float32 and torch.equal(back, image)
    assert torch.equal(read_exr(tmp_path / "rgba.exr"), image)


@pytest.mark.parametrize(
    "names",
    [
        ["Z"],
        ["Y"],
        ["Y", "A"],
        ["R", "G", "B"],
        ["normal.X", "normal.Y", "normal.Z"],
        ["Z", "A", "B", "depth"],
    ],
)
def test_exr_custom_channels_keep_their_order(tmp_path: Path, names: list[str]) -> None:
    image = torch.rand(5, 7, len(names), generator=torch.Generator().manual_seed(len(names)))
    path = tmp_path / "channels.exr"
    write_exr(path, image, channel_names=names)
    back, back_names = read_exr_channels(path)
    assert back_names == names and torch.equal(back, image)


def test_exr_written_elsewhere_gets_conventional_order_and_float32(tmp_path: Path) -> None:
    height, width = 3, 4
    planes = {
        "A": np.full((height, width), 0.5, np.float32),
        "B": np.full((height, width), 3, np.float16),
        "G": np.full((height, width), 2, np.float32),
        "R": np.full((height, width), 1, np.float32),
        "normal.Z": np.full((height, width), 6, np.float32),
        "normal.X": np.full((height, width), 4, np.float32),
    }
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, planes).write(
        str(tmp_path / "other.exr")
    )
    image, names = read_exr_channels(tmp_path / "other.exr")
    assert names == ["R", "G", "B", "A", "normal.X", "normal.Z"]
    assert image.dtype == torch.float32 and image[0, 0].tolist() == [1, 2, 3, 0.5, 4, 6]


def test_exr_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ReconError, match=r"missing\.exr: EXR file not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "garbage.exr").write_bytes(b"garbage")
    with pytest.raises(ReconError, match=r"garbage\.exr: cannot read EXR"):
        read_exr(tmp_path / "garbage.exr")
    with pytest.raises(ReconError, match=r"depth\.exr: expected 2 channel names .*\['Z'\]"):
        write_exr(tmp_path / "depth.exr", torch.zeros(2, 2, 2), channel_names=["Z"])
    with pytest.raises(ReconError, match=r"five\.exr: expected 5 channel names .*none"):
        write_exr(tmp_path / "five.exr", torch.zeros(2, 2, 5))
    with pytest.raises(ReconError, match=r"twice\.exr: channel names must be unique"):
        write_exr(tmp_path / "twice.exr", torch.zeros(2, 2, 2), channel_names=["Z", "Z"])


def test_a_full_disk_during_an_exr_write_says_so_by_name(tmp_path: Path, monkeypatch) -> None:
    """OpenEXR reports a full disk as a RuntimeError with the OS's text inside; the error must
    read as every other full disk does (the errno's name and what to do), and leave no file."""

    def full(self, path):
        raise RuntimeError(
            f'Failed to write pixel data to image file "{path}". No space left on device.'
        )

    monkeypatch.setattr(OpenEXR.File, "write", full)
    with pytest.raises(
        ReconError, match=r"full\.exr: No space left on device \(ENOSPC: the disk is full"
    ):
        write_exr(tmp_path / "full.exr", torch.zeros(2, 2, 3))
    assert list(tmp_path.iterdir()) == []

    def other(self, path):
        raise RuntimeError("unsupported compression")

    monkeypatch.setattr(OpenEXR.File, "write", other)
    with pytest.raises(
        ReconError, match=r"other\.exr: cannot write EXR \(unsupported compression\)"
    ):
        write_exr(tmp_path / "other.exr", torch.zeros(2, 2, 3))


def test_contact_sheet_size(tmp_path: Path) -> None:
    images = [torch.full((16, 20, 3), index / 5) for index in range(5)]
    sheet = save_contact_sheet(images, tmp_path / "sheet.png", columns=3)
    assert sheet.shape == (32, 60, 3)
    assert read_png(tmp_path / "sheet.png").shape == (32, 60, 3)
    assert float(sheet[16, 20, 0]) == pytest.approx(4 / 5)  # fifth image: row 1, column 1
    padded = save_contact_sheet(images + [torch.ones(8, 8, 1)], tmp_path / "padded.png", padding=2)
    assert padded.shape == (2 * (16 + 2) + 2, 3 * (20 + 2) + 2, 3)  # 3 columns, 2 rows
    with pytest.raises(ReconError, match=r"empty\.png: expected at least one image"):
        save_contact_sheet([], tmp_path / "empty.png")
    with pytest.raises(ReconError, match=r"bad\.png: contact sheet image 0: expected shape"):
        save_contact_sheet([torch.zeros(4, 4, 4)], tmp_path / "bad.png")


def test_atomic_path_replaces_only_on_success(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "file.txt"
    atomic_write_text(target, "first")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as temporary:
            assert temporary.parent == target.parent and temporary.name.endswith(".tmp.txt")
            temporary.write_text("half")
            raise RuntimeError("writer failed")
    assert target.read_text() == "first"
    assert [entry.name for entry in target.parent.iterdir()] == ["file.txt"]
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask


def test_atomic_write_json(tmp_path: Path) -> None:
    atomic_write_json(tmp_path / "data.json", {"a": [1, 2.5]})
    assert json.loads((tmp_path / "data.json").read_text()) == {"a": [1, 2.5]}
    with pytest.raises(ReconError, match=r"nan\.json: cannot write as JSON"):
        atomic_write_json(tmp_path / "nan.json", {"a": float("nan")})
    assert not (tmp_path / "nan.json").exists()
    assert sorted(entry.name for entry in tmp_path.iterdir()) == ["data.json"]


def test_png_chunk_helper_crc() -> None:
    # Guards the byte layout the truncation/CRC tests above rely on.
    data = _encode_png(np.zeros((2, 2, 3), np.uint16))
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    (length,) = struct.unpack(">I", data[8:12])
    assert length == 13 and data[-8:-4] == b"IEND"


def test_16bit_transparent_colour_key_becomes_alpha(tmp_path: Path) -> None:
    pixels = np.array([[[1, 2, 3], [4, 5, 6]]], dtype=np.uint16)
    data = _encode_png(pixels)
    key = struct.pack(">3H", 4, 5, 6)
    chunk = struct.pack(">I", 6) + b"tRNS" + key + struct.pack(">I", zlib.crc32(b"tRNS" + key))
    header_end = 8 + 25  # signature + IHDR chunk; tRNS must come before IDAT
    (tmp_path / "keyed.png").write_bytes(data[:header_end] + chunk + data[header_end:])
    decoded = read_png_pixels(tmp_path / "keyed.png")
    assert decoded.tolist() == [[[1, 2, 3, 65535], [4, 5, 6, 0]]]
