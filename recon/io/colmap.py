"""COLMAP sparse models (cameras, images, points3D; text or binary) -> a CaptureSet.

Read with pycolmap (the COLMAP project's own Python bindings; optional extra `colmap`). COLMAP's
camera frame is OpenCV's (x right, y down, z forward) and cam_from_world maps world points to
it, so its poses are recon's world_to_cam as they are: no axis conversion. Pixel centres are at
i + 0.5 in both.

Layout: FOLDER/images/ (the photos, by the model's image names), FOLDER/masks/ (optional, by
stem, or COLMAP's 'NAME.png' habit for 'NAME.jpg'), the model in FOLDER/sparse/0/,
FOLDER/sparse/ or FOLDER/ itself. Lens distortion (SIMPLE_RADIAL, RADIAL, OPENCV, ...) is known
from the model: every photo and mask is resampled on load to the pinhole camera with the same
focal lengths and principal point (COLMAP's own distortion function maps each pinhole pixel to
the photo), so the fit's pinhole renderer sees undistorted images.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from recon.camera import Cameras
from recon.errors import DatasetError, ReconError
from recon.io.exif import read_exif
from recon.io.images import read_image

# Models whose parameters start with one shared focal length, or with fx, fy (then cx, cy).
SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE"}
TWO_FOCALS = {"PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "THIN_PRISM_FISHEYE"}
PINHOLE_MODELS = {"PINHOLE", "SIMPLE_PINHOLE"}
# near = this x the nearest point depth, far = the farthest x its inverse (with margins).
DEPTH_MARGIN = 0.5


def colmap_model_folder(folder: str | os.PathLike) -> Path | None:
    """The folder holding cameras.{txt,bin} (sparse/0, sparse, or folder itself), or None."""
    folder = Path(folder)
    for candidate in (folder / "sparse" / "0", folder / "sparse", folder):
        if (candidate / "cameras.bin").is_file() or (candidate / "cameras.txt").is_file():
            return candidate
    return None


def _pycolmap():
    try:
        import pycolmap
    except ImportError as error:
        raise DatasetError(
            "reading a COLMAP model needs pycolmap: pip install 'recon[colmap]' "
            "(or pip install pycolmap)"
        ) from error
    return pycolmap


def _pose_matrix(image) -> np.ndarray:
    """cam_from_world as a 3x4 matrix (a method in pycolmap >= 3.12, a property before)."""
    transform = image.cam_from_world
    transform = transform() if callable(transform) else transform
    return np.asarray(transform.matrix(), dtype=np.float64)


def _intrinsics(camera) -> np.ndarray:
    """[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] of a COLMAP camera of any supported model."""
    name = camera.model.name
    params = np.asarray(camera.params, dtype=np.float64)
    if name in SINGLE_FOCAL:
        fx = fy = params[0]
        cx, cy = params[1], params[2]
    elif name in TWO_FOCALS:
        fx, fy, cx, cy = params[:4]
    else:
        raise DatasetError(f"COLMAP camera {camera.camera_id}: unsupported model {name}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def undistortion_grid(camera, size: tuple[int, int]) -> torch.Tensor | None:
    """grid_sample coordinates [1, H, W, 2] that resample a photo of `camera` to the pinhole
    camera with its focal lengths and principal point; None for pinhole models."""
    if camera.model.name in PINHOLE_MODELS:
        return None
    height, width = size
    intrinsics = _intrinsics(camera)
    columns, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (columns - intrinsics[0, 2]) / intrinsics[0, 0]
    y = (rows - intrinsics[1, 2]) / intrinsics[1, 1]
    points = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=-1)
    pixels = np.asarray(camera.img_from_cam(points), dtype=np.float64).reshape(height, width, 2)
    # grid_sample with align_corners=False: -1 and 1 are the outer edges of the border pixels.
    normalised = np.stack([pixels[..., 0] / width * 2 - 1, pixels[..., 1] / height * 2 - 1], -1)
    return torch.from_numpy(normalised).float()[None]


def _resample(image: torch.Tensor, grid: torch.Tensor | None) -> torch.Tensor:
    """[H, W, C] bilinearly resampled at grid (zeros outside the photo)."""
    if grid is None:
        return image
    sampled = torch.nn.functional.grid_sample(
        image.permute(2, 0, 1)[None], grid, mode="bilinear", align_corners=False
    )
    return sampled[0].permute(1, 2, 0).contiguous()


def _mask_path(masks_folder: Path, image_name: str) -> Path | None:
    from recon.io.datasets import find_mask_file

    if not masks_folder.is_dir():
        return None
    colmap_style = masks_folder / f"{image_name}.png"
    if colmap_style.is_file():
        return colmap_style
    return find_mask_file(masks_folder / Path(image_name).parent, Path(image_name).stem)


def read_colmap(
    folder: str | os.PathLike,
    max_resolution: int | None = None,
    premultiply: bool = False,
):
    """Read a COLMAP dataset folder (see the module docstring) into a CaptureSet (split 'all').

    Registered images in name order; all must share one image size. masks: from masks/ (by
    stem, or 'NAME.jpg.png'), else the images' alpha, else 1 (mask_source 'none').
    max_resolution, premultiply: as recon.io.datasets.read_llff. near/far: from the depths of
    the model's 3D points (a margin either side), else from the camera distances.
    metadata: EXIF per image plus the COLMAP camera model and its parameters.
    """
    from recon.io.datasets import (
        CaptureSet,
        _near_far_from_distances,
        _note_cap,
        _split_colour_alpha,
        read_mask,
        shrink_image,
    )

    folder = Path(folder)
    model_folder = colmap_model_folder(folder)
    if model_folder is None:
        raise DatasetError(
            f"{folder}: no COLMAP model (cameras.bin/.txt in sparse/0/, sparse/ or the folder)"
        )
    pycolmap = _pycolmap()
    try:
        model = pycolmap.Reconstruction(str(model_folder))
    except (RuntimeError, ValueError, IndexError) as error:
        raise DatasetError(f"{model_folder}: cannot read the COLMAP model ({error})") from error
    images_folder = folder / "images"
    if not images_folder.is_dir():
        raise DatasetError(f"{images_folder}: images folder not found")
    registered = sorted(
        (model.images[image_id] for image_id in model.reg_image_ids()), key=lambda im: im.name
    )
    if not registered:
        raise DatasetError(f"{model_folder}: the model has no registered images")
    sizes = {
        (model.cameras[im.camera_id].height, model.cameras[im.camera_id].width) for im in registered
    }
    if len(sizes) != 1:
        raise DatasetError(
            f"{model_folder}: images of several sizes {sorted(sizes)}; recon needs one"
        )
    size = sizes.pop()
    target = _note_cap(size, max_resolution, images_folder)
    count = len(registered)
    images = torch.empty(count, *target, 3)
    masks = torch.empty(count, *target, 1)
    world_to_cam = torch.zeros(count, 4, 4, dtype=torch.float64)
    intrinsics = torch.zeros(count, 3, 3, dtype=torch.float64)
    grids: dict[int, torch.Tensor | None] = {}
    sources: set[str] = set()
    metadata = []
    for index, image in enumerate(registered):
        camera = model.cameras[image.camera_id]
        path = images_folder / image.name
        if not path.is_file():
            raise DatasetError(f"{path}: image of the COLMAP model not found")
        try:
            colour, alpha = _split_colour_alpha(read_image(path))
        except ReconError as error:
            raise DatasetError(f"{path}: cannot read image: {error}") from error
        if tuple(colour.shape[:2]) != size:
            raise DatasetError(
                f"{path}: image size (H, W) = {tuple(colour.shape[:2])}, but COLMAP camera "
                f"{image.camera_id} says {size}"
            )
        mask_path = _mask_path(folder / "masks", image.name)
        if mask_path is not None:
            alpha = read_mask(mask_path, size)
            sources.add("masks")
        else:
            sources.add("none" if alpha is None else "alpha")
        if alpha is None:
            alpha = torch.ones_like(colour[..., :1])
        if image.camera_id not in grids:
            grids[image.camera_id] = undistortion_grid(camera, size)
        grid = grids[image.camera_id]
        colour, alpha = _resample(colour, grid), _resample(alpha, grid)
        images[index] = shrink_image(colour * alpha if premultiply else colour, target)
        masks[index] = shrink_image(alpha.clamp(0.0, 1.0), target)
        world_to_cam[index, :3] = torch.from_numpy(_pose_matrix(image))
        world_to_cam[index, 3, 3] = 1.0
        intrinsics[index] = torch.from_numpy(_intrinsics(camera))
        metadata.append(
            {
                **read_exif(path),
                "colmap_model": camera.model.name,
                "colmap_params": [float(v) for v in camera.params],
                "undistorted": grid is not None,
            }
        )
    if len(sources) > 1:
        raise DatasetError(f"{images_folder}: images mix coverage sources {sorted(sources)}")
    cameras = Cameras(
        world_to_cam.float(), intrinsics.float(), size, *_near_far(model, world_to_cam)
    ).with_image_size(target)
    if cameras.near <= 0:
        near, far = _near_far_from_distances(cameras.centers())
        cameras = Cameras(cameras.world_to_cam, cameras.intrinsics, target, near, far)
    return CaptureSet(
        cameras=cameras,
        images=images,
        masks=masks,
        names=[Path(image.name).stem for image in registered],
        split="all",
        mask_source=sources.pop(),
        metadata=metadata,
    )


def _near_far(model, world_to_cam: torch.Tensor) -> tuple[float, float]:
    """(near, far) bracketing the depths of the model's points in every camera, with margins;
    from the camera distances to the origin when the model has no points in front."""
    from recon.io.datasets import _near_far_from_distances

    points = np.array([point.xyz for point in model.points3D.values()], dtype=np.float64)
    if len(points):
        rotation = world_to_cam[:, :3, :3].numpy()
        translation = world_to_cam[:, :3, 3].numpy()
        depths = np.einsum("bij,nj->bni", rotation, points)[..., 2] + translation[:, None, 2]
        depths = depths[depths > 0]
        if depths.size:
            return DEPTH_MARGIN * float(depths.min()), float(depths.max()) / DEPTH_MARGIN
    rotation = world_to_cam[:, :3, :3]
    centres = -(rotation.transpose(1, 2) @ world_to_cam[:, :3, 3:])[..., 0]
    return _near_far_from_distances(centres)
