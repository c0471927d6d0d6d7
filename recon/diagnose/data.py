"""What the sim-to-real diagnosis looks at: observed views beside the fitted scene's renders.

"Sim" is the fitted forward model (the fitted mesh, texture and light rendered by recon's
Renderer); "real" is the observed images of one split. DiagnosisData keeps, besides the two
images, the render's auxiliary buffers (normals, depth, texel coordinates, triangle ids) so the
residual can be binned in image, surface, light and edge domains without rendering again.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from recon.camera.cameras import Cameras
from recon.config.run_config import DiagnoseConfig
from recon.effects.base import ModelEffect
from recon.effects.forward import (
    EffectContext,
    apply_camera_effects,
    apply_image_effects,
    apply_shading_effects,
)
from recon.errors import ReconError
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.render.interpolate import interpolate
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import Lighting

# The diagnose section's defaults (config diagnose), for callers that pass no settings.
DEFAULTS = DiagnoseConfig()
# Coverage above this counts as the object (antialiased alpha is fractional at the edge).
COVERAGE_THRESHOLD = 0.5
VIEWS_PER_BATCH = 4


@dataclass
class DiagnosisData:
    """A set of B views of one split: observations, the fitted scene's renders and its buffers.

    observed: [B, H, W, 3] linear colour, premultiplied by coverage (background removed).
    rendered: [B, H, W, 3] linear colour of the fitted scene, premultiplied (over black).
    observed_alpha: [B, H, W, 1] observed coverage in [0, 1].
    rendered_alpha: [B, H, W, 1] antialiased rendered coverage in [0, 1].
    region: [B, H, W, 1] float 0/1: observed or rendered object, dilated by a band of pixels.
    normals: [B, H, W, 3] world shading normals (0 where no triangle covers the pixel centre).
    depth: [B, H, W, 1] camera-space depth z (0 on background).
    texel_uv: [B, H, W, 2] fitted texture coordinates in [0, 1] ((0, 0) = the texture's top-left),
        -1 where no triangle covers the pixel or the mesh has no UVs.
    triangle_id: [B, H, W] int64 rendered triangle per pixel centre, -1 on background.
    cameras, lighting, mesh: the fitted scene (on the device it was rendered on).
    names: B view names; split: the dataset split they come from.
    """

    observed: torch.Tensor
    rendered: torch.Tensor
    observed_alpha: torch.Tensor
    rendered_alpha: torch.Tensor
    region: torch.Tensor
    normals: torch.Tensor
    depth: torch.Tensor
    texel_uv: torch.Tensor
    triangle_id: torch.Tensor
    cameras: Cameras
    lighting: Lighting
    mesh: Mesh
    names: list[str] = field(default_factory=list)
    split: str = ""
    # The fitted model the renders come from (its material and its own effects, which the
    # probes keep on); None: the Lambertian mesh and lighting above, without effects.
    model: FittedModel | None = None

    def __post_init__(self) -> None:
        if self.observed.ndim != 4 or self.observed.shape[-1] != 3:
            raise ReconError(
                f"diagnosis_data.observed: expected shape [B, H, W, 3], got "
                f"{tuple(self.observed.shape)}"
            )
        batch, height, width, _ = self.observed.shape
        expected = {
            "rendered": (batch, height, width, 3),
            "observed_alpha": (batch, height, width, 1),
            "rendered_alpha": (batch, height, width, 1),
            "region": (batch, height, width, 1),
            "normals": (batch, height, width, 3),
            "depth": (batch, height, width, 1),
            "texel_uv": (batch, height, width, 2),
            "triangle_id": (batch, height, width),
        }
        for name, shape in expected.items():
            actual = tuple(getattr(self, name).shape)
            if actual != shape:
                raise ReconError(
                    f"diagnosis_data.{name}: expected shape {list(shape)}, got {list(actual)}"
                )
        if len(self.cameras) != batch or tuple(self.cameras.image_size) != (height, width):
            raise ReconError(
                f"diagnosis_data.cameras: expected {batch} cameras of size ({height}, {width}), "
                f"got {len(self.cameras)} of size {self.cameras.image_size}"
            )
        if not self.names:
            self.names = [str(index) for index in range(batch)]

    @property
    def residual(self) -> torch.Tensor:
        """observed - rendered [B, H, W, 3], linear radiance."""
        return self.observed - self.rendered

    @property
    def view_count(self) -> int:
        return self.observed.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.observed.shape[1], self.observed.shape[2])

    @property
    def rendered_mask(self) -> torch.Tensor:
        """[B, H, W] bool: a fitted triangle covers the pixel centre."""
        return self.triangle_id >= 0


def box_dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary dilation of masks [B, 1, H, W] (float 0/1) by a (2 radius + 1)^2 square, as
    max_pool2d with that window, stride 1 and padding radius gives it, at a fraction of its
    cost on the CPU: the square is separable, and along each axis the dilation is the OR of
    the mask shifted by 1..radius pixels either way (in place on booleans; a 384 px diagnosis
    dilates dozens of such masks, a pooling pass cost several times as much)."""
    if radius <= 0:
        return mask

    def along(values: torch.Tensor, dim: int) -> torch.Tensor:
        grown = values.clone()
        size = values.shape[dim]
        for shift in range(1, min(radius, size - 1) + 1):
            grown.narrow(dim, shift, size - shift).logical_or_(values.narrow(dim, 0, size - shift))
            grown.narrow(dim, 0, size - shift).logical_or_(values.narrow(dim, shift, size - shift))
        return grown

    return along(along(mask > 0, 3), 2).to(mask.dtype)


def box_erode(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary erosion of masks [B, 1, H, W] (float 0/1) by a (2 radius + 1)^2 square; pixels
    beyond the image border do not erode (as -max_pool2d(-mask) gives it)."""
    return 1 - box_dilate(1 - mask, radius)


def region_mask(
    observed_alpha: torch.Tensor,
    rendered_alpha: torch.Tensor,
    band_pixels: int = DEFAULTS.band_pixels,
) -> torch.Tensor:
    """The pixels the gap is measured on: [B, H, W, 1] float 0/1.

    The union of the observed and the rendered object (alpha [B, H, W, 1] above one half), so a
    silhouette that is too small or too large is counted on both sides, dilated by band_pixels
    (a square structuring element) so that edge residuals outside both silhouettes count too.
    """
    covered = (observed_alpha > COVERAGE_THRESHOLD) | (rendered_alpha > COVERAGE_THRESHOLD)
    covered = covered.float().permute(0, 3, 1, 2)  # [B, 1, H, W]
    covered = box_dilate(covered, band_pixels)
    return covered.permute(0, 2, 3, 1).contiguous()


def texel_coordinates(output: RenderOutput, mesh: Mesh) -> torch.Tensor:
    """Fitted UVs at each pixel [B, H, W, 2], -1 where no triangle covers it or no UVs exist."""
    fragments = output.fragments
    batch = fragments.batch_size
    height, width = fragments.resolution
    if mesh.uvs is None or mesh.uv_faces is None:
        return torch.full((batch, height, width, 2), -1.0, device=output.color.device)
    uv = interpolate(mesh.uvs, fragments, mesh.uv_faces)
    covered = (fragments.tri_id >= 0).unsqueeze(-1)
    return torch.where(covered, uv, torch.full_like(uv, -1.0))


def build_diagnosis_data(
    observed: torch.Tensor,
    observed_alpha: torch.Tensor,
    output: RenderOutput,
    cameras: Cameras,
    lighting: Lighting,
    mesh: Mesh,
    band_pixels: int = DEFAULTS.band_pixels,
    names: list[str] | None = None,
    split: str = "",
    model: FittedModel | None = None,
) -> DiagnosisData:
    """Bundle observations [B, H, W, 3] / [B, H, W, 1] with a render of the fitted scene.

    output: the Renderer's output for the same cameras, rendered over a black background so
    its colour is premultiplied like the observations. Everything is detached and moved to the
    CPU: the diagnosis is analysis, not optimisation.
    """
    cpu = torch.device("cpu")
    rendered_alpha = output.alpha.detach().to(cpu)
    observed_alpha = observed_alpha.detach().to(cpu)
    return DiagnosisData(
        observed=observed.detach().to(cpu).float(),
        rendered=output.color.detach().to(cpu).float(),
        observed_alpha=observed_alpha,
        rendered_alpha=rendered_alpha,
        region=region_mask(observed_alpha, rendered_alpha, band_pixels),
        normals=output.normals.detach().to(cpu),
        depth=output.depth.detach().to(cpu),
        texel_uv=texel_coordinates(output, mesh).detach().to(cpu),
        triangle_id=output.fragments.tri_id.detach().to(cpu),
        cameras=cameras.to(cpu),
        lighting=lighting.to(cpu),
        mesh=mesh.to(cpu),
        names=list(names) if names is not None else [],
        split=split,
        model=model,
    )


@dataclass
class FittedModel:
    """The model the diagnosis starts from: what the fit fitted, rendered as the fit renders it.

    mesh, lighting: the fitted mesh (texture, UVs) and light (its frame: lighting.frame).
    effects: the fit's own effect modules (config fit.effects) with the parameters the fit
        left them at (per-view ones belong to the training views); they are part of the model,
        never candidates.
    pbr: the fitted pbr material (recon.optimize.material_stage.PbrTextureResult) of a
        fit.material: pbr run, rendered with its environment instead of the Lambertian light;
        None for the Lambertian material.
    """

    mesh: Mesh
    lighting: Lighting
    effects: list[ModelEffect] = field(default_factory=list)
    pbr: Any = None

    @property
    def material(self) -> str:
        return "lambert" if self.pbr is None else "pbr"

    @property
    def effect_names(self) -> list[str]:
        return [module.name for module in self.effects]

    def describe(self) -> dict:
        """diagnosis.json's model record."""
        return {
            "material": self.material,
            "light_frame": getattr(self.lighting, "frame", "world"),
            "effects": self.effect_names,
        }

    def render(
        self, renderer: Renderer, cameras: Cameras, lighting: Lighting | None = None
    ) -> RenderOutput:
        """The fitted scene without effects (pbr: its material under its environment; a
        given lighting replaces the fitted light of the Lambertian model only)."""
        if self.pbr is not None and lighting is None:
            return self.pbr.render(renderer, cameras)
        return renderer.render(self.mesh, cameras, self.lighting if lighting is None else lighting)

    def render_with(
        self,
        renderer: Renderer,
        cameras: Cameras,
        effects: Sequence[ModelEffect],
        lighting: Lighting | None = None,
    ) -> RenderOutput:
        """The fitted scene with effect modules around it (held-out views: view_indices None,
        per-view effects at their typical view)."""
        if not effects:
            return self.render(renderer, cameras, lighting)
        moved = apply_camera_effects(effects, cameras, None)
        output = self.render(renderer, moved, lighting)
        light = self.lighting if lighting is None else lighting
        context = EffectContext(self.mesh, light, moved, None, renderer)
        output = apply_shading_effects(effects, output, context)
        color, alpha = apply_image_effects(effects, output.color, output.alpha, moved, None)
        return replace(output, color=color, alpha=alpha)

    def to(self, device: torch.device | str) -> FittedModel:
        """The model on a device (the fit's effect modules copied there)."""
        return replace(
            self,
            mesh=self.mesh.to(device),
            lighting=self.lighting.to(device),
            effects=[copy.deepcopy(module).to(device) for module in self.effects],
        )


def render_diagnosis_data(
    captures: CaptureSet,
    model: FittedModel,
    device: torch.device | str = "cpu",
    band_pixels: int = DEFAULTS.band_pixels,
    effects: Sequence[ModelEffect] | None = None,
    lighting: Lighting | None = None,
) -> DiagnosisData:
    """The fitted model against one split's captures.

    Renders like the evaluate stage (trilinear texture, clamped at the border, black
    background) but keeps the render's buffers. effects: effect modules switched on around the
    render (held-out views: no per-view parameters); their colour and alpha are the render's,
    the other buffers come from the underlying rasterisation. lighting: render under this light
    instead of the fitted one (a relight split's own light). band_pixels: the silhouette band
    (config diagnose.band_pixels). The returned tensors live on the CPU whatever device
    rendered them.
    """
    device = torch.device(device)
    if len(captures.cameras) == 0:
        raise ReconError(f"diagnose: split '{captures.split}' has no views")
    model = model.to(device)
    lighting = None if lighting is None else lighting.to(device)
    parts = [
        _render_views(
            captures,
            slice(start, start + VIEWS_PER_BATCH),
            model,
            device,
            band_pixels,
            effects,
            lighting,
        )[0]
        for start in range(0, len(captures.cameras), VIEWS_PER_BATCH)
    ]
    return concatenate(parts)


def render_views_once(
    captures: CaptureSet, model: FittedModel, band_pixels: int = DEFAULTS.band_pixels
) -> tuple[DiagnosisData, RenderOutput]:
    """The fitted model (without effects) against every view of captures in one batch on the
    CPU, and the RenderOutput it was made from: the EffectProbe's cached scene render
    (recon.diagnose.which), so the held-out views are rendered once. A view's render does not
    depend on the views batched with it: the same data as render_diagnosis_data."""
    if len(captures.cameras) == 0:
        raise ReconError(f"diagnose: split '{captures.split}' has no views")
    cpu = torch.device("cpu")
    views = slice(0, len(captures.cameras))
    return _render_views(captures, views, model.to(cpu), cpu, band_pixels, None, None)


def _render_views(
    captures: CaptureSet,
    views: slice,
    model: FittedModel,
    device: torch.device,
    band_pixels: int,
    effects: Sequence[ModelEffect] | None,
    lighting: Lighting | None,
) -> tuple[DiagnosisData, RenderOutput]:
    """One batch of render_diagnosis_data (model and lighting on device already), with the
    render."""
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    with torch.no_grad():
        cameras = captures.cameras[views].to(device)
        output = model.render_with(renderer, cameras, list(effects or []), lighting)
        data = build_diagnosis_data(
            captures.images[views],
            captures.masks[views],
            output,
            cameras,
            model.lighting if lighting is None else lighting,
            model.mesh,
            band_pixels,
            captures.names[views],
            captures.split,
            model.to("cpu"),
        )
    return data, output


def concatenate(parts: list[DiagnosisData]) -> DiagnosisData:
    """One DiagnosisData from batches of views of the same scene (in order)."""
    if not parts:
        raise ReconError("diagnosis_data: nothing to concatenate")
    first = parts[0]
    if len(parts) == 1:
        return first

    def joined(name: str) -> torch.Tensor:
        return torch.cat([getattr(part, name) for part in parts])

    cameras = Cameras(
        world_to_cam=torch.cat([part.cameras.world_to_cam for part in parts]),
        intrinsics=torch.cat([part.cameras.intrinsics for part in parts]),
        image_size=first.cameras.image_size,
        near=first.cameras.near,
        far=first.cameras.far,
    )
    return DiagnosisData(
        observed=joined("observed"),
        rendered=joined("rendered"),
        observed_alpha=joined("observed_alpha"),
        rendered_alpha=joined("rendered_alpha"),
        region=joined("region"),
        normals=joined("normals"),
        depth=joined("depth"),
        texel_uv=joined("texel_uv"),
        triangle_id=joined("triangle_id"),
        cameras=cameras,
        lighting=first.lighting,
        mesh=first.mesh,
        names=[name for part in parts for name in part.names],
        split=first.split,
        model=first.model,
    )
