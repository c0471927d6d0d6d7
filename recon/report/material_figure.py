"""The report's figure of a `pbr` fit: base colour, roughness and metalness textures and the
fitted environment map (tone-mapped), side by side."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt

from recon.io.atomic import atomic_path
from recon.io.images import linear_to_srgb
from recon.optimize.material_stage import PbrTextureResult

matplotlib.use("Agg")


def material_figure(result: PbrTextureResult, path: Path) -> None:
    """Four panels: base colour (sRGB), roughness and metalness (0 black .. 1 white, linear),
    environment (radiance / (1 + radiance), sRGB-coded, row 0 looking up)."""
    base = linear_to_srgb(result.mesh.texture.detach().cpu().clamp(0, 1)).numpy()
    maps = result.material.detach().cpu().clamp(0, 1).numpy()
    environment = result.environment.detach().cpu().clamp_min(0)
    environment = linear_to_srgb(environment / (1 + environment)).numpy()
    figure, axes = plt.subplots(1, 4, figsize=(14, 3.4))
    panels = [
        ("base colour", base, None),
        (f"roughness (median {float(result.material[..., 0].median()):.2f})", maps[..., 0], "gray"),
        (f"metalness (median {float(result.material[..., 1].median()):.2f})", maps[..., 1], "gray"),
        ("environment (tone-mapped)", environment, None),
    ]
    for axis, (title, image, colormap) in zip(axes, panels, strict=True):
        axis.imshow(image, cmap=colormap, vmin=0, vmax=1, interpolation="nearest")
        axis.set_title(title, fontsize=9)
        axis.axis("off")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)
