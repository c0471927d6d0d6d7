"""The fit stage: the run's training captures -> recon.optimize.fit.fit_scene -> mesh/ and
light/ (recon.stages.fitted_scene), with history.jsonl and checkpoints/ for --resume.

With dataset.normalize.enabled (default: on for a dataset given with 'data') the fit works in a
recentred, rescaled frame recorded in normalization.json; the fitted mesh is written back in the
dataset's own frame.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.datasets import read_captures
from recon.io.run_folder import RunPaths
from recon.optimize.checkpoint import History
from recon.optimize.fit import HULL_MARGIN, FitCheckpoints, fit_scene
from recon.optimize.normalize import SceneTransform, estimate_scene_transform
from recon.stages.fitted_scene import write_fitted_scene, write_pbr_fit


def fit_stage(
    config: RunConfig, paths: RunPaths, device: torch.device, resume: bool = False
) -> dict:
    """Stage 'fit': reads paths.dataset's train split, writes the fitted scene, history and
    checkpoints into the run folder."""
    if not paths.dataset_layout.has_split("train"):
        raise ReconError(
            f"fit: no training split in {paths.dataset} (run the synth stage first, or point "
            "the run at a dataset)"
        )
    captures = read_captures(paths.dataset, "train", config.dataset)
    transform = None
    hull_radius = None
    normalize = config.dataset.normalize.enabled
    if normalize is None:
        normalize = config.data is not None
    if normalize:
        if resume and paths.normalization.exists():
            transform = SceneTransform.read(paths.normalization)
        else:
            transform = estimate_scene_transform(
                captures.cameras, captures.masks, config.dataset.normalize
            )
            transform.write(paths.normalization)
        captures = replace(captures, cameras=transform.cameras(captures.cameras))
        # The object fills radius; the hull's grid keeps a margin so that it never touches it.
        hull_radius = HULL_MARGIN * config.dataset.normalize.radius
    checkpoints = FitCheckpoints(paths.geometry_checkpoint, paths.texture_checkpoint)
    history = History(paths.history, truncate_after=checkpoints.resume_point() if resume else None)
    result = fit_scene(
        captures, config.fit, device, config.seed, checkpoints, history, resume, hull_radius
    )
    if config.fit.material == "pbr":
        return write_pbr_fit(paths, result, transform)
    return write_fitted_scene(paths, result, transform)
