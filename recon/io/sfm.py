"""Poses for a plain folder of photos (+ masks): structure from motion on the CPU through
pycolmap (COLMAP's SIFT features, exhaustive matching and incremental mapper), cached in the
dataset folder as a COLMAP model that recon.io.colmap then reads.

FOLDER/images/ holds the photos and FOLDER/masks/ (optional, by stem) their masks; features are
taken on the object only (COLMAP ignores mask pixels that are 0), which a turntable capture
needs: its background stays still while the object turns. The result is written once to
FOLDER/sparse/0/ (binary model) with COLMAP's database beside it in FOLDER/sparse/; an existing
FOLDER/sparse/ is used as it is and never overwritten.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from recon.config.run_config import SfmConfig
from recon.errors import DatasetError, warn_user


def has_plain_photos(folder: str | os.PathLike) -> bool:
    """Whether folder has images/ with photos (and no poses of any kind: the caller checks)."""
    from recon.io.datasets import _image_files

    images = Path(folder) / "images"
    return images.is_dir() and len(_image_files(images)) > 0


def _colmap_masks(folder: Path, names: list[str], target: Path) -> bool:
    """COLMAP-style masks (target/NAME.png, 0 = ignore) from masks/ by stem; False without."""
    from recon.io.datasets import find_mask_file

    masks = folder / "masks"
    if not masks.is_dir():
        return False
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        mask_path = find_mask_file(masks, Path(name).stem)
        if mask_path is None:
            raise DatasetError(f"{masks}: no mask for {name} (expected {Path(name).stem}.png)")
        with Image.open(mask_path) as image:
            values = np.asarray(image.convert("L"))
        Image.fromarray(((values >= 128) * 255).astype(np.uint8)).save(target / f"{name}.png")
    return True


def estimate_poses(
    folder: str | os.PathLike,
    camera_model: str = "SIMPLE_RADIAL",
    options: SfmConfig | None = None,
) -> Path:
    """Run structure from motion on folder/images (one shared camera of camera_model) and cache
    the largest model in folder/sparse/0; returns that path. An existing folder/sparse/0 is
    returned untouched. options: config dataset.sfm (features and mapper). DatasetError when
    pycolmap is missing or no model can be built."""
    options = options or SfmConfig()
    from recon.io.colmap import _pycolmap
    from recon.io.datasets import _image_files

    folder = Path(folder)
    cached = folder / "sparse" / "0"
    if (cached / "cameras.bin").is_file() or (cached / "cameras.txt").is_file():
        return cached
    if (folder / "sparse").exists():
        raise DatasetError(
            f"{folder / 'sparse'}: exists but holds no model in sparse/0; move it away to let "
            "recon estimate the poses again"
        )
    pycolmap = _pycolmap()
    images = folder / "images"
    names = [path.name for path in _image_files(images)]
    if len(names) < 3:
        raise DatasetError(
            f"{images}: structure from motion needs at least 3 photos, got {len(names)}"
        )
    warn_user(
        f"{folder}: no poses; estimating them by structure from motion (pycolmap, "
        f"{len(names)} photos), cached in {cached}",
        kind="note",
    )
    with tempfile.TemporaryDirectory(prefix="recon_sfm_") as scratch:
        scratch = Path(scratch)
        database = scratch / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        if _colmap_masks(folder, names, scratch / "masks"):
            reader.mask_path = str(scratch / "masks")
        extraction = pycolmap.FeatureExtractionOptions()
        # Photos shrunk for a small machine (a few hundred pixels) give COLMAP's default SIFT
        # too few features on the object: a lower contrast threshold keeps more.
        extraction.sift.peak_threshold = options.peak_threshold
        pycolmap.extract_features(
            database,
            images,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        output = scratch / "models"
        output.mkdir()
        mapping = pycolmap.IncrementalPipelineOptions()
        # The same photos give the same poses (RANSAC draws from this seed).
        mapping.random_seed = options.seed
        mapping.min_model_size = 3
        mapping.mapper.init_min_num_inliers = options.init_min_inliers
        models = pycolmap.incremental_mapping(database, images, output, options=mapping)
        if not models:
            raise DatasetError(
                f"{images}: structure from motion registered no model ({len(names)} photos): "
                "the photos may overlap too little or the object be too plain; give poses "
                "(COLMAP, LLFF) instead"
            )
        best = max(models.values(), key=lambda model: model.num_reg_images())
        staging = scratch / "sparse"
        (staging / "0").mkdir(parents=True)
        best.write_binary(str(staging / "0"))
        shutil.copy(database, staging / "database.db")
        # One rename makes the cache appear whole or not at all.
        shutil.move(str(staging), str(folder / "sparse"))
    return cached
