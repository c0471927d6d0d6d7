"""Image files <-> float32 tensors [H, W, C] in LINEAR colour.

PNG (and other 8-bit formats Pillow reads, such as JPEG) hold sRGB-encoded colour: readers decode
it to linear, writers encode linear to sRGB. Alpha is coverage and is never sRGB-coded: it passes
through unchanged (only scaled to [0, 1]). EXR holds linear float data and is passed through.

Channel layouts by count C: 1 = gray, 2 = gray + alpha, 3 = RGB, 4 = RGBA.

16-bit PNG is read and written by a small numpy codec in this module, because Pillow 13 neither
writes 16-bit RGB(A) nor reads it without silently truncating it to 8 bits.
"""

from __future__ import annotations

import errno
import math
import os
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import OpenEXR
import torch
from PIL import Image, UnidentifiedImageError

from recon.errors import ReconError, WriteError, describe_os_error
from recon.io.atomic import atomic_path, atomic_write_bytes

# --------------------------------------------------------------------------------------------
# sRGB transfer function
# --------------------------------------------------------------------------------------------


def srgb_to_linear(values: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 sRGB decoding, elementwise on any shape (values in [0, 1]).

    This is the same formula as kornia.color.rgb_to_linear_rgb, written out because kornia's
    function only accepts [..., 3, H, W] and so fits neither gray images, channels-last
    images, nor vertex colours [V, 3]. The pow argument is clamped so that gradients stay finite.
    """
    curve = torch.pow(((values + 0.055) / 1.055).clamp(min=1e-12), 2.4)
    return torch.where(values > 0.04045, curve, values / 12.92)


def linear_to_srgb(values: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 sRGB encoding, elementwise on any shape (inverse of srgb_to_linear)."""
    curve = 1.055 * torch.pow(values.clamp(min=0.0031308), 1 / 2.4) - 0.055
    return torch.where(values > 0.0031308, curve, 12.92 * values)


def _colour_channel_count(channels: int) -> int:
    """How many leading channels are colour (sRGB-coded in PNG); the rest is alpha."""
    return {1: 1, 2: 1, 3: 3, 4: 3}[channels]


# --------------------------------------------------------------------------------------------
# A minimal PNG codec for 8/16-bit gray, gray+alpha, RGB and RGBA (non-interlaced)
# --------------------------------------------------------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channel count (type 3, palette, is left to Pillow: always 8 bits or fewer).
_COLOUR_TYPE_CHANNELS = {0: 1, 4: 2, 2: 3, 6: 4}
_CHANNELS_COLOUR_TYPE = {channels: kind for kind, channels in _COLOUR_TYPE_CHANNELS.items()}


def _png_chunks(data: bytes, path: Path) -> list[tuple[bytes, bytes]]:
    """Split a PNG byte string into (type, payload) chunks, checking lengths and CRCs."""
    if not data.startswith(_PNG_SIGNATURE):
        raise ReconError(f"{path}: not a PNG file (bad signature)")
    chunks = []
    position = len(_PNG_SIGNATURE)
    while position < len(data):
        if position + 12 > len(data):
            raise ReconError(f"{path}: PNG is truncated (incomplete chunk at byte {position})")
        length, kind = struct.unpack(">I4s", data[position : position + 8])
        end = position + 8 + length
        if end + 4 > len(data):
            raise ReconError(f"{path}: PNG is truncated (chunk {kind!r} at byte {position})")
        payload = data[position + 8 : end]
        (crc,) = struct.unpack(">I", data[end : end + 4])
        if zlib.crc32(kind + payload) != crc:
            raise ReconError(f"{path}: PNG chunk {kind!r} at byte {position} has a bad CRC")
        chunks.append((kind, payload))
        position = end + 4
        if kind == b"IEND":
            break
    return chunks


def _png_header(data: bytes, path: Path) -> tuple[int, int, int, int, int]:
    """(width, height, bit_depth, colour_type, interlace) from the IHDR chunk."""
    if len(data) < 33 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise ReconError(f"{path}: not a PNG file (missing signature or IHDR chunk)")
    width, height, bit_depth, colour_type, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    return width, height, bit_depth, colour_type, interlace


def _paeth(left: np.ndarray, up: np.ndarray, up_left: np.ndarray) -> np.ndarray:
    """The PNG Paeth predictor, elementwise on int32 arrays."""
    estimate = left + up - up_left
    distance_left = np.abs(estimate - left)
    distance_up = np.abs(estimate - up)
    distance_up_left = np.abs(estimate - up_left)
    return np.where(
        (distance_left <= distance_up) & (distance_left <= distance_up_left),
        left,
        np.where(distance_up <= distance_up_left, up, up_left),
    )


def _unfilter(
    filtered: np.ndarray, filters: np.ndarray, width: int, bytes_per_pixel: int
) -> np.ndarray:
    """Undo PNG row filters. filtered: [H, W * bpp] uint8, filters: [H]. Returns [H, W * bpp].

    Sub, Average and Paeth depend on the already decoded pixel to the left, so a row cannot be
    decoded in one vectorised step. Pixel (row, column) depends only on pixels with a smaller
    row + column, so we sweep anti-diagonals instead: H + W - 1 vectorised steps rather than
    H * W Python iterations.
    """
    height = filtered.shape[0]
    filtered = filtered.reshape(height, width, bytes_per_pixel).astype(np.int32)
    # One zero row on top and one zero column on the left: PNG's out-of-image neighbours are 0.
    decoded = np.zeros((height + 1, width + 1, bytes_per_pixel), dtype=np.int32)
    for step in range(height + width - 1):
        rows = np.arange(max(0, step - width + 1), min(height - 1, step) + 1)
        columns = step - rows
        left = decoded[rows + 1, columns]
        up = decoded[rows, columns + 1]
        up_left = decoded[rows, columns]
        kind = filters[rows][:, None]
        predictor = np.select(
            [kind == 0, kind == 1, kind == 2, kind == 3],
            [np.zeros_like(left), left, up, (left + up) >> 1],
            _paeth(left, up, up_left),
        )
        decoded[rows + 1, columns + 1] = (filtered[rows, columns] + predictor) & 0xFF
    return decoded[1:, 1:].reshape(height, width * bytes_per_pixel).astype(np.uint8)


def _decode_png(data: bytes, path: Path) -> np.ndarray:
    """Decode a non-interlaced 8/16-bit gray/gray+alpha/RGB/RGBA PNG to [H, W, C] uint8/uint16.

    A tRNS chunk (one transparent colour, for gray and RGB) becomes an alpha channel.
    """
    chunks = _png_chunks(data, path)
    width, height, bit_depth, colour_type, interlace = _png_header(data, path)
    if colour_type not in _COLOUR_TYPE_CHANNELS or bit_depth not in (8, 16):
        raise ReconError(
            f"{path}: PNG colour type {colour_type} with bit depth {bit_depth} is not supported "
            "by the 16-bit reader (expected gray, gray+alpha, RGB or RGBA at 8 or 16 bits)"
        )
    if interlace:
        raise ReconError(f"{path}: interlaced (Adam7) 16-bit PNG is not supported")
    channels = _COLOUR_TYPE_CHANNELS[colour_type]
    bytes_per_pixel = channels * bit_depth // 8
    compressed = b"".join(payload for kind, payload in chunks if kind == b"IDAT")
    try:
        raw = zlib.decompress(compressed)
    except zlib.error as error:
        raise ReconError(f"{path}: PNG image data is corrupt ({error})") from error
    row_bytes = 1 + width * bytes_per_pixel
    if len(raw) < height * row_bytes:
        raise ReconError(
            f"{path}: PNG image data is truncated (expected {height * row_bytes} bytes, "
            f"got {len(raw)})"
        )
    rows = np.frombuffer(raw, dtype=np.uint8, count=height * row_bytes).reshape(height, row_bytes)
    if rows[:, 0].max(initial=0) > 4:
        raise ReconError(f"{path}: PNG has an invalid row filter type {int(rows[:, 0].max())}")
    decoded = _unfilter(rows[:, 1:], rows[:, 0], width, bytes_per_pixel)
    dtype = np.dtype(">u2") if bit_depth == 16 else np.dtype(np.uint8)
    pixels = decoded.view(dtype).reshape(height, width, channels).astype(dtype.newbyteorder("="))
    transparency = [payload for kind, payload in chunks if kind == b"tRNS"]
    if transparency and channels in (1, 3):
        key = np.array(struct.unpack(f">{channels}H", transparency[0][: 2 * channels]))
        opaque = ~np.all(pixels == key.astype(pixels.dtype), axis=-1, keepdims=True)
        alpha = opaque.astype(pixels.dtype) * np.iinfo(pixels.dtype).max
        pixels = np.concatenate([pixels, alpha], axis=-1)
    return pixels


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return (
        struct.pack(">I", len(payload))
        + kind
        + payload
        + struct.pack(">I", zlib.crc32(kind + payload))
    )


def _encode_png(pixels: np.ndarray, block_rows: int = 64) -> bytes:
    """Encode [H, W, C] uint8 or uint16 (C = 1..4) as a PNG byte string.

    Each row gets the filter that minimises the sum of absolute signed bytes (libpng's
    heuristic). Filtering uses the original bytes only, so it is vectorised; rows are processed
    in blocks to bound the memory of the five candidate filterings.
    """
    height, width, channels = pixels.shape
    bit_depth = 16 if pixels.dtype == np.uint16 else 8
    row_bytes_array = np.ascontiguousarray(pixels.astype(">u2" if bit_depth == 16 else np.uint8))
    row_bytes_array = row_bytes_array.view(np.uint8).reshape(height, -1).astype(np.int32)
    bytes_per_pixel = channels * bit_depth // 8
    output = np.empty((height, row_bytes_array.shape[1] + 1), dtype=np.uint8)
    for start in range(0, height, block_rows):
        current = row_bytes_array[start : start + block_rows]
        if start:
            up = row_bytes_array[start - 1 : start - 1 + current.shape[0]]
        else:
            up = np.concatenate([np.zeros_like(current[:1]), current[:-1]])
        left = np.zeros_like(current)
        left[:, bytes_per_pixel:] = current[:, :-bytes_per_pixel]
        up_left = np.zeros_like(current)
        up_left[:, bytes_per_pixel:] = up[:, :-bytes_per_pixel]
        candidates = (
            np.stack(
                [
                    current,
                    current - left,
                    current - up,
                    current - ((left + up) >> 1),
                    current - _paeth(left, up, up_left),
                ]
            )
            & 0xFF
        )  # [5, rows, row_bytes]
        cost = np.minimum(candidates, 256 - candidates).sum(axis=-1)  # [5, rows]
        best = cost.argmin(axis=0)
        rows = np.arange(current.shape[0])
        output[start : start + block_rows, 0] = best
        output[start : start + block_rows, 1:] = candidates[best, rows]
    header = struct.pack(
        ">IIBBBBB", width, height, bit_depth, _CHANNELS_COLOUR_TYPE[channels], 0, 0, 0
    )
    return (
        _PNG_SIGNATURE
        + _png_chunk(b"IHDR", header)
        + _png_chunk(b"IDAT", zlib.compress(output.tobytes(), 6))
        + _png_chunk(b"IEND", b"")
    )


# --------------------------------------------------------------------------------------------
# PNG (and other Pillow formats)
# --------------------------------------------------------------------------------------------


def _pillow_pixels(image: Image.Image) -> np.ndarray:
    """[H, W, C] uint8 or uint16 array of a Pillow image, with C in 1..4 (alpha last)."""
    if image.mode in ("I;16", "I;16B", "I;16L"):
        return np.asarray(image).astype(np.uint16)[..., None]
    has_alpha = "transparency" in image.info or "A" in image.getbands() or "a" in image.getbands()
    gray = image.mode in ("1", "L", "LA", "La")
    if has_alpha:
        pixels = np.asarray(image.convert("LA" if gray else "RGBA"))
    else:
        pixels = np.asarray(image.convert("L" if gray else "RGB"))
    return pixels[..., None] if pixels.ndim == 2 else pixels


def read_png_pixels(path: str | os.PathLike) -> np.ndarray:
    """Raw pixel values [H, W, C] uint8 or uint16 of a PNG (or any image Pillow reads).

    16-bit PNGs keep their 16 bits. Raises ReconError naming the path when the file is missing
    or cannot be decoded.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError as error:
        raise ReconError(f"{path}: image file not found") from error
    except OSError as error:
        raise ReconError(f"{path}: cannot read image file ({error})") from error
    if data.startswith(_PNG_SIGNATURE):
        width, height, bit_depth, colour_type, _ = _png_header(data, path)
        if bit_depth == 16:
            return _decode_png(data, path)
    try:
        with Image.open(path) as image:
            image.load()
            return _pillow_pixels(image)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise ReconError(f"{path}: cannot decode image ({error})") from error


def read_png(path: str | os.PathLike, decode_srgb: bool = True) -> torch.Tensor:
    """Read an 8- or 16-bit PNG (or JPEG, ...) as float32 [H, W, C], C = 1..4.

    Colour channels are sRGB-decoded to linear (unless decode_srgb=False, for data images such
    as masks); an alpha channel (C = 2 or 4) is coverage and is only scaled to [0, 1].
    """
    pixels = read_png_pixels(path)
    scale = float(np.iinfo(pixels.dtype).max)
    image = torch.from_numpy(pixels.astype(np.float32) / scale)
    if decode_srgb:
        colour = _colour_channel_count(image.shape[-1])
        image[..., :colour] = srgb_to_linear(image[..., :colour])
    return image


def _as_image_tensor(
    image: torch.Tensor | np.ndarray, path: Path, max_channels: int | None
) -> torch.Tensor:
    """Validate an image [H, W, C] (or [H, W]) and return it as a float32 CPU tensor [H, W, C]."""
    image = torch.as_tensor(image).detach().to("cpu", torch.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise ReconError(f"{path}: expected an image of shape [H, W, C], got {tuple(image.shape)}")
    if max_channels is not None and not 1 <= image.shape[-1] <= max_channels:
        raise ReconError(
            f"{path}: expected 1 to {max_channels} channels (gray, gray+alpha, RGB, RGBA), "
            f"got shape {tuple(image.shape)}"
        )
    if bool(torch.isnan(image).any()):
        raise ReconError(f"{path}: image contains NaN")
    return image


def write_png(
    path: str | os.PathLike,
    image: torch.Tensor | np.ndarray,
    bits: int = 8,
    encode_srgb: bool = True,
) -> None:
    """Write a linear float image [H, W, C] (C = 1..4) as an 8- or 16-bit PNG, atomically.

    Colour channels are clamped to [0, 1], sRGB-encoded (unless encode_srgb=False) and rounded;
    alpha (C = 2 or 4) is clamped and rounded as is. Raises ReconError for a bad shape, NaN, or a
    bit depth other than 8 or 16.
    """
    path = Path(path)
    if bits not in (8, 16):
        raise ReconError(f"{path}: bits must be 8 or 16, got {bits}")
    image = _as_image_tensor(image, path, max_channels=4).clamp(0.0, 1.0)
    if encode_srgb:
        colour = _colour_channel_count(image.shape[-1])
        image[..., :colour] = linear_to_srgb(image[..., :colour])
    scale = 255.0 if bits == 8 else 65535.0
    pixels = torch.round(image * scale).numpy().astype(np.uint8 if bits == 8 else np.uint16)
    if bits == 16:
        atomic_write_bytes(path, _encode_png(pixels))
        return
    with atomic_path(path) as temporary:
        Image.fromarray(pixels[..., 0] if pixels.shape[-1] == 1 else pixels).save(
            temporary, format="PNG"
        )


# --------------------------------------------------------------------------------------------
# EXR
# --------------------------------------------------------------------------------------------

# Header attribute in which write_exr records the caller's channel order: EXR itself stores
# channels sorted by name, so "Z, normal.X" or "R, G, B" would otherwise come back reordered.
_CHANNEL_ORDER_ATTRIBUTE = "reconChannelOrder"
# Order of well-known channel suffixes inside one layer (alpha last).
_CHANNEL_RANK = {name: rank for rank, name in enumerate("R G B X Y Z U V W A".split())}


def _default_channel_names(channels: int) -> list[str]:
    return {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}.get(channels, [])


def _conventional_channel_order(name: str) -> tuple[str, int, str]:
    """Sort key: by layer ('normal' of 'normal.X'), then R G B X Y Z U V W A, then by name."""
    layer, _, suffix = name.rpartition(".")
    return layer, _CHANNEL_RANK.get(suffix, len(_CHANNEL_RANK)), suffix


def read_exr_channels(path: str | os.PathLike) -> tuple[torch.Tensor, list[str]]:
    """Read the first part of an EXR as float32 [H, W, C] and its channel names.

    Channel order: the order write_exr was given when the file carries it, otherwise layer by
    layer with R G B / X Y Z first and A last (so 'R G B A', 'Y A', 'normal.X normal.Y normal.Z').
    Half and uint channels are converted to float32. Raises ReconError naming the path when the
    file is missing, unreadable, or has subsampled channels.
    """
    path = Path(path)
    if not path.is_file():
        raise ReconError(f"{path}: EXR file not found")
    try:
        # Copy everything out inside the block: on exit the File clears the very dicts that
        # header() and channels() returned, so using them afterwards finds no channels.
        with OpenEXR.File(str(path), separate_channels=True) as exr_file:
            recorded = str(exr_file.header().get(_CHANNEL_ORDER_ATTRIBUTE, "")).split(",")
            channels = {
                name: (
                    channel.xSampling,
                    channel.ySampling,
                    np.array(channel.pixels, dtype=np.float32),
                )
                for name, channel in exr_file.channels().items()
            }
    except (RuntimeError, ValueError, OSError) as error:
        raise ReconError(f"{path}: cannot read EXR ({error})") from error
    if not channels:
        raise ReconError(f"{path}: EXR has no channels")
    for name, (x_sampling, y_sampling, _) in channels.items():
        if x_sampling != 1 or y_sampling != 1:
            raise ReconError(
                f"{path}: EXR channel {name!r} is subsampled ({x_sampling}x{y_sampling}); "
                "expected full-resolution channels"
            )
    if sorted(recorded) == sorted(channels):
        names = recorded
    else:
        names = sorted(channels, key=_conventional_channel_order)
    planes = [channels[name][2] for name in names]
    return torch.from_numpy(np.stack(planes, axis=-1)), names


def read_exr(path: str | os.PathLike) -> torch.Tensor:
    """Read an EXR as float32 [H, W, C] (linear data as stored; see read_exr_channels)."""
    return read_exr_channels(path)[0]


def write_exr(
    path: str | os.PathLike,
    image: torch.Tensor | np.ndarray,
    channel_names: Sequence[str] | None = None,
) -> None:
    """Write float32 [H, W, C] as a ZIP-compressed float32 EXR, atomically (bit-exact round trip).

    channel_names default to Y / Y A / R G B / R G B A for C = 1..4 and are required for other C
    (for example ['Z'] for depth, or ['normal.X', 'normal.Y', 'normal.Z']). NaN and inf are
    written as they are.
    """
    path = Path(path)
    image = torch.as_tensor(image).detach().to("cpu", torch.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise ReconError(f"{path}: expected an image of shape [H, W, C], got {tuple(image.shape)}")
    names = (
        list(channel_names)
        if channel_names is not None
        else _default_channel_names(image.shape[-1])
    )
    if len(names) != image.shape[-1]:
        raise ReconError(
            f"{path}: expected {image.shape[-1]} channel names for an image of shape "
            f"{tuple(image.shape)}, got {names if channel_names is not None else 'none'}"
        )
    if len(set(names)) != len(names) or not all(names) or any("," in name for name in names):
        raise ReconError(f"{path}: channel names must be unique, non-empty, without ',': {names}")
    pixels = image.numpy()
    planes = {name: np.ascontiguousarray(pixels[..., index]) for index, name in enumerate(names)}
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        _CHANNEL_ORDER_ATTRIBUTE: ",".join(names),
    }
    with atomic_path(path) as temporary:
        try:
            with OpenEXR.File(header, planes) as exr_file:
                exr_file.write(str(temporary))
        except (RuntimeError, ValueError) as error:
            os_error = _os_error_named_in(str(error), path)
            if os_error is not None:
                raise WriteError(describe_os_error(os_error, path)) from error
            raise ReconError(f"{path}: cannot write EXR ({error})") from error


# The OS errors a write meets most (recon.errors' hints), recognised in a library's message.
_WRITE_ERRNOS = ("ENOSPC", "EDQUOT", "EROFS", "EACCES", "EPERM")


def _os_error_named_in(message: str, path: str | os.PathLike) -> OSError | None:
    """The OSError whose text a library's exception carries (OpenEXR reports a full disk as a
    RuntimeError with the OS's "No space left on device" inside), or None."""
    for name in _WRITE_ERRNOS:
        code = getattr(errno, name, None)
        if code is not None and os.strerror(code) in message:
            return OSError(code, os.strerror(code), str(path))
    return None


# --------------------------------------------------------------------------------------------
# Any image, contact sheets
# --------------------------------------------------------------------------------------------


def read_image(path: str | os.PathLike, decode_srgb: bool = True) -> torch.Tensor:
    """float32 [H, W, C] linear: EXR passes through, other formats go through read_png."""
    if Path(path).suffix.lower() == ".exr":
        return read_exr(path)
    return read_png(path, decode_srgb=decode_srgb)


def save_contact_sheet(
    images: Sequence[torch.Tensor],
    path: str | os.PathLike,
    columns: int | None = None,
    padding: int = 0,
    background: float = 0.0,
) -> torch.Tensor:
    """Tile linear images [H_i, W_i, 3] (or [H_i, W_i, 1]) row by row into one PNG, atomically.

    Every cell is max(H_i) x max(W_i), with `padding` pixels of `background` between cells and
    around the sheet; smaller images sit in the top-left corner of their cell. columns defaults
    to ceil(sqrt(count)). Returns the sheet [rows * (H + padding) + padding,
    columns * (W + padding) + padding, 3] as written (linear, before clamping).
    """
    path = Path(path)
    if len(images) == 0:
        raise ReconError(f"{path}: expected at least one image for the contact sheet, got none")
    tiles = []
    for index, image in enumerate(images):
        image = torch.as_tensor(image).detach().to("cpu", torch.float32)
        if image.ndim == 2:
            image = image[..., None]
        if image.ndim != 3 or image.shape[-1] not in (1, 3):
            raise ReconError(
                f"{path}: contact sheet image {index}: expected shape [H, W, 3] or [H, W, 1], "
                f"got {tuple(image.shape)}"
            )
        tiles.append(image.expand(-1, -1, 3))
    columns = columns or math.ceil(math.sqrt(len(tiles)))
    if columns < 1:
        raise ReconError(f"{path}: columns must be at least 1, got {columns}")
    rows = math.ceil(len(tiles) / columns)
    cell_height = max(tile.shape[0] for tile in tiles)
    cell_width = max(tile.shape[1] for tile in tiles)
    sheet = torch.full(
        (rows * (cell_height + padding) + padding, columns * (cell_width + padding) + padding, 3),
        float(background),
    )
    for index, tile in enumerate(tiles):
        top = padding + (index // columns) * (cell_height + padding)
        left = padding + (index % columns) * (cell_width + padding)
        sheet[top : top + tile.shape[0], left : left + tile.shape[1]] = tile
    write_png(path, sheet)
    return sheet
