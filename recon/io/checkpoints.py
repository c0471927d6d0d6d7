"""Checkpoint files: torch.save written atomically, so an interrupted stage can always resume."""

from __future__ import annotations

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
                + " (the disk may be full; free space, then continue with --resume)"
            ) from error


def load_checkpoint(path: Path) -> dict | None:
    if not path.exists():
        return None
    return torch.load(path, map_location="cpu", weights_only=False)
