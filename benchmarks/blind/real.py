"""The real-photo world of the blind check: a real capture with known camera effects injected.

The photos (an LLFF/NeRD folder: poses_bounds.npy, images/, masks/) are read with recon's own
reader at a reduced size (linear colour, straight, the whole frame), a subset of the views is
kept, and data_synth's world effects (the same implementations the synthetic worlds use) are
applied to the linear frames; the result is written as a new LLFF folder (8-bit sRGB PNG, the
masks after the same optics) outside the repository and outside the capture's folder. The truth
(what was injected, per split in recon's LLFF split order) goes to a file beside it, never into
the derived folder. The untouched photos are written the same way (same size and views): the
clean case, whose exposure is fixed by the capture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.datasets import read_llff
from recon.io.images import write_png


def select_views(count: int, every: int) -> list[int]:
    """Indices of the kept views: every `every`-th of count."""
    return list(range(0, count, max(1, every)))


def derive_real_dataset(
    source: Path,
    destination: Path,
    truth_path: Path,
    effects: list[str],
    seed: int,
    max_resolution: int,
    view_every: int,
    holdout_every: int,
) -> dict:
    """Write destination (an LLFF folder) from source with effects injected; returns the truth
    record (also written to truth_path, which must lie outside destination).

    effects: world effect names (data_synth.effects); empty for the untouched photos.
    seed: draws the effects' strengths (data_synth.withhold.sample_effects) and their per-view
        randomness.
    view_every: keep every view_every-th photo. holdout_every: the fit's dataset.holdout_every,
        so that the truth's split order matches recon's (index % holdout_every == 0 is test).
    """
    from data_synth.effects.base import Capture
    from data_synth.effects.registry import apply_effects, make_world_effect
    from data_synth.withhold import sample_effects

    source, destination = Path(source), Path(destination)
    if truth_path.resolve().is_relative_to(destination.resolve()):
        raise ReconError(f"{truth_path}: the truth must lie outside the dataset {destination}")
    if destination.resolve().is_relative_to(source.resolve()):
        raise ReconError(f"{destination}: the derived dataset must not go inside {source}")
    captures = read_llff(source, max_resolution=max_resolution)
    kept = select_views(len(captures.cameras), view_every)
    cameras = captures.cameras[kept]
    images = captures.images[kept].clone()
    masks = captures.masks[kept].clone()
    configured = sample_effects(
        list(effects), torch.Generator().manual_seed(seed + 7919), cameras[:1]
    )
    # The whole frame is the sensor's image (background included): the optics act on all of it,
    # and the mask follows the same geometry as the alpha of a rendered view would.
    capture = Capture(images, masks, cameras)
    applied = apply_effects(
        capture,
        [make_world_effect(effect.name, dict(effect.parameters)) for effect in configured],
        torch.Generator().manual_seed(seed + 104729),
    )
    table = np.load(source / "poses_bounds.npy", allow_pickle=False)[kept]
    (destination / "images").mkdir(parents=True, exist_ok=True)
    (destination / "masks").mkdir(parents=True, exist_ok=True)
    names = [captures.names[index] for index in kept]
    for index, name in enumerate(names):
        write_png(destination / "images" / f"{name}.png", capture.images[index])
        write_png(destination / "masks" / f"{name}.png", capture.alpha[index], encode_srgb=False)
    with open(destination / "poses_bounds.npy", "wb") as handle:
        np.save(handle, table)
    truth = {
        "withheld": [
            {"name": effect.name, "parameters": dict(effect.parameters)} for effect in configured
        ],
        "realised": split_realised(applied, len(kept), holdout_every),
        "source": str(source),
        "views": names,
        "max_resolution": max_resolution,
    }
    atomic_write_json(truth_path, truth)
    return truth


def split_realised(applied, views: int, holdout_every: int) -> dict[str, list[dict]]:
    """Realised effect parameters per split in recon's LLFF order: per-view lists (exposure
    ratios, white-balance gains, ...) of length `views` are split into train and test."""
    test = [index for index in range(views) if index % holdout_every == 0]
    train = [index for index in range(views) if index % holdout_every != 0]
    result: dict[str, list[dict]] = {"train": [], "test": []}
    for item in applied:
        for split, chosen in (("train", train), ("test", test)):
            parameters = {}
            for key, value in item.parameters.items():
                if isinstance(value, list) and len(value) == views:
                    parameters[key] = [value[index] for index in chosen]
                else:
                    parameters[key] = value
            result[split].append({"name": item.name, "parameters": parameters})
    return result
