"""Capture datasets on disk <-> recon Cameras (OpenCV axes) and linear image tensors.

Two layouts are read:

NeRF-synthetic (Blender) folders: `transforms_{split}.json` with `camera_angle_x` (horizontal field
of view in radians; `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` override or complete it, at the top level
or per frame) and `frames`, each with a `file_path` (the extension may be left out: Blender's
'./train/r_0' means './train/r_0.png') and a 4x4 OpenGL camera-to-world `transform_matrix`. The
images are RGBA PNGs with straight (not premultiplied) sRGB colour, or linear EXRs with
premultiplied RGB (the EXR convention).

LLFF / NeRD folders: `poses_bounds.npy` [N, 17], `images/` (or `images_{factor}/`) and optionally
`masks/`. Each row is a 3x5 matrix (row-major) [R | t | hwf] followed by the near and far depth
bounds of that image. The columns of R are the camera's axes in world coordinates in LLFF's
[down, right, backwards] order, t is the camera centre, and hwf = (height, width, focal in pixels).
Since OpenGL camera axes are [right, up, backwards] = [col1, -col0, col2] (this is the swap in
LLFF's and NeRF's load_llff.py), OpenCV axes [right, down, forwards] are [col1, col0, -col2]:

    camera_to_world_opencv = [[R[:, 1], R[:, 0], -R[:, 2], t], [0, 0, 0, 1]]

The poses are used as they are: no recentring, rescaling by the bounds, or spherifying.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recon.camera import (
    Cameras,
    check_rigid,
    opengl_cam_to_world_to_world_to_cam,
    rigid_inverse,
    world_to_cam_to_opengl_cam_to_world,
)
from recon.errors import DatasetError, ReconError, warn_user
from recon.io.atomic import atomic_write_json

# The names of a dataset's extra captures are the layout's (re-exported for their readers).
from recon.io.dataset_layout import (  # noqa: F401
    FLAT_FIELD_SPLIT,
    LINE_TARGET_SPLIT,
    RELIGHT_LIGHTING,
)
from recon.io.exif import exposure_value, read_exif
from recon.io.images import read_exr_channels, read_image, write_png
from recon.io.images import write_exr as write_exr_file  # the writer has a write_exr flag

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


@dataclass
class CaptureSet:
    """Images of one split with their cameras.

    cameras: B cameras (OpenCV axes) of one image size (H, W).
    images: [B, H, W, 3] float32 linear colour (composited as the reader was asked).
    masks: [B, H, W, 1] float32 coverage in [0, 1] (alpha or mask images; 1 where none).
    names: B image names (file stems), in frame order.
    split: the split's name ('train', 'test', ... ; 'all' for LLFF).
    """

    cameras: Cameras
    images: torch.Tensor
    masks: torch.Tensor
    names: list[str]
    split: str
    # Where the masks came from: 'alpha' (the images' alpha channel), 'masks' (mask images),
    # 'key' (a background colour key) or 'none' (no coverage information: masks are all 1).
    mask_source: str = "alpha"
    # Per image: EXIF exposure_time, f_number, iso, white_balance, camera_model (None where
    # absent; recon.io.exif); or None.
    metadata: list[dict] | None = None
    # Per-view gains [B] the images were divided by on load (dataset.exposure 'exif': the EXIF
    # exposure over the median), or None when the pixels are as stored.
    known_gains: torch.Tensor | None = None
    # [B, H, W, 3] linear straight colour of the whole frames, backdrop included (read with
    # keep_frames where the layout has one: photos with masks or a background key); None where
    # the reader was not asked or the frames have no backdrop (rendered RGBA: alpha 0 there).
    frames: torch.Tensor | None = None

    def __post_init__(self) -> None:
        count = len(self.cameras)
        height, width = self.cameras.image_size
        if tuple(self.images.shape) != (count, height, width, 3):
            raise ReconError(
                f"capture_set.images: expected shape [{count}, {height}, {width}, 3], "
                f"got {tuple(self.images.shape)}"
            )
        if tuple(self.masks.shape) != (count, height, width, 1):
            raise ReconError(
                f"capture_set.masks: expected shape [{count}, {height}, {width}, 1], "
                f"got {tuple(self.masks.shape)}"
            )
        if len(self.names) != count:
            raise ReconError(f"capture_set.names: expected {count} names, got {len(self.names)}")

    def __len__(self) -> int:
        return len(self.cameras)


# --------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------


def _resize(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Resize [B, H, W, C] to [B, h, w, C]: area averaging to shrink, bilinear to enlarge.

    Both are linear in the pixel values, so resizing commutes with alpha compositing.
    """
    if tuple(images.shape[1:3]) == tuple(size):
        return images
    shrinking = size[0] <= images.shape[1] and size[1] <= images.shape[2]
    channels_first = images.permute(0, 3, 1, 2)
    if shrinking:
        resized = torch.nn.functional.interpolate(channels_first, size=size, mode="area")
    else:
        resized = torch.nn.functional.interpolate(
            channels_first, size=size, mode="bilinear", align_corners=False
        )
    return resized.permute(0, 2, 3, 1).contiguous()


def _near_far_from_distances(centres: torch.Tensor) -> tuple[float, float]:
    """near = 0.05 * the smallest camera distance to the origin, far = 10 * the largest.

    Object-centric captures orbit the origin, so this brackets the object with a wide margin.
    Cameras all at the origin fall back to (0.01, 100).
    """
    distances = centres.double().norm(dim=-1)
    smallest, largest = float(distances.min()), float(distances.max())
    if largest <= 0:
        return 0.01, 100.0
    near = 0.05 * smallest if smallest > 0 else 0.0005 * largest
    return near, 10.0 * largest


