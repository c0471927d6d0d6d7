"""Cheap checks of a dataset folder before any expensive stage reads it.

The readers (recon.io.datasets) validate every file when a stage loads it, but a fit reads the
training split first and the evaluation reads the held-out split only after the whole fit. These
checks look at the layout and the image headers only (no pixels decoded), so that a wrong folder,
a missing split or image sizes that differ between splits fail in a second, not after the fit.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image

from recon.config.run_config import MINIMUM_VIEW_SIZE
from recon.errors import DatasetError
from recon.io.datasets import _frame_image_path, dataset_layout

SPLITS = ("train", "val", "test")


@dataclass
class DatasetSummary:
    """What a dataset folder holds.

    layout: recon.io.datasets.dataset_layout's name ('nerf_synthetic', 'llff', 'colmap',
    'photos'). splits: split name -> number of views (LLFF: the whole
    capture under 'all'). image_size: (height, width) of the first view of each split.
    warnings: things that are legal but a user should know (e.g. evaluation falls back to 'val').
    """

    folder: Path
    layout: str
    splits: dict[str, int] = field(default_factory=dict)
    image_size: dict[str, tuple[int, int]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def heldout_split(self) -> str | None:
        """The split the evaluation scores: 'test', else 'val' (with a warning), else None."""
        if self.layout != "nerf_synthetic" or self.splits.get("test"):
            return "test"
        return "val" if self.splits.get("val") else None


def _header_size(path: Path, where: str) -> tuple[int, int]:
    """(height, width) from an image file's header without decoding its pixels."""
    if not path.is_file():
        raise DatasetError(f"{path}: image named by {where} not found")
    if path.suffix.lower() == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(path), header_only=True) as exr:
                window = exr.header()["dataWindow"]
        except Exception as error:  # OpenEXR raises RuntimeError/OSError for damaged files
            raise DatasetError(f"{path}: cannot read the EXR header ({error})") from error
        (left, top), (right, bottom) = window
        return int(bottom - top + 1), int(right - left + 1)
    try:
        with Image.open(path) as image:
            width, height = image.size
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read the image header ({error})") from error
    return height, width


def _nerf_split(folder: Path, split: str, summary: DatasetSummary) -> None:
    json_path = folder / f"transforms_{split}.json"
    try:
        settings = json.loads(json_path.read_text(encoding="utf-8"))
    except OSError as error:
        raise DatasetError(f"{json_path}: cannot read ({error})") from error
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"{json_path}: invalid JSON at line {error.lineno}, column {error.colno}: {error.msg}"
        ) from error
    frames = settings.get("frames") if isinstance(settings, dict) else None
    if not isinstance(frames, list):
        raise DatasetError(f"{json_path}: expected a 'frames' list")
    summary.splits[split] = len(frames)
    if not frames:
        return
    first = frames[0]
    file_path = first.get("file_path") if isinstance(first, dict) else None
    if not isinstance(file_path, str):
        raise DatasetError(
            f"{json_path}: frames[0].file_path: expected a string, got {file_path!r}"
        )
    image = _frame_image_path(folder, file_path, prefer_exr=False)
    summary.image_size[split] = _header_size(image, f"{json_path.name} frames[0]")


def check_dataset(folder: str | Path, heldout_needed: bool = False) -> DatasetSummary:
    """Check a dataset folder's layout, splits and image sizes; raise DatasetError naming the file.

    heldout_needed: the run evaluates, so a held-out split ('test', or 'val' as a fallback that
    is reported in warnings) must exist.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: dataset folder not found")
    layout = dataset_layout(folder)
    if layout != "nerf_synthetic":
        # LLFF, COLMAP and plain photo folders hold one set of views; the readers hold every
        # holdout_every-th out and check the images and masks as they load them.
        summary = DatasetSummary(folder, layout)
        images = folder / "images"
        if layout == "llff" and not images.is_dir():
            raise DatasetError(f"{images}: the LLFF folder has no images/ folder")
        return summary
    found = sorted(path.name for path in folder.glob("transforms_*.json"))
    if not (folder / "transforms_train.json").is_file():
        raise DatasetError(
            f"{folder / 'transforms_train.json'}: not found; expected a NeRF-synthetic folder "
            f"(transforms_train.json) or an LLFF folder (poses_bounds.npy), the folder has "
            f"{found if found else 'neither'}"
        )
    summary = DatasetSummary(folder, "nerf_synthetic")
    for split in SPLITS:
        if (folder / f"transforms_{split}.json").is_file():
            _nerf_split(folder, split, summary)
    sizes = summary.image_size
    for split, (height, width) in sizes.items():
        if min(height, width) < MINIMUM_VIEW_SIZE:
            raise DatasetError(
                f"{folder}: the {split} views are {height}x{width}; expected at least "
                f"{MINIMUM_VIEW_SIZE} px a side (evaluation's SSIM window)"
            )
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{split} {size[0]}x{size[1]}" for split, size in sizes.items())
        raise DatasetError(
            f"{folder}: image sizes differ between splits ({listed}); expected one size "
            "(height x width) for every split"
        )
    if heldout_needed:
        split = summary.heldout_split
        if split is None:
            raise DatasetError(
                f"{folder}: no held-out views to evaluate on (no transforms_test.json, and "
                "transforms_val.json is missing or empty)"
            )
        if split == "val":
            summary.warnings.append(
                f"{folder}: no transforms_test.json; the evaluation scores the "
                f"{summary.splits['val']} view(s) of the 'val' split instead"
            )
    return summary
