"""Checkpoint files: torch.save written atomically, so an interrupted stage can always resume."""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

from recon.errors import WriteError
from recon.io.atomic import atomic_path

__all__ = ["load_checkpoint", "save_checkpoint"]


def save_checkpoint(path: Path, state: dict) -> None:
    """torch.save to a temp file in the same folder, then rename: never a half-written file."""
    with atomic_path(path) as temporary:
        try:
            torch.save(state, temporary)
        except RuntimeError as error:
            # torch's zip writer reports a failed write (a full disk, a vanished folder) as
            # RuntimeError('[enforce fail at inline_container.cc] ... file write failed').
            raise WriteError(
                f"cannot write checkpoint {path}: {error}".splitlines()[0]
                + f" (the disk may be full: {_free_bytes(path.parent)} free; free space, then "
                "continue with --resume)"
            ) from error


def _free_bytes(folder: Path) -> str:
    """The free space of folder's file system, for the message of a failed write."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "unknown bytes"
    return f"{free / 1024**2:.1f} MiB" if free >= 1024**2 else f"{free} bytes"


def load_checkpoint(path: Path) -> dict | None:
    if not path.exists():
        return None
    return torch.load(path, map_location="cpu", weights_only=False)
