"""How well can the model's vignetting polynomial know the corner from the object's pixels?

For every vignetting case of a blind benchmark folder (``recon-bench diagnose --out OUT``):
the world's true falloff (data_synth's Vignetting with the withheld parameters, relative to the
image centre) on the pixels the object covers in the held-out views, the best least-squares fit
of the model's 1 + a r^2 + b r^4 to it there, and that fit's corner value against the true
corner falloff. The error is what no diagnosis can beat: the corners lie outside the object.
The same fit over every pixel of the frame (as if a backdrop or a frame-filling object covered
the corners) shows what is left of it once the corners are seen. Prints JSON.

    recon-bench vignetting-extrapolation OUT/default OUT/spot
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from recon.io.run_folder import RunPaths


def corner_of_fit(radius, falloff, pixels) -> float:
    """1 + a + b of the least-squares 1 + a r^2 + b r^4 to falloff on the chosen pixels
    (radius, falloff, pixels: [B, H, W] tensors, pixels boolean)."""
    import torch

    squared = radius[pixels] ** 2
    design = torch.stack([squared, squared * squared], dim=1)
    a, b = torch.linalg.lstsq(design, (falloff[pixels] - 1)[:, None]).solution[:, 0]
    return float(1 + a + b)


def main(argv: list[str] | None = None) -> int:
    import torch

    from data_synth.effects.optics import Vignetting, pixel_grid
    from recon.effects.photometric import normalised_radius
    from recon.io.datasets import read_captures

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("folders", nargs="+", help="benchmark scene folders (with truth/)")
    arguments = parser.parse_args(argv)
    results = []
    for folder in map(Path, arguments.folders):
        for truth_path in sorted((folder / "truth").glob("*vignetting*.json")):
            truth = json.loads(truth_path.read_text())
            parameters = next(
                item["parameters"] for item in truth["withheld"] if item["name"] == "vignetting"
            )
            captures = read_captures(RunPaths(folder / truth_path.stem).dataset, "test")
            height, width = captures.cameras.image_size
            like = torch.empty(0, dtype=torch.float64)
            effect = Vignetting(parameters)
            u, v = pixel_grid(height, width, like)
            falloff = effect.relative_falloff(captures.cameras, u, v, height, width)
            radius = normalised_radius(captures.cameras, height, width, like)
            covered = captures.masks[..., 0] > 0.5
            realised = next(
                item["parameters"]
                for item in truth["realised"]["test"]
                if item["name"] == "vignetting"
            )
            true_corner = sum(realised["corner_falloff"]) / len(realised["corner_falloff"])
            fitted_corner = corner_of_fit(radius, falloff, covered)
            full_frame_corner = corner_of_fit(radius, falloff, torch.ones_like(covered))
            results.append(
                {
                    "case": f"{folder.name}/{truth_path.stem}",
                    "largest_covered_radius": round(float(radius[covered].max()), 3),
                    "true_corner_falloff": round(true_corner, 4),
                    "best_fit_corner_falloff": round(fitted_corner, 4),
                    "corner_relative_error": round(
                        abs(fitted_corner - true_corner) / true_corner, 3
                    ),
                    "full_frame_fit_corner_falloff": round(full_frame_corner, 4),
                    "full_frame_corner_relative_error": round(
                        abs(full_frame_corner - true_corner) / true_corner, 3
                    ),
                }
            )
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