def _split_colour_alpha(
    image: torch.Tensor, names: list[str] | None = None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """[H, W, C] -> colour [H, W, 3] and alpha [H, W, 1] or None, by channel count or names."""
    if names is not None and {"R", "G", "B"} <= set(names):
        colour = torch.stack([image[..., names.index(key)] for key in "RGB"], dim=-1)
        alpha = image[..., names.index("A")][..., None] if "A" in names else None
        return colour, alpha
    channels = image.shape[-1]
    if channels in (1, 2):
        colour = image[..., :1].expand(-1, -1, 3)
    else:
        colour = image[..., :3]
    alpha = image[..., -1:] if channels in (2, 4) else None
    return colour, alpha


def _same_aspect(size: tuple[float, float], other: tuple[float, float]) -> bool:
    """Whether two (H, W) sizes have the same aspect ratio within 1% (rounding when resizing)."""
    return abs((size[1] / size[0]) / (other[1] / other[0]) - 1) <= 0.01


def _image_files(folder: Path) -> list[Path]:
    """Image files directly inside folder, sorted by name (hidden files skipped)."""
    return sorted(
        entry
        for entry in folder.iterdir()
        if entry.is_file()
        and not entry.name.startswith(".")
        and entry.suffix.lower() in IMAGE_SUFFIXES
    )


def capped_size(size: tuple[int, int], max_resolution: int | None) -> tuple[int, int]:
    """(H, W) shrunk so that the longer side is at most max_resolution (aspect kept)."""
    height, width = size
    if max_resolution is None or max(height, width) <= max_resolution:
        return (height, width)
    scale = max_resolution / max(height, width)
    return (max(1, round(height * scale)), max(1, round(width * scale)))


def _note_cap(size: tuple[int, int], max_resolution: int | None, where: Path) -> tuple[int, int]:
    """capped_size, telling the user when it shrinks the images."""
    capped = capped_size(size, max_resolution)
    if capped != size:
        warn_user(
            f"{where}: images are {size[0]} x {size[1]}; reading them at {capped[0]} x "
            f"{capped[1]} (dataset.max_resolution = {max_resolution}; set it higher or to null "
            "for more detail at more memory and time)",
            kind="note",
        )
    return capped


def shrink_image(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """[H, W, C] -> [h, w, C] with an antialiased (area-averaging) filter: every output pixel is
    the mean of the input pixels it covers, as a coarser sensor would integrate them."""
    return _resize(image[None], size)[0]


def find_mask_file(masks_folder: Path, stem: str) -> Path | None:
    """The mask image of an image stem in masks_folder (any of PNG/JPG/EXR; 'NAME.png' or the
    image's full name plus an extension, as in 'IMG_1.jpg.png'), or None."""
    for suffix in IMAGE_SUFFIXES + tuple(suffix.upper() for suffix in IMAGE_SUFFIXES):
        candidate = masks_folder / f"{stem}{suffix}"
        if candidate.is_file():
            return candidate
    matches = [
        path
        for path in masks_folder.glob(f"{stem}.*")
        if path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()
    ]
    return sorted(matches)[0] if matches else None


def read_mask(path: Path, size: tuple[int, int] | None = None) -> torch.Tensor:
    """A mask image as coverage [H, W, 1] in [0, 1]: 1 channel as it is, 3 channels averaged,
    2 or 4 channels their alpha unless it is all opaque (then the colour). Values are read
    without sRGB decoding. size: shrink to this (H, W) first (same aspect ratio only)."""
    try:
        image = read_image(path, decode_srgb=False)
    except ReconError as error:
        raise DatasetError(f"{path}: cannot read mask: {error}") from error
    channels = image.shape[-1]
    if channels in (2, 4) and bool((image[..., -1] < 1).any()):
        mask = image[..., -1:]
    elif channels == 1:
        mask = image
    else:
        mask = image[..., : min(3, channels - 1 if channels in (2, 4) else channels)].mean(
            -1, keepdim=True
        )
    if size is not None and tuple(mask.shape[:2]) != tuple(size):
        if not _same_aspect(tuple(mask.shape[:2]), size):
            raise DatasetError(
                f"{path}: mask size (H, W) = {tuple(mask.shape[:2])} has another aspect ratio "
                f"than its image ({size[0]} x {size[1]})"
            )
        mask = _resize(mask[None], size)[0]
    return mask.clamp(0.0, 1.0)


# --------------------------------------------------------------------------------------------
# NeRF-synthetic reader
# --------------------------------------------------------------------------------------------


def _load_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise DatasetError(f"{path}: cannot read ({error})") from error
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"{path}: invalid JSON at line {error.lineno}, column {error.colno}: {error.msg}"
        ) from error


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _frame_image_path(folder: Path, file_path: str, prefer_exr: bool) -> Path:
    """The image file a frame's file_path names ('.png' implied when it has no image extension)."""
    path = folder / file_path
    stem_path = path.with_suffix("") if path.suffix.lower() in IMAGE_SUFFIXES else path
    if prefer_exr:
        exr_path = stem_path.parent / (stem_path.name + ".exr")
        if exr_path.is_file():
            return exr_path
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return path
    return stem_path.parent / (stem_path.name + ".png")


def _frame_intrinsics(
    settings: dict[str, Any],
    frame: dict[str, Any],
    size: tuple[int, int],
    where: str,
    json_path: Path,
) -> list[list[float]]:
    """[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] from a frame's keys, falling back on the top level."""
    height, width = size

    def lookup(key: str) -> float | None:
        if key in frame:
            return _number(frame[key], f"{where}.{key}")
        if key in settings:
            return _number(settings[key], f"{json_path}: {key}")
        return None

    focal_x, focal_y = lookup("fl_x"), lookup("fl_y")
    if focal_x is None:
        angle_x = lookup("camera_angle_x")
        if angle_x is None:
            raise DatasetError(
                f"{where}: missing key 'camera_angle_x' (horizontal field of view in radians) "
                "and no 'fl_x' focal length either"
            )
        if not 0 < angle_x < math.pi:
            raise DatasetError(
                f"{where}: camera_angle_x must lie in (0, pi) radians, got {angle_x}"
            )
        focal_x = 0.5 * width / math.tan(0.5 * angle_x)
    if focal_y is None:
        angle_y = lookup("camera_angle_y")
        if angle_y is not None and not 0 < angle_y < math.pi:
            raise DatasetError(
                f"{where}: camera_angle_y must lie in (0, pi) radians, got {angle_y}"
            )
        focal_y = focal_x if angle_y is None else 0.5 * height / math.tan(0.5 * angle_y)
    centre_x, centre_y = lookup("cx"), lookup("cy")
    centre_x = width / 2 if centre_x is None else centre_x
    centre_y = height / 2 if centre_y is None else centre_y
    return [[focal_x, 0.0, centre_x], [0.0, focal_y, centre_y], [0.0, 0.0, 1.0]]


def _frame_matrix(frame: Any, where: str) -> np.ndarray:
    """A frame's checked 4x4 rigid OpenGL camera-to-world matrix (float64)."""
    if not isinstance(frame, dict):
        raise DatasetError(f"{where}: expected an object, got {type(frame).__name__}")
    for key in ("file_path", "transform_matrix"):
        if key not in frame:
            raise DatasetError(f"{where}: missing key {key!r}")
    if not isinstance(frame["file_path"], str) or not frame["file_path"]:
        raise DatasetError(
            f"{where}.file_path: expected a non-empty string, got {frame['file_path']!r}"
        )
    try:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise DatasetError(
            f"{where}.transform_matrix: expected a 4x4 array of numbers ({error})"
        ) from error
    if matrix.shape != (4, 4):
        raise DatasetError(
            f"{where}.transform_matrix: expected a 4x4 matrix, got shape {matrix.shape}"
        )
    try:
        check_rigid(torch.from_numpy(matrix), f"{where}.transform_matrix")
    except ReconError as error:
        raise DatasetError(str(error)) from error
    return matrix


def _read_premultiplied(path: Path, where: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Linear premultiplied colour [H, W, 3] and alpha [H, W, 1] (None without) of a frame.

    PNG colour is straight (Blender writes unassociated alpha) and gets multiplied here; EXR
    colour is premultiplied already (the OpenEXR convention).
    """
    try:
        if path.suffix.lower() == ".exr":
            image, channel_names = read_exr_channels(path)
            return _split_colour_alpha(image, channel_names)
        colour, alpha = _split_colour_alpha(read_image(path))
    except ReconError as error:
        raise DatasetError(f"{where}: cannot read image: {error}") from error
    return (colour if alpha is None else colour * alpha), alpha


def read_nerf_synthetic(
    folder: str | os.PathLike,
    split: str = "train",
    background: str | None = "white",
    scale: float | None = None,
    prefer_exr: bool = False,
    near: float | None = None,
    far: float | None = None,
    strict: bool = False,
    max_resolution: int | None = None,
) -> CaptureSet:
    """Read one split of a NeRF-synthetic (Blender) folder.

    background: 'white' or 'black' composites the images over that colour in linear space;
        None returns them premultiplied by alpha (the same as 'black'; the straight colour of
        fully transparent pixels is unknowable). masks are the alpha channel (1 without one).
    scale: image resolution factor (0.5 halves height and width by area averaging); the
        intrinsics follow. None keeps the stored resolution.
    prefer_exr: read `NAME.exr` (linear, premultiplied RGBA) instead of the PNG when it exists.
    near, far: clip distances; default to the JSON's 'near'/'far' keys, else derived from the
        camera distances to the origin (0.05 x the smallest, 10 x the largest).
    strict: also fail on image files in the frames' folders that no frame references (files
        named like a referenced frame plus '_...', such as 'r_0_depth_0000.png', are allowed).
    max_resolution: shrink every frame on load (antialiased) so that its longer side is at most
        this; the intrinsics follow. Applied before `scale`.
    Images without alpha take their masks from `masks/` beside the JSON files: the frame's
    path inside it ('masks/train/r_0.png') or its stem alone ('masks/r_0.png'), PNG or JPG, 1
    or 3 channels; mask_source says which was used ('none': masks are all 1).

    Raises DatasetError naming the file and the problem.
    """
    folder = Path(folder)
    if background not in ("white", "black", None):
        raise ReconError(f"background: expected 'white', 'black' or None, got {background!r}")
    if scale is not None and not scale > 0:
        raise ReconError(f"scale: expected a positive resolution factor, got {scale}")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: NeRF-synthetic folder not found")
    json_path = folder / f"transforms_{split}.json"
    if not json_path.is_file():
        found = sorted(path.name for path in folder.glob("transforms_*.json"))
        raise DatasetError(
            f"{json_path}: transforms file for split {split!r} not found "
            f"(the folder has {found if found else 'no transforms_*.json'})"
        )
    settings = _load_json(json_path)
    if not isinstance(settings, dict):
        raise DatasetError(
            f"{json_path}: expected a JSON object at the top, got {type(settings).__name__}"
        )
    if "frames" not in settings:
        raise DatasetError(f"{json_path}: missing key 'frames'")
    frames = settings["frames"]
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{json_path}: 'frames' must be a non-empty list, got {frames!r:.80}")
    if (
        "camera_angle_x" not in settings
        and "fl_x" not in settings
        and not all(
            isinstance(frame, dict) and ("camera_angle_x" in frame or "fl_x" in frame)
            for frame in frames
        )
    ):
        raise DatasetError(
            f"{json_path}: missing key 'camera_angle_x' (horizontal field of view in radians; "
            "or give 'fl_x' in pixels)"
        )

    images = masks = None
    stored_size: tuple[int, int] | None = None
    sources: set[str] = set()
    matrices, intrinsics, names, image_paths = [], [], [], []
    for index, frame in enumerate(frames):
        where = f"{json_path}: frames[{index}]"
        matrix = _frame_matrix(frame, where)
        image_path = _frame_image_path(folder, frame["file_path"], prefer_exr)
        if not image_path.is_file():
            raise DatasetError(f"{where}: image file {image_path} not found")
        premultiplied, alpha = _read_premultiplied(image_path, where)
        image_size = (int(premultiplied.shape[0]), int(premultiplied.shape[1]))
        if alpha is None:
            mask_path = _nerf_mask_path(folder, image_path)
            if mask_path is not None:
                alpha = read_mask(mask_path, image_size)
                premultiplied = premultiplied * alpha
                sources.add("masks")
            else:
                sources.add("none")
        else:
            sources.add("alpha")
        target_size = (
            _note_cap(image_size, max_resolution, json_path)
            if stored_size is None
            else capped_size(image_size, max_resolution)
        )
        if target_size != image_size:
            premultiplied = shrink_image(premultiplied, target_size)
            alpha = None if alpha is None else shrink_image(alpha, target_size)
        if stored_size is None:
            stored_size = image_size
            for key, expected in (("h", image_size[0]), ("w", image_size[1])):
                if key in settings and _number(settings[key], f"{json_path}: {key}") != expected:
                    raise DatasetError(
                        f"{json_path}: '{key}' is {settings[key]} but image {image_path} has "
                        f"{'height' if key == 'h' else 'width'} {expected}"
                    )
            # Filled frame by frame: a Blender split (100 x 800 x 800) is large enough that a
            # list of frames plus a stacked copy would double the peak memory.
            images = torch.empty(len(frames), *target_size, 3)
            masks = torch.empty(len(frames), *target_size, 1)
        elif image_size != stored_size:
            raise DatasetError(
                f"{where}: image {image_path} has size (H, W) = {image_size}, expected "
                f"{stored_size} like the first frame"
            )
        images[index] = premultiplied
        masks[index] = 1.0 if alpha is None else alpha.clamp(0.0, 1.0)
        matrices.append(matrix)
        intrinsics.append(_frame_intrinsics(settings, frame, image_size, where, json_path))
        names.append(image_path.stem)
        image_paths.append(image_path)

    if strict:
        _check_unreferenced(json_path, image_paths)
    if background == "white":
        images += 1.0 - masks
    size = (int(images.shape[1]), int(images.shape[2]))
    cam_to_world = torch.from_numpy(np.stack(matrices))
    near, far = _resolve_near_far(near, far, settings, json_path, cam_to_world[:, :3, 3])
    cameras = Cameras(
        world_to_cam=opengl_cam_to_world_to_world_to_cam(cam_to_world).float(),
        intrinsics=torch.tensor(intrinsics, dtype=torch.float32),
        image_size=stored_size,
        near=near,
        far=far,
    ).with_image_size(size)
    if scale is not None and scale != 1:
        new_size = (max(1, round(size[0] * scale)), max(1, round(size[1] * scale)))
        images, masks = _resize(images, new_size), _resize(masks, new_size)
        cameras = cameras.with_image_size(new_size)
    if len(sources) > 1:
        raise DatasetError(
            f"{json_path}: frames mix coverage sources {sorted(sources)} (alpha channel, mask "
            "images, none): give every frame the same"
        )
    return CaptureSet(
        cameras=cameras,
        images=images,
        masks=masks,
        names=names,
        split=split,
        mask_source=sources.pop(),
        metadata=[read_exif(path) for path in image_paths],
    )


def _nerf_mask_path(folder: Path, image_path: Path) -> Path | None:
    """masks/<the image's path relative to folder, any image suffix>, else masks/<stem>.*"""
    masks_folder = folder / "masks"
    if not masks_folder.is_dir():
        return None
    try:
        relative = image_path.relative_to(folder)
    except ValueError:
        relative = Path(image_path.name)
    nested = find_mask_file(masks_folder / relative.parent, relative.stem)
    return nested if nested is not None else find_mask_file(masks_folder, image_path.stem)


def _resolve_near_far(
    near: float | None,
    far: float | None,
    settings: dict[str, Any],
    json_path: Path,
    centres: torch.Tensor,
) -> tuple[float, float]:
    """Explicit arguments first, then the JSON's 'near'/'far', then camera distances."""
    derived_near, derived_far = _near_far_from_distances(centres)
    if near is None:
        near = (
            _number(settings["near"], f"{json_path}: near") if "near" in settings else derived_near
        )
    if far is None:
        far = _number(settings["far"], f"{json_path}: far") if "far" in settings else derived_far
    if not 0 < near < far:
        raise DatasetError(f"{json_path}: expected 0 < near < far, got near={near}, far={far}")
    return near, far


def _check_unreferenced(json_path: Path, image_paths: list[Path]) -> None:
    """DatasetError when the frames' folders hold image files no frame references."""
    referenced = {path.with_suffix("") for path in image_paths}
    for directory in sorted({path.parent for path in image_paths}):
        extra = [
            path.name
            for path in _image_files(directory)
            if path.with_suffix("") not in referenced
            # Auxiliary maps of a frame ('r_0_depth_0000.png' next to 'r_0.png') are not extra.
            and not any(path.stem.startswith(stem.name + "_") for stem in referenced)
        ]
        if extra:
            shown = ", ".join(extra[:5]) + (", ..." if len(extra) > 5 else "")
            raise DatasetError(
                f"{json_path}: {len(extra)} image file(s) in {directory} are not referenced by "
                f"any frame (strict=True): {shown}"
            )


# --------------------------------------------------------------------------------------------
# NeRF-synthetic writer
# --------------------------------------------------------------------------------------------


def write_nerf_synthetic(
    folder: str | os.PathLike,
    split: str,
    cameras: Cameras,
    images: torch.Tensor,
    masks: torch.Tensor | None = None,
    names: Sequence[str] | None = None,
    write_exr: bool = True,
    force: bool = False,
    background: str | None = None,
) -> Path:
    """Write one split in the NeRF-synthetic layout; read_nerf_synthetic reads it back.

    images: [B, H, W, 3] linear colour, composited over `background`: None or 'black' means
        premultiplied by the masks (what a renderer outputs with coverage), 'white' means over
        white. masks: [B, H, W, 1] coverage (default 1).
    Writes `{split}/{name}.png` (RGBA, straight sRGB colour with alpha = coverage, 8 bits),
    `{split}/{name}.exr` (linear premultiplied float32 RGBA) when write_exr, and
    `transforms_{split}.json` with camera_angle_x, fl_x, fl_y, cx, cy, w, h, near, far and
    per-frame file_path './{split}/{name}' and OpenGL camera-to-world transform_matrix (per-frame
    fl_x, fl_y, cx, cy too when the intrinsics differ between cameras). names default to r_0,
    r_1, ... Every file is written atomically, images first and the JSON last. Existing files are
    never overwritten unless force=True (DatasetError naming the path). Returns the JSON path.
    """
    folder = Path(folder)
    count = len(cameras)
    height, width = cameras.image_size
    images = torch.as_tensor(images).detach().to("cpu", torch.float32)
    if tuple(images.shape) != (count, height, width, 3):
        raise ReconError(
            f"images: expected shape [{count}, {height}, {width}, 3] (cameras' count and size), "
            f"got {tuple(images.shape)}"
        )
    if masks is None:
        masks = torch.ones(count, height, width, 1)
    masks = torch.as_tensor(masks).detach().to("cpu", torch.float32).clamp(0.0, 1.0)
    if tuple(masks.shape) != (count, height, width, 1):
        raise ReconError(
            f"masks: expected shape [{count}, {height}, {width}, 1], got {tuple(masks.shape)}"
        )
    if background not in ("white", "black", None):
        raise ReconError(f"background: expected 'white', 'black' or None, got {background!r}")
    names = (
        [f"r_{index}" for index in range(count)] if names is None else [str(name) for name in names]
    )
    if len(names) != count or len(set(names)) != count:
        raise ReconError(f"names: expected {count} unique names, got {names}")
    for name in names:
        if not name or "/" in name or "\\" in name or name.startswith("."):
            raise ReconError(f"names: {name!r} is not a plain file name")

    json_path = folder / f"transforms_{split}.json"
    targets = [json_path]
    for name in names:
        targets.append(folder / split / f"{name}.png")
        if write_exr:
            targets.append(folder / split / f"{name}.exr")
    if not force:
        existing = [path for path in targets if path.exists()]
        if existing:
            raise DatasetError(
                f"{existing[0]}: already exists ({len(existing)} of the split's files do); "
                "pass force=True to overwrite"
            )

    premultiplied = images - (1.0 - masks) if background == "white" else images
    # Straight colour for the PNG; pixels without coverage have no colour and are written black.
    covered = masks > 0
    straight = torch.where(
        covered, premultiplied / masks.clamp(min=1e-12), torch.zeros_like(images)
    )
    for index, name in enumerate(names):
        write_png(
            folder / split / f"{name}.png", torch.cat([straight[index], masks[index]], dim=-1)
        )
        if write_exr:
            write_exr_file(
                folder / split / f"{name}.exr",
                torch.cat([premultiplied[index], masks[index]], dim=-1),
            )

    intrinsics = cameras.intrinsics.detach().cpu().double()
    cam_to_world = world_to_cam_to_opengl_cam_to_world(cameras.world_to_cam.detach().cpu().double())
    first = intrinsics[0]
    per_frame_intrinsics = not bool(torch.equal(intrinsics, first.expand_as(intrinsics)))
    frames = []
    for index, name in enumerate(names):
        frame: dict[str, Any] = {
            "file_path": f"./{split}/{name}",
            "transform_matrix": cam_to_world[index].tolist(),
        }
        if per_frame_intrinsics:
            frame.update(_intrinsics_keys(intrinsics[index]))
        frames.append(frame)
    settings = {
        "camera_angle_x": 2.0 * math.atan(0.5 * width / float(first[0, 0])),
        **_intrinsics_keys(first),
        "w": width,
        "h": height,
        "near": float(cameras.near),
        "far": float(cameras.far),
        "frames": frames,
    }
    atomic_write_json(json_path, settings)
    return json_path


def _intrinsics_keys(intrinsics: torch.Tensor) -> dict[str, float]:
    return {
        "fl_x": float(intrinsics[0, 0]),
        "fl_y": float(intrinsics[1, 1]),
        "cx": float(intrinsics[0, 2]),
        "cy": float(intrinsics[1, 2]),
    }


# --------------------------------------------------------------------------------------------
# LLFF / NeRD reader
# --------------------------------------------------------------------------------------------


def llff_to_world_to_cam(poses: torch.Tensor) -> torch.Tensor:
    """OpenCV world-to-camera [N, 4, 4] from LLFF camera-to-world [N, 3, 4] ([down, right, back]).

    See the module docstring: OpenCV camera axes [right, down, forward] = [col1, col0, -col2].
    """
    rotation = poses[:, :, :3]
    camera_to_world = torch.zeros(poses.shape[0], 4, 4, dtype=poses.dtype)
    camera_to_world[:, :3, 0] = rotation[:, :, 1]
    camera_to_world[:, :3, 1] = rotation[:, :, 0]
    camera_to_world[:, :3, 2] = -rotation[:, :, 2]
    camera_to_world[:, :3, 3] = poses[:, :, 3]
    camera_to_world[:, 3, 3] = 1.0
    return rigid_inverse(camera_to_world)


def llff_downscale_for(folder: str | os.PathLike, max_resolution: int | None) -> int | None:
    """The largest N of the LLFF folder's `images_N/` downscales whose images are still at
    least max_resolution on their longer side (from poses_bounds.npy's full size), so that a
    large capture is read from its prepared smaller copies; None when there is none (or no
    cap). A folder with another count of images than images/ is ignored."""
    folder = Path(folder)
    if max_resolution is None or not (folder / "images").is_dir():
        return None
    try:
        table = np.load(folder / "poses_bounds.npy", allow_pickle=False)
        longer = float(max(table[0, 4], table[0, 9]))  # hwf: H, W in the pose's last column
    except (OSError, ValueError, IndexError):
        return None  # read_llff reports a broken table
    count = len(_image_files(folder / "images"))
    best = None
    for candidate in folder.glob("images_*"):
        suffix = candidate.name.removeprefix("images_")
        if not suffix.isdigit() or int(suffix) < 2 or not candidate.is_dir():
            continue
        factor = int(suffix)
        if longer / factor >= max_resolution and len(_image_files(candidate)) == count:
            best = factor if best is None else max(best, factor)
    return best


def read_llff(
    folder: str | os.PathLike,
    factor: float | None = None,
    near: float | None = None,
    far: float | None = None,
    max_resolution: int | None = None,
    premultiply: bool = False,
) -> CaptureSet:
    """Read an LLFF / NeRD folder: poses_bounds.npy + images/ (+ masks/).

    factor: downsampling factor (4 reads `images_4/` and `masks_4/` when they exist, else shrinks
        images/ and masks/ by area averaging). Intrinsics come from each pose's hwf (focal in
        pixels, principal point at the centre) scaled to the size of the images read.
    Images are matched to poses in sorted file-name order (LLFF's convention); masks to images
    by file stem (any of PNG/JPG), or in sorted order when no stem matches.
    masks: each mask image as linear coverage (no sRGB decoding; 1 channel as is, 3 averaged);
        without masks/, the images' alpha, else 1 (mask_source 'none').
    max_resolution: shrink every image as it is read (antialiased) so that its longer side is at
        most this; the intrinsics follow.
    premultiply: return colour x mask (multiplied before shrinking, as a coarser sensor would
        integrate the object's radiance) instead of the photos' straight colour.
    near, far: default to 0.9 x the smallest near bound and 1.1 x the largest far bound.
    Raises DatasetError naming the file and the problem.
    """
    folder = Path(folder)
    if factor is not None and not factor >= 1:
        raise ReconError(f"factor: expected a downsampling factor >= 1, got {factor}")
    if not folder.is_dir():
        raise DatasetError(f"{folder}: LLFF folder not found")
    poses_path = folder / "poses_bounds.npy"
    if not poses_path.is_file():
        raise DatasetError(f"{poses_path}: poses file not found")
    try:
        table = np.load(poses_path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise DatasetError(f"{poses_path}: cannot read ({error})") from error
    if table.ndim != 2 or table.shape[1] != 17 or table.shape[0] == 0:
        raise DatasetError(
            f"{poses_path}: expected shape [N, 17] (a 3x5 pose and 2 bounds per image), "
            f"got {table.shape}"
        )
    if not np.isfinite(table).all():
        raise DatasetError(f"{poses_path}: contains NaN or inf")
    table = table.astype(np.float64)
    poses = torch.from_numpy(table[:, :15].reshape(-1, 3, 5))
    bounds = table[:, 15:]

    suffix = "" if factor in (None, 1) else f"_{factor:g}"
    images_folder = folder / f"images{suffix}"
    if not images_folder.is_dir():
        images_folder = folder / "images"
    if not images_folder.is_dir():
        raise DatasetError(f"{images_folder}: images folder not found")
    # Masks at the images' resolution when there are some (masks_4/ with images_4/); full-size
    # masks/ next to downsampled images_4/ are shrunk to match.
    masks_folder = folder / f"masks{suffix}"
    if images_folder.name == "images" or not masks_folder.is_dir():
        masks_folder = folder / "masks"
    shrink_masks = images_folder.name != "images" and masks_folder.name == "masks"
    image_paths = _image_files(images_folder)
    if len(image_paths) != len(poses):
        raise DatasetError(
            f"{poses_path}: {len(poses)} poses but {len(image_paths)} images in {images_folder}"
        )
    for index in range(len(poses)):
        padded = torch.eye(4, dtype=torch.float64)
        padded[:3, :4] = poses[index, :, :4]
        try:
            check_rigid(padded, f"{poses_path}: pose {index} ({image_paths[index].name})")
        except ReconError as error:
            raise DatasetError(str(error)) from error
    world_to_cam = llff_to_world_to_cam(poses[:, :, :4]).float()

    mask_paths = _llff_mask_paths(masks_folder, image_paths, images_folder)
    size: tuple[int, int] | None = None
    target: tuple[int, int] | None = None
    images = mask_tensor = None
    sources: set[str] = set()
    for index, image_path in enumerate(image_paths):
        try:
            colour, alpha = _split_colour_alpha(read_image(image_path))
        except ReconError as error:
            raise DatasetError(f"{image_path}: cannot read image: {error}") from error
        image_size = (int(colour.shape[0]), int(colour.shape[1]))
        if size is None:
            size = image_size
            target = size
            if factor not in (None, 1) and images_folder.name == "images":
                target = (max(1, round(size[0] / factor)), max(1, round(size[1] / factor)))
            target = _note_cap(target, max_resolution, images_folder)
            # Filled image by image, each shrunk as it is read: a full-resolution capture
            # (119 x 3648^2) never sits in memory at its stored size.
            images = torch.empty(len(image_paths), *target, 3)
            mask_tensor = torch.empty(len(image_paths), *target, 1)
        elif image_size != size:
            raise DatasetError(
                f"{image_path}: image size (H, W) = {image_size}, expected {size} like "
                f"{image_paths[0].name}"
            )
        if mask_paths is not None:
            alpha = read_mask(mask_paths[index], image_size if shrink_masks else None)
            if tuple(alpha.shape[:2]) != image_size:
                raise DatasetError(
                    f"{mask_paths[index]}: mask size (H, W) = {tuple(alpha.shape[:2])}, expected "
                    f"{image_size} like its image {image_path.name}"
                )
            sources.add("masks")
        else:
            sources.add("none" if alpha is None else "alpha")
        if alpha is None:
            alpha = torch.ones_like(colour[..., :1])
        images[index] = shrink_image(colour * alpha if premultiply else colour, target)
        mask_tensor[index] = shrink_image(alpha.clamp(0.0, 1.0), target)
    height, width = target
    if len(sources) > 1:
        raise DatasetError(
            f"{images_folder}: images mix coverage sources {sorted(sources)} (alpha channel, "
            "none): give every image an alpha channel or add masks/"
        )

    hwf = poses[:, :, 4]  # [N, 3] = height, width, focal at the resolution the poses were made
    pose_height, pose_width, focal = hwf[:, 0], hwf[:, 1], hwf[:, 2]
    if bool((pose_height <= 0).any() or (pose_width <= 0).any() or (focal <= 0).any()):
        raise DatasetError(f"{poses_path}: hwf column must be positive, got {hwf[0].tolist()} ...")
    scale_x, scale_y = width / pose_width, height / pose_height
    if not all(
        _same_aspect((height, width), (pose_size_height, pose_size_width))
        for pose_size_height, pose_size_width in zip(
            pose_height.tolist(), pose_width.tolist(), strict=True
        )
    ):
        raise DatasetError(
            f"{poses_path}: images in {images_folder} are {height}x{width} but the poses' hwf says "
            f"{int(pose_height[0])}x{int(pose_width[0])}: the aspect ratios differ"
        )
    intrinsics = torch.zeros(len(poses), 3, 3, dtype=torch.float64)
    intrinsics[:, 0, 0] = focal * scale_x
    intrinsics[:, 1, 1] = focal * scale_y
    intrinsics[:, 0, 2] = width / 2
    intrinsics[:, 1, 2] = height / 2
    intrinsics[:, 2, 2] = 1.0

    if near is None:
        near = 0.9 * float(bounds[:, 0].min())
    if far is None:
        far = 1.1 * float(bounds[:, 1].max())
    if not 0 < near < far:
        raise DatasetError(
            f"{poses_path}: expected positive bounds with near < far, got near={near}, far={far}"
        )
    cameras = Cameras(
        world_to_cam=world_to_cam,
        intrinsics=intrinsics.float(),
        image_size=(height, width),
        near=near,
        far=far,
    )
    names = [path.stem for path in image_paths]
    return CaptureSet(
        cameras=cameras,
        images=images,
        masks=mask_tensor,
        names=names,
        split="all",
        mask_source=sources.pop(),
        metadata=[read_exif(path) for path in image_paths],
    )


def _llff_mask_paths(
    masks_folder: Path, image_paths: list[Path], images_folder: Path
) -> list[Path] | None:
    """The mask file of every image: same stem in masks_folder (any image suffix), else, when
    no stem matches at all, the masks in sorted order (LLFF's habit). None without the folder."""
    if not masks_folder.is_dir():
        return None
    by_stem = [find_mask_file(masks_folder, path.stem) for path in image_paths]
    if all(path is not None for path in by_stem):
        return by_stem
    missing = [path.name for path, mask in zip(image_paths, by_stem, strict=True) if mask is None]
    in_order = _image_files(masks_folder)
    if len(missing) == len(image_paths) and len(in_order) == len(image_paths):
        return in_order
    if len(missing) < len(image_paths):
        shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise DatasetError(
            f"{masks_folder}: no mask for {len(missing)} of {len(image_paths)} images "
            f"(expected a file with the image's stem, e.g. {Path(missing[0]).stem}.png): {shown}"
        )
    raise DatasetError(
        f"{masks_folder}: {len(in_order)} masks but {len(image_paths)} images in {images_folder}"
    )


# LLFF captures have no splits: every 8th image is held out for testing (the LLFF/NeRF habit);
# dataset.holdout_every in a run config changes it.
LLFF_HOLDOUT_EVERY = 8


def dataset_layout(folder: str | os.PathLike) -> str:
    """'llff' (poses_bounds.npy), 'nerf_synthetic' (transforms_*.json) or 'colmap' (a sparse
    model in sparse/0/, sparse/ or the folder), or 'photos' (images/ without poses: read_captures
    estimates them, recon.io.sfm); DatasetError else."""
    from recon.io.colmap import colmap_model_folder

    folder = Path(folder)
    if (folder / "poses_bounds.npy").exists():
        return "llff"
    if any(folder.glob("transforms_*.json")):
        return "nerf_synthetic"
    if colmap_model_folder(folder) is not None:
        return "colmap"
    from recon.io.sfm import has_plain_photos

    if has_plain_photos(folder):
        return "photos"
    raise DatasetError(
        f"{folder}: not a dataset recon reads (expected poses_bounds.npy with images/ (LLFF), "
        "transforms_train.json (NeRF-synthetic), or a COLMAP model in sparse/0/ with images/)"
    )


def has_split(folder: str | os.PathLike, split: str) -> bool:
    """Whether read_captures can read this split: LLFF has 'train' and 'test' (held out by
    index); NeRF-synthetic the splits it has transforms files for."""
    folder = Path(folder)
    if dataset_layout(folder) in ("llff", "colmap", "photos"):
        return split in ("train", "test")
    return (folder / f"transforms_{split}.json").exists()


def held_out_split(folder: str | os.PathLike) -> str:
    """The split that held-out metrics read: 'test' when there is one, else 'val'."""
    return "test" if has_split(folder, "test") else "val"


def read_captures(
    folder: str | os.PathLike, split: str, options: Any = None, keep_frames: bool = False
) -> CaptureSet:
    """One split of a dataset in either layout, as a fit needs it: linear colour premultiplied
    by coverage (background removed), masks from alpha, mask images or a background key.

    NeRF-synthetic: transforms_{split}.json (EXR preferred when present). LLFF/NeRD
    (poses_bounds.npy) and COLMAP (recon.io.colmap): 'test' = every holdout_every-th image and
    'train' the rest.
    options: a recon.config.run_config.DatasetConfig (max_resolution, background_key,
        holdout_every, exposure); None reads at the stored size with LLFF_HOLDOUT_EVERY.
    Photos with neither masks nor alpha are a DatasetError unless options.background_key is
    set (then pixels near that colour are background).
    keep_frames: also keep the photos' straight colour, backdrop included, as
        CaptureSet.frames (LLFF and COLMAP layouts; the diagnosis reads the camera's per-view
        gains off the backdrop, recon.diagnose.backdrop). The frames are read a second time.
    """
    folder = Path(folder)
    max_resolution = getattr(options, "max_resolution", None)
    holdout_every = getattr(options, "holdout_every", LLFF_HOLDOUT_EVERY)
    layout = dataset_layout(folder)
    if layout == "photos":
        from recon.io.sfm import estimate_poses

        estimate_poses(folder, options=getattr(options, "sfm", None))
        layout = "colmap"
    if layout in ("llff", "colmap"):
        if split not in ("train", "test"):
            raise DatasetError(
                f"{folder}: {layout.upper()} datasets have only 'train' and 'test' splits, "
                f"got {split!r}"
            )
        captures = _read_photos(folder, layout, max_resolution, premultiply=True)
        index = torch.arange(len(captures.cameras))
        held_out = index % holdout_every == 0
        chosen = held_out if split == "test" else ~held_out
        selected = torch.nonzero(chosen).squeeze(1)
        metadata = captures.metadata
        frames = None
        if keep_frames:
            straight = _read_photos(folder, layout, max_resolution, premultiply=False)
            frames = straight.images[selected]
        captures = CaptureSet(
            captures.cameras[selected],
            captures.images[selected],
            captures.masks[selected],
            [captures.names[i] for i in selected.tolist()],
            split,
            mask_source=captures.mask_source,
            metadata=None if metadata is None else [metadata[i] for i in selected.tolist()],
            frames=frames,
        )
    else:
        captures = read_nerf_synthetic(
            folder, split, background=None, prefer_exr=True, max_resolution=max_resolution
        )
    captures = _apply_background_key(captures, folder, options)
    if getattr(options, "exposure", "none") == "exif":
        captures.known_gains = exif_gains(captures, folder)
        captures.images = captures.images / captures.known_gains[:, None, None, None]
        if captures.frames is not None:
            captures.frames = captures.frames / captures.known_gains[:, None, None, None]
    return captures


def _read_photos(
    folder: Path, layout: str, max_resolution: int | None, premultiply: bool
) -> CaptureSet:
    """Every photo of an LLFF or COLMAP folder (layout 'llff' or 'colmap'), read_captures'
    reader for that layout."""
    if layout == "llff":
        return read_llff(
            folder,
            factor=llff_downscale_for(folder, max_resolution),
            max_resolution=max_resolution,
            premultiply=premultiply,
        )
    from recon.io.colmap import read_colmap

    return read_colmap(folder, max_resolution=max_resolution, premultiply=premultiply)


def _apply_background_key(captures: CaptureSet, folder: Path, options: Any) -> CaptureSet:
    """Masks from options.background_key where the images have none (their colour is then
    straight), and the colour premultiplied by them; DatasetError without a key."""
    if captures.mask_source != "none":
        return captures
    key = getattr(options, "background_key", None)
    if key is None:
        raise DatasetError(
            f"{folder}: the images have no masks/ folder and no alpha channel, so the object "
            "cannot be told from the background; add masks/ (one PNG or JPG per image, same "
            "file stem, white = object), or set dataset.background_key to the background's "
            "linear RGB colour (e.g. [1, 1, 1]) in the run config"
        )
    colour = torch.tensor(key, dtype=captures.images.dtype)
    difference = (captures.images - colour).abs().amax(-1, keepdim=True)
    tolerance = getattr(options, "background_tolerance", 0.08)
    captures.masks = (difference > tolerance).to(captures.images.dtype)
    captures.images = captures.images * captures.masks
    captures.mask_source = "key"
    return captures


def exif_gains(captures: CaptureSet, folder: Path) -> torch.Tensor:
    """Per-view known gains [B]: EXIF exposure (time x ISO / f-number^2) over the median of
    the views. DatasetError naming the first image whose EXIF lacks a value."""
    values = []
    for name, metadata in zip(
        captures.names, captures.metadata or [{}] * len(captures), strict=True
    ):
        value = exposure_value(metadata)
        if value is None:
            raise DatasetError(
                f"{folder}: dataset.exposure is 'exif' but image {name!r} has no EXIF "
                f"exposure time, f-number and ISO (got {metadata})"
            )
        values.append(value)
    gains = torch.tensor(values, dtype=torch.float64)
    return (gains / gains.median()).float()
