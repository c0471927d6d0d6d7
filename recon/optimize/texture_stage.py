"""Stage 2 of the fit: simplify, unwrap, bake, then optimise the UV texture, the lighting and the
vertex positions on the now fixed topology."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from recon.config.run_config import FitConfig
from recon.effects.forward import render_with_effects
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.mesh.uv import bake_vertex_attribute, dilate, unwrap
from recon.optimize.checkpoint import (
    History,
    load_checkpoint,
    random_states,
    restore_random_states,
    save_checkpoint,
)
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.large_steps import LaplacianPreconditioner, UniformAdam
from recon.optimize.scene_model import (
    FitEffects,
    LightModel,
    TrainingPyramid,
    image_loss,
    sample_views,
    step_record,
    texture_total_variation,
)
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer
from recon.render.texture import build_mip_pyramid

LOG_EVERY = 10


@dataclass
class TextureResult:
    """The final textured mesh, the light and the effect modules (empty when none)."""

    mesh: Mesh
    light: LightModel
    effects: FitEffects | None = None


def simplify_and_unwrap(geometry: GeometryResult, config: FitConfig) -> tuple[Mesh, torch.Tensor]:
    """Simplify to the target face count (repaired), carry albedo by nearest old vertex, unwrap
    with xatlas and bake + dilate the albedo into the texture. Returns the mesh and the chart
    coverage [h, w] bool."""
    from recon.mesh.simplify import repair, simplify

    device = geometry.verts.device
    verts = geometry.verts.detach().cpu()
    faces = geometry.faces.cpu()
    albedo = geometry.albedo.detach().cpu()
    if faces.shape[0] > config.simplify.target_faces:
        new_verts, new_faces = simplify(verts, faces, target_faces=config.simplify.target_faces)
        new_verts, new_faces, _ = repair(new_verts, new_faces)
        new_verts = torch.as_tensor(new_verts, dtype=torch.float32)
        new_faces = torch.as_tensor(new_faces, dtype=torch.int64)
        # Simplification moves vertices a little: the nearest old vertex's albedo is close.
        _, nearest = cKDTree(verts.numpy()).query(new_verts.numpy())
        albedo = albedo[torch.as_tensor(nearest)]
        verts, faces = new_verts, new_faces
    size = config.texture.texture_size
    uvs, uv_faces = unwrap(verts, faces, resolution=size)
    texture, coverage = bake_vertex_attribute((faces, uvs, uv_faces), albedo, (size, size))
    texture = dilate(texture, coverage)
    mesh = Mesh(
        verts.to(device),
        faces.to(device),
        uvs=uvs.float().to(device),
        uv_faces=uv_faces.to(device),
        texture=texture.float().to(device),
    )
    return mesh, coverage.to(device)


@dataclass
class TextureStart:
    """What a texture-stage loop (Lambertian or pbr) starts from: the mesh and texel coverage
    (from the checkpoint when resuming, else the given textured mesh, else simplified and
    unwrapped), the training views at one resolution, and the vertex latent.

    cameras [B], images [B, H, W, 3], masks [B, H, W, 1]; latent [V, 3]."""

    mesh: Mesh
    coverage: torch.Tensor
    start_step: int
    checkpoint: dict | None
    cameras: object
    images: torch.Tensor
    masks: torch.Tensor
    renderer: Renderer
    topology: object
    preconditioner: LaplacianPreconditioner
    latent: torch.nn.Parameter


def start_texture_stage(
    captures: CaptureSet,
    geometry: GeometryResult,
    config: FitConfig,
    device: torch.device,
    checkpoint_path: Path,
    resume: bool,
    resolution: int | None,
    initial: Mesh | None = None,
) -> TextureStart:
    """The start shared by run_texture_stage and the pbr material stage."""
    checkpoint = load_checkpoint(checkpoint_path) if resume else None
    if checkpoint is not None:
        mesh = Mesh(
            checkpoint["verts"].to(device),
            checkpoint["faces"].to(device),
            uvs=checkpoint["uvs"].to(device),
            uv_faces=checkpoint["uv_faces"].to(device),
            texture=checkpoint["texture"].to(device),
        )
        coverage = checkpoint["coverage"].to(device)
        start_step = checkpoint["step"]
    elif initial is not None:
        mesh = initial
        coverage = torch.ones(mesh.texture.shape[:2], dtype=torch.bool, device=device)
        start_step = 0
    else:
        mesh, coverage = simplify_and_unwrap(geometry, config)
        start_step = 0
    resolution = resolution or max(captures.cameras.image_size)
    pyramid = TrainingPyramid.build(captures, [resolution], device)
    cameras, images, masks = pyramid.levels[-1]
    preconditioner = LaplacianPreconditioner(
        mesh.faces, mesh.verts.shape[0], config.texture.large_steps_lambda
    )
    latent = torch.nn.Parameter(preconditioner.to_latent(mesh.verts))
    if checkpoint is not None:
        latent.data.copy_(checkpoint["latent"].to(device))
    return TextureStart(
        mesh,
        coverage,
        start_step,
        checkpoint,
        cameras,
        images,
        masks,
        Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp"),
        build_topology(mesh.faces, mesh.verts.shape[0]),
        preconditioner,
        latent,
    )


def run_texture_stage(
    captures: CaptureSet,
    geometry: GeometryResult,
    config: FitConfig,
    device: torch.device,
    seed: int,
    checkpoint_path: Path,
    history: History,
    resume: bool = False,
    initial: Mesh | None = None,
    effects: FitEffects | None = None,
    resolution: int | None = None,
) -> TextureResult:
    """initial: an already textured mesh to start from (skips simplify + unwrap; a warm-started
    refit). effects: effect modules to keep optimising (default: the geometry stage's, else
    those config.effects names). resolution: the longer image side to fit at (default: the
    captures' own)."""
    settings = config.texture
    generator = torch.Generator().manual_seed(seed + 1)
    start = start_texture_stage(
        captures, geometry, config, device, checkpoint_path, resume, resolution, initial
    )
    mesh, coverage, start_step, checkpoint = (
        start.mesh,
        start.coverage,
        start.start_step,
        start.checkpoint,
    )
    cameras, images, masks = start.cameras, start.images, start.masks
    renderer, topology = start.renderer, start.topology
    preconditioner, latent = start.preconditioner, start.latent
    if effects is None:
        effects = geometry.effects or FitEffects(config.effects, len(captures.cameras), device)
    light = geometry.light
    texture = torch.nn.Parameter(mesh.texture.clone())
    position_optimizer = UniformAdam([latent], lr=settings.learning_rate)
    texture_optimizer = torch.optim.Adam([texture], lr=settings.texture_learning_rate)
    light_optimizer = torch.optim.Adam(light.parameters(), lr=settings.light_learning_rate)
    if checkpoint is not None:
        effects.load_state_dict(checkpoint["effects"])
        light.load_state_dict(checkpoint["light"])
        position_optimizer.load_state_dict(checkpoint["position_optimizer"])
        texture_optimizer.load_state_dict(checkpoint["texture_optimizer"])
        light_optimizer.load_state_dict(checkpoint["light_optimizer"])
        restore_random_states(checkpoint["random"], generator)

    def save(step: int, stage: str = "texture") -> None:
        save_checkpoint(
            checkpoint_path,
            {
                "stage": stage,
                "step": step,
                "verts": preconditioner.from_latent(latent).detach().cpu(),
                "latent": latent.detach().cpu(),
                "faces": mesh.faces.cpu(),
                "uvs": mesh.uvs.cpu(),
                "uv_faces": mesh.uv_faces.cpu(),
                "texture": texture.detach().cpu(),
                "coverage": coverage.cpu(),
                "light": light.state_dict(),
                "position_optimizer": position_optimizer.state_dict(),
                "texture_optimizer": texture_optimizer.state_dict(),
                "light_optimizer": light_optimizer.state_dict(),
                "effects": effects.state_dict(),
                "random": random_states(generator),
            },
        )

    started = time.perf_counter()
    bar = tqdm(
        range(start_step, settings.steps),
        desc="fit texture",
        initial=start_step,
        total=settings.steps,
        unit="step",
    )
    for step in bar:
        views = sample_views(len(cameras), settings.views_per_step, generator).to(device)
        verts = preconditioner.from_latent(latent)
        current = Mesh(verts, mesh.faces, uvs=mesh.uvs, uv_faces=mesh.uv_faces, texture=texture)
        output = render_with_effects(
            renderer,
            current,
            cameras[views],
            light.lighting(),
            effects.modules,
            view_indices=views,
            topology=topology,
            mip_pyramid=build_mip_pyramid(texture),
        )
        color_loss = image_loss(output.color, images[views], settings.image_loss)
        mask_loss = (output.alpha - masks[views]).abs().mean()
        # Total variation inside the charts keeps texels that few views see from speckling.
        smoothness = texture_total_variation(texture)
        loss = (
            color_loss + settings.mask_weight * mask_loss + settings.smoothness_weight * smoothness
        )
        position_optimizer.zero_grad()
        texture_optimizer.zero_grad()
        light_optimizer.zero_grad()
        effects.zero_grad()
        loss.backward()
        position_optimizer.step()
        texture_optimizer.step()
        light_optimizer.step()
        # The geometry stage already ran: effects are past their lock here.
        effects.step(1.0)
        with torch.no_grad():
            texture.clamp_(0, 1)
        if step % LOG_EVERY == 0 or step == settings.steps - 1:
            record = step_record(
                "texture",
                step,
                {"loss": loss, "color_loss": color_loss, "mask_loss": mask_loss},
                output.color,
                images[views],
                cameras.image_size,
                int(mesh.faces.shape[0]),
                time.perf_counter() - started,
            )
            history.log(record)
            bar.set_postfix(loss=f"{record['loss']:.4f}")
        if (step + 1) % config.checkpoint_every == 0:
            save(step + 1)
    bar.close()
    with torch.no_grad():
        # Texels outside the charts only ever received mip-averaged gradients: refill them
        # from the charts so coarse levels stay clean.
        final_texture = dilate(texture.detach(), coverage)
    final = Mesh(
        preconditioner.from_latent(latent).detach(),
        mesh.faces,
        uvs=mesh.uvs,
        uv_faces=mesh.uv_faces,
        texture=final_texture,
    )
    save(settings.steps, stage="texture_done")
    return TextureResult(final, light, effects)
