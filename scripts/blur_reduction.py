"""How much of a run's misfit a plain blur of its render removes, on held-out and training views.

    python scripts/blur_reduction.py RUN [RUN ...]

For each fitted RUN (a run folder with a fit; a blind-check case folder works), the fitted model
is rendered on the held-out and on the training views, and an isotropic Gaussian blur of the
render is chosen from a grid of widths on one half of the image's 4-px blocks (a checkerboard)
and scored on the other half: the share of that half's squared error (over the diagnosis
region) the blur removes. One JSON line per run: {"run", "heldout": [sigma, reduction],
"train": [sigma, reduction]}.

A measurement for decision 0220, not part of the diagnosis: where the fit was optimised (the
training views) a clean fit leaves little blur-like misfit, while a blurred capture keeps its
blur in every view.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import kornia
import torch

from recon.diagnose.data import DiagnosisData

SIGMAS_PX = (0.0, 0.3, 0.45, 0.6, 0.75, 0.9, 1.1, 1.3, 1.6, 2.0)
BLOCK_PIXELS = 4


def gaussian_blurred(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """[B, H, W, C] images blurred by an isotropic Gaussian of sigma pixels (zero outside)."""
    if sigma <= 0:
        return images
    size = int(2 * round(3 * sigma) + 1)
    planes = images.permute(0, 3, 1, 2)
    blurred = kornia.filters.gaussian_blur2d(
        planes, (size, size), (sigma, sigma), border_type="constant"
    )
    return blurred.permute(0, 2, 3, 1)


def blur_reduction(data: DiagnosisData) -> tuple[float, float]:
    """(sigma, reduction): the grid's width that best fits the first half of the blocks, and the
    share of the second half's squared error it removes (negative: it adds error)."""
    observed, rendered = data.observed.double(), data.rendered.double()
    region = data.region.double()
    _, height, width, _ = observed.shape
    rows = torch.arange(height) // BLOCK_PIXELS
    columns = torch.arange(width) // BLOCK_PIXELS
    first = ((rows[:, None] + columns[None, :]) % 2 == 0).double()[None, :, :, None]
    errors = [(gaussian_blurred(rendered, sigma) - observed) ** 2 * region for sigma in SIGMAS_PX]
    fitted = [float((error * first).sum()) for error in errors]
    scored = [float((error * (1 - first)).sum()) for error in errors]
    best = min(range(len(SIGMAS_PX)), key=fitted.__getitem__)
    return SIGMAS_PX[best], 1.0 - scored[best] / max(scored[0], 1e-30)


def measure_run(run: Path) -> dict:
    """The run's held-out and training-view blur reductions."""
    from recon.config import load_config
    from recon.config.run_config import RunConfig
    from recon.diagnose.data import render_views_once
    from recon.io.run_folder import RunPaths
    from recon.stages.diagnose import diagnosis_inputs

    config = load_config(RunPaths(run).resolved_config, RunConfig)
    data = Path(str(config.data)) if config.data else None
    paths = RunPaths(run, data if data is not None and data.is_dir() else None)
    inputs = diagnosis_inputs(paths, config, torch.device("cpu"))
    band = config.diagnose.band_pixels
    result = {"run": str(run)}
    for name, captures in (("heldout", inputs.heldout), ("train", inputs.training)):
        views, _ = render_views_once(captures, inputs.model, band)
        sigma, reduction = blur_reduction(views)
        result[name] = [sigma, round(reduction, 4)]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="fitted run folders")
    arguments = parser.parse_args(argv)
    for run in arguments.runs:
        print(json.dumps(measure_run(run)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
