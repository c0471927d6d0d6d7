"""Checkpoints and history: written atomically so an interrupted run can always resume.

save_checkpoint/load_checkpoint live in recon.io.checkpoints (data_synth uses them too).
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import torch

from recon.io.atomic import append_json_line, atomic_path
from recon.io.checkpoints import load_checkpoint, save_checkpoint

__all__ = [
    "History",
    "load_checkpoint",
    "random_states",
    "restore_random_states",
    "save_checkpoint",
]


def random_states(generator: torch.Generator) -> dict:
    """Every random source a stage draws from, so a resumed run continues identically."""
    return {
        "generator": generator.get_state(),
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }


def restore_random_states(states: dict, generator: torch.Generator) -> None:
    generator.set_state(states["generator"])
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])


class History:
    """Append-only JSON lines (one record per logged step), flushed as it goes."""

    def __init__(self, path: Path, truncate_after: tuple[str, int] | None = None) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        if truncate_after is not None and path.exists():
            # On resume, drop records logged after the checkpoint so the history has no repeats.
            stage, step = truncate_after
            stage_order = {"geometry": 0, "texture": 1}
            kept = []
            for line in path.read_text().splitlines():
                record = json.loads(line)
                order = (stage_order.get(record["stage"], 9), record["step"])
                if order <= (stage_order.get(stage, 9), step):
                    kept.append(line)
            text = "\n".join(kept) + ("\n" if kept else "")
            with atomic_path(path) as temporary:
                temporary.write_text(text)

    def log(self, record: dict) -> None:
        # A diverged loss is logged as NaN rather than lost.
        append_json_line(self.path, record, allow_nan=True)

    def records(self) -> list[dict]:
        if not self.path.exists():
            return []
        return [json.loads(line) for line in self.path.read_text().splitlines() if line]
