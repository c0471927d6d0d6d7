"""What a dataset folder holds, asked in one place: its kind, its splits, its extra captures.

Stages ask a `DatasetLayout` rather than probing for `transforms_*.json` themselves, so that a
layout without split files (LLFF, COLMAP, plain photos: 'train' and 'test' by index) answers the
same questions as a NeRF-synthetic folder.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

# A dataset's relight split may carry its light (a known capture condition) in this file, in the
# lighting JSON format of recon.render.shading.Lighting.from_json.
RELIGHT_LIGHTING = "lighting_relight.json"
# A dataset's flat-field frames (a uniformly lit card filling the frame, through the capture's
# camera chain; see recon.config.run_config.FlatFieldConfig) are this split. No fit reads it.
FLAT_FIELD_SPLIT = "flat_field"
# A dataset's line-target frames (a card of straight stripes filling the frame, through the
# capture's camera chain; see recon.config.run_config.LineTargetConfig). No fit reads it.
LINE_TARGET_SPLIT = "line_target"
# The split of views under another, known light (capture.relight).
RELIGHT_SPLIT = "relight"


@dataclass(frozen=True)
class DatasetLayout:
    """One dataset folder's layout (recon.io.datasets reads it).

    folder: the dataset's root (a NeRF-synthetic folder, an LLFF/NeRD folder, a COLMAP project
    or a folder of photos).
    """

    folder: Path

    @classmethod
    def of(cls, folder: str | os.PathLike) -> DatasetLayout:
        return cls(Path(folder))

    @property
    def kind(self) -> str:
        """'nerf_synthetic', 'llff', 'colmap' or 'photos' (DatasetError for none of them)."""
        from recon.io.datasets import dataset_layout

        return dataset_layout(self.folder)

    def split_file(self, split: str) -> Path:
        """A NeRF-synthetic split's transforms file (the other layouts have none)."""
        return self.folder / f"transforms_{split}.json"

    def has_split(self, split: str) -> bool:
        """Whether read_captures can read this split: LLFF, COLMAP and photos have 'train' and
        'test' (held out by index); NeRF-synthetic the splits it has transforms files for. A
        folder that does not exist has none."""
        if not self.folder.is_dir():
            return False
        from recon.io.datasets import has_split

        return has_split(self.folder, split)

    @property
    def held_out_split(self) -> str:
        """The split that held-out metrics read: 'test' when there is one, else 'val'."""
        return "test" if self.has_split("test") else "val"

    @property
    def has_relight(self) -> bool:
        """Views of the object under another, known light (capture.relight)."""
        return self.split_file(RELIGHT_SPLIT).is_file()

    @property
    def relight_lighting(self) -> Path:
        """The relight split's light, beside its transforms file."""
        return self.folder / RELIGHT_LIGHTING

    @property
    def has_flat_field(self) -> bool:
        """Flat-field frames (capture.flat_field) beside the views."""
        return self.split_file(FLAT_FIELD_SPLIT).is_file()

    @property
    def flat_field(self) -> Path:
        """The flat-field split's folder (its frames)."""
        return self.folder / FLAT_FIELD_SPLIT

    @property
    def has_line_target(self) -> bool:
        """Line-target frames (capture.line_target) beside the views."""
        return self.split_file(LINE_TARGET_SPLIT).is_file()

    @property
    def line_target(self) -> Path:
        """The line-target split's folder (its frames)."""
        return self.folder / LINE_TARGET_SPLIT

    def split_files(self) -> list[Path]:
        """Every NeRF-synthetic transforms file, sorted by name (none for the other layouts)."""
        return sorted(self.folder.glob("transforms_*.json"))
