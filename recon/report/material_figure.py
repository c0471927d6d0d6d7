"""The report's figure of a `pbr` fit: base colour, roughness and metalness textures, the
tangent-space normal map when the fit has one, and the fitted environment map (tone-mapped),
side by side."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from recon.io.atomic import atomic_path
from recon.io.images import linear_to_srgb
from recon.optimize.material_stage import PbrTextureResult

matplotlib.use("Agg")


def material_panels(result: PbrTextureResult) -> list[tuple[str, np.ndarray, str | None]]:
    """(title, image, colour map) of each channel, as shown: base colour [h, w, 3] (sRGB),
    roughness and metalness [h, w] (linear, 0 black .. 1 white, grey colour map), the normal
    map [h, w, 3] coded (n + 1) / 2 as normal-map files are (flat = (0.5, 0.5, 1)) when the
    material has one, and the environment [he, we, 3] as radiance / (1 + radiance), sRGB-coded,
    row 0 looking up."""
    base = linear_to_srgb(result.mesh.texture.detach().cpu().clamp(0, 1)).numpy()
    material = result.material.detach().cpu()
    maps = material.clamp(0, 1).numpy()
    environment = result.environment.detach().cpu().clamp_min(0)
    environment = linear_to_srgb(environment / (1 + environment)).numpy()
    panels = [
        ("base colour", base, None),
        (f"roughness (median {float(material[..., 0].median()):.2f})", maps[..., 0], "gray"),
        (f"metalness (median {float(material[..., 1].median()):.2f})", maps[..., 1], "gray"),
    ]
    if material.shape[-1] == 5:
        coded = ((material[..., 2:5].clamp(-1, 1) + 1) / 2).numpy()
        panels.append(("normal map (tangent space)", coded, None))
    panels.append(("environment (tone-mapped)", environment, None))
    return panels


def material_figure(result: PbrTextureResult, path: Path) -> None:
    """The material_panels side by side in one PNG at path (written atomically)."""
    panels = material_panels(result)
    figure, axes = plt.subplots(1, len(panels), figsize=(3.5 * len(panels), 3.4))
    for axis, (title, image, colormap) in zip(axes, panels, strict=True):
        axis.imshow(image, cmap=colormap, vmin=0, vmax=1, interpolation="nearest")
        axis.set_title(title, fontsize=9)
        axis.axis("off")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)
