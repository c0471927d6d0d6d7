"""The report's figures of a `pbr` fit: base colour, roughness and metalness textures, the
tangent-space normal map when the fit has one, and the fitted environment map (tone-mapped),
side by side; and, on a synthetic world whose reference carries its true maps, the fitted
roughness against the true one seen from a held-out view, with their difference."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch

from recon.camera import Cameras
from recon.io.atomic import atomic_path
from recon.io.images import linear_to_srgb
from recon.mesh.mesh import Mesh
from recon.optimize.material_stage import PbrTextureResult
from recon.render.environment import add_suns
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

matplotlib.use("Agg")


def material_panels(result: PbrTextureResult) -> list[tuple[str, np.ndarray, str | None]]:
    """(title, image, colour map) of each channel, as shown: base colour [h, w, 3] (sRGB),
    roughness and metalness [h, w] (linear, 0 black .. 1 white, grey colour map), the normal
    map [h, w, 3] coded (n + 1) / 2 as normal-map files are (flat = (0.5, 0.5, 1)) when the
    material has one, and the environment [he, we, 3] (with the fit's suns added, recon.render.environment.add_suns)
    as radiance / (1 + radiance), sRGB-coded, row 0 looking up."""
    base = linear_to_srgb(result.mesh.texture.detach().cpu().clamp(0, 1)).numpy()
    material = result.material.detach().cpu()
    maps = material.clamp(0, 1).numpy()
    environment = result.environment.detach().cpu()
    if result.suns:
        environment = add_suns(environment, result.suns)
    environment = environment.clamp_min(0)
    environment = linear_to_srgb(environment / (1 + environment)).numpy()
    panels = [
        ("base colour", base, None),
        (f"roughness (median {float(material[..., 0].median()):.2f})", maps[..., 0], "gray"),
        (f"metalness (median {float(material[..., 1].median()):.2f})", maps[..., 1], "gray"),
    ]
    if material.shape[-1] == 5:
        coded = ((material[..., 2:5].clamp(-1, 1) + 1) / 2).numpy()
        panels.append(("normal map (tangent space)", coded, None))
    suns = f", {len(result.suns)} sun(s) added" if result.suns else ""
    panels.append((f"environment (tone-mapped{suns})", environment, None))
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


# The roughness comparison's error panel maps |fitted - true| from 0 to this through magma.
ROUGHNESS_ERROR_MAXIMUM = 0.25


def material_value_image(
    mesh: Mesh, maps: torch.Tensor, cameras: Cameras, channel: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """One channel of material maps [h, w, C] on mesh's UVs as seen from cameras (unshaded,
    bilinear): values [B, H, W] and hard coverage [B, H, W] bool."""
    values = maps.detach().cpu().float()[..., channel : channel + 1].expand(-1, -1, 3)
    carrier = Mesh(mesh.verts, mesh.faces, uvs=mesh.uvs, uv_faces=mesh.uv_faces, texture=values)
    renderer = Renderer(texture_filter="linear", texture_boundary="clamp")
    with torch.no_grad():
        output = renderer.render(carrier.to(cameras.device), cameras, Lighting.constant())
    return output.albedo[..., 0].cpu(), output.mask[..., 0].cpu() > 0.5


def roughness_comparison_panels(
    fitted: Mesh,
    fitted_maps: torch.Tensor,
    reference: Mesh,
    true_maps: torch.Tensor,
    camera: Cameras,
) -> list[tuple[str, np.ndarray, str, float]]:
    """(title, image [H, W], colour map, maximum) of the roughness comparison from one camera:
    the fitted roughness on the fitted mesh, the true roughness on the reference mesh (viridis,
    0 .. 1), and |fitted - true| where both meshes cover the pixel (magma, 0 ..
    ROUGHNESS_ERROR_MAXIMUM). Pixels without surface are NaN (drawn white)."""
    found, found_mask = material_value_image(fitted, fitted_maps, camera)
    true, true_mask = material_value_image(reference, true_maps, camera)
    found, found_mask, true, true_mask = found[0], found_mask[0], true[0], true_mask[0]
    both = found_mask & true_mask
    error = torch.where(both, (found - true).abs(), torch.nan)
    mean = float(error[both].mean()) if bool(both.any()) else float("nan")
    return [
        ("fitted roughness", torch.where(found_mask, found, torch.nan).numpy(), "viridis", 1.0),
        ("true roughness", torch.where(true_mask, true, torch.nan).numpy(), "viridis", 1.0),
        (f"|fitted - true| (mean {mean:.3f})", error.numpy(), "magma", ROUGHNESS_ERROR_MAXIMUM),
    ]


def roughness_comparison_figure(
    fitted: Mesh,
    fitted_maps: torch.Tensor,
    reference: Mesh,
    true_maps: torch.Tensor,
    camera: Cameras,
    path: Path,
) -> None:
    """roughness_comparison_panels side by side, each with its colour bar, in one PNG at path
    (written atomically). camera: one view (a held-out one in the report)."""
    panels = roughness_comparison_panels(fitted, fitted_maps, reference, true_maps, camera)
    figure, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6))
    for axis, (title, image, colormap, maximum) in zip(axes, panels, strict=True):
        shown = axis.imshow(image, cmap=colormap, vmin=0, vmax=maximum, interpolation="nearest")
        axis.set_title(title, fontsize=9)
        axis.axis("off")
        figure.colorbar(shown, ax=axis, fraction=0.046, pad=0.04)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)
