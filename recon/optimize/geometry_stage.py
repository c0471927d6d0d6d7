"""Stage 1 of the fit: vertex positions, per-vertex albedo and lighting, with remeshing.

Positions move through the Large Steps latent (smooth updates), the image is compared in linear
radiance (or log-sRGB) plus the antialiased coverage against the masks, the resolution grows
coarse to fine, and every remesh_every steps the surface is remeshed isotropically toward a
target edge length that shrinks over the run; albedo and optimizer moments ride along.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch
import trimesh
from tqdm import tqdm

from recon.config.run_config import FitConfig
from recon.errors import warn_user
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.optimize.checkpoint import (
    History,
    load_checkpoint,
    random_states,
    restore_random_states,
    save_checkpoint,
)
from recon.optimize.large_steps import LaplacianPreconditioner, UniformAdam
from recon.optimize.scene_model import (
    FitEffects,
    LightModel,
    TrainingPyramid,
    image_loss,
    sample_views,
    step_record,
)
from recon.optimize.visual_hull import visual_hull
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer

LOG_EVERY = 10
# A remeshed face count above this multiple of the simplification target is warned about.
FACE_WARNING_FACTOR = 10


@dataclass
class GeometryResult:
    """verts [V, 3], faces [F, 3], albedo [V, 3] (linear), the fitted light and effects."""

    verts: torch.Tensor
    faces: torch.Tensor
    albedo: torch.Tensor
    light: LightModel
    effects: FitEffects | None = None


def initial_mesh(
    captures: CaptureSet, config: FitConfig, device: torch.device, radius: float | None = None
) -> Mesh:
    """The visual hull of the masks, or an icosphere filling the hull's bounds. radius: the
    carving grid's half-size (default: visual_hull's, from the camera distances)."""
    hull = visual_hull(
        captures.cameras.to(device), captures.masks.to(device), config.hull_resolution, radius
    )
    if config.init == "visual_hull":
        return hull
    center = (hull.verts.amax(0) + hull.verts.amin(0)) / 2
    radius = float((hull.verts - center).norm(dim=-1).max())
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return Mesh(
        torch.tensor(sphere.vertices, dtype=torch.float32, device=device) + center,
        torch.tensor(sphere.faces, device=device),
    )


def _diagonal(verts: torch.Tensor) -> float:
    return float((verts.amax(0) - verts.amin(0)).norm())


def target_edge_length(config: FitConfig, progress: float, diagonal: float) -> float:
    """Geometric interpolation from edge_length_start to edge_length_end over the remeshing."""
    geometry = config.geometry
    share = min(1.0, progress / max(geometry.remesh_until, 1e-9))
    ratio = geometry.edge_length_end / geometry.edge_length_start
    return geometry.edge_length_start * ratio**share * diagonal


class _PositionOptimizer:
    """Latent positions with their preconditioner and UniformAdam, rebuilt after a remesh."""

    def __init__(self, verts: torch.Tensor, faces: torch.Tensor, config: FitConfig) -> None:
        self.faces = faces
        self.preconditioner = LaplacianPreconditioner(
            faces, verts.shape[0], config.geometry.large_steps_lambda
        )
        self.latent = torch.nn.Parameter(self.preconditioner.to_latent(verts))
        self.optimizer = UniformAdam([self.latent], lr=config.geometry.learning_rate)
        self.topology = build_topology(faces, verts.shape[0])

    def verts(self) -> torch.Tensor:
        return self.preconditioner.from_latent(self.latent)


def _remesh(
    verts: torch.Tensor,
    faces: torch.Tensor,
    target_length: float,
    attributes: dict[str, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    from recon.mesh.remesh import remesh

    result = remesh(verts, faces, target_length, attributes=attributes)
    return (
        torch.as_tensor(result.verts, dtype=torch.float32, device=verts.device),
        torch.as_tensor(result.faces, dtype=torch.int64, device=verts.device),
        {k: torch.as_tensor(v, device=verts.device) for k, v in result.attributes.items()},
    )


def run_geometry_stage(
    captures: CaptureSet,
    config: FitConfig,
    device: torch.device,
    seed: int,
    checkpoint_path: Path,
    history: History,
    resume: bool = False,
    hull_radius: float | None = None,
) -> GeometryResult:
    """hull_radius: half-size of the visual hull's carving grid (None: visual_hull's default)."""
    geometry = config.geometry
    generator = torch.Generator().manual_seed(seed)
    pyramid = TrainingPyramid.build(captures, geometry.resolutions, device)
    renderer = Renderer()
    checkpoint = load_checkpoint(checkpoint_path) if resume else None
    if checkpoint is not None and checkpoint.get("stage") == "geometry_done":
        return _result_from_checkpoint(checkpoint, device, config.light.frame)

    if checkpoint is not None:
        verts = checkpoint["verts"].to(device)
        faces = checkpoint["faces"].to(device)
        albedo_values = checkpoint["albedo"].to(device)
        diagonal = checkpoint["diagonal"]
        start_step = checkpoint["step"]
    else:
        mesh = initial_mesh(captures, config, device, hull_radius)
        diagonal = _diagonal(mesh.verts)
        verts, faces = mesh.verts, mesh.faces
        if geometry.remesh_every > 0:
            verts, faces, _ = _remesh(
                verts, faces, target_edge_length(config, 0.0, diagonal), attributes={}
            )
        albedo_values = torch.full((verts.shape[0], 3), 0.5, device=device)
        start_step = 0

    masks_all = pyramid.levels[-1][2]
    images_all = pyramid.levels[-1][1]
    mean_radiance = float(images_all.sum() / (masks_all.sum() * 3).clamp_min(1))
    light = LightModel(
        ambient=mean_radiance / 0.5 * 0.7,
        with_sun=geometry.directional_light,
        frame=config.light.frame,
    ).to(device)
    albedo = torch.nn.Parameter(albedo_values)
    positions = _PositionOptimizer(verts, faces, config)
    albedo_optimizer = torch.optim.Adam([albedo], lr=geometry.albedo_learning_rate)
    light_optimizer = torch.optim.Adam(light.parameters(), lr=geometry.light_learning_rate)
    effects = FitEffects(config.effects, len(captures.cameras), device)
    if checkpoint is not None:
        effects.load_state_dict(checkpoint["effects"])
        # The latent itself, not M v recomputed from the saved vertices: resuming is exact.
        positions.latent.data.copy_(checkpoint["latent"].to(device))
        light.load_state_dict(checkpoint["light"])
        positions.optimizer.load_state_dict(checkpoint["position_optimizer"])
        albedo_optimizer.load_state_dict(checkpoint["albedo_optimizer"])
        light_optimizer.load_state_dict(checkpoint["light_optimizer"])
        restore_random_states(checkpoint["random"], generator)

    def save(step: int, stage: str = "geometry") -> None:
        save_checkpoint(
            checkpoint_path,
            {
                "stage": stage,
                "step": step,
                "verts": positions.verts().detach().cpu(),
                "latent": positions.latent.detach().cpu(),
                "faces": positions.faces.cpu(),
                "albedo": albedo.detach().cpu(),
                "diagonal": diagonal,
                "light": light.state_dict(),
                "position_optimizer": positions.optimizer.state_dict(),
                "albedo_optimizer": albedo_optimizer.state_dict(),
                "light_optimizer": light_optimizer.state_dict(),
                "effects": effects.state_dict(),
                "random": random_states(generator),
            },
        )

    warned_faces = False
    started = time.perf_counter()
    bar = tqdm(
        range(start_step, geometry.steps),
        desc="fit geometry",
        initial=start_step,
        total=geometry.steps,
        unit="step",
    )
    for step in bar:
        progress = step / max(geometry.steps, 1)
        level = pyramid.level_for(progress)
        cameras, images, masks = pyramid.levels[level]
        views = sample_views(len(cameras), geometry.views_per_step, generator).to(device)
        verts = positions.verts()
        mesh = Mesh(verts, positions.faces, vertex_colors=albedo.clamp(0, 1))
        output = renderer.render(
            mesh, cameras[views], light.lighting(), topology=positions.topology
        )
        color_loss = image_loss(output.color, images[views], geometry.image_loss)
        mask_loss = (output.alpha - masks[views]).abs().mean()
        loss = color_loss + geometry.mask_weight * mask_loss
        positions.optimizer.zero_grad()
        albedo_optimizer.zero_grad()
        light_optimizer.zero_grad()
        effects.zero_grad()
        loss.backward()
        positions.optimizer.step()
        albedo_optimizer.step()
        light_optimizer.step()
        effects.step(progress)

        if step % LOG_EVERY == 0 or step == geometry.steps - 1:
            record = step_record(
                "geometry",
                step,
                {"loss": loss, "color_loss": color_loss, "mask_loss": mask_loss},
                output.color,
                images[views],
                cameras.image_size,
                int(positions.faces.shape[0]),
                time.perf_counter() - started,
            )
            history.log(record)
            bar.set_postfix(loss=f"{record['loss']:.4f}", faces=record["faces"])

        remesh_now = (
            geometry.remesh_every > 0
            and (step + 1) % geometry.remesh_every == 0
            and progress < geometry.remesh_until
            and step + 1 < geometry.steps
        )
        if remesh_now:
            positions, albedo, albedo_optimizer = _remesh_state(
                positions, albedo, albedo_optimizer, config, progress, diagonal
            )
            faces_now = int(positions.faces.shape[0])
            if not warned_faces and faces_now > FACE_WARNING_FACTOR * config.simplify.target_faces:
                warned_faces = True
                warn_user(
                    f"fit: remeshing grew the mesh to {faces_now} faces, over "
                    f"{FACE_WARNING_FACTOR} x fit.simplify.target_faces "
                    f"({config.simplify.target_faces}); each step slows down with it. The "
                    "initial hull is probably much larger than the object (keep "
                    "dataset.normalize.enabled true, check the masks), or raise "
                    "fit.geometry.edge_length_end"
                )
        if (step + 1) % config.checkpoint_every == 0:
            save(step + 1)
    bar.close()
    save(geometry.steps, stage="geometry_done")
    return GeometryResult(
        positions.verts().detach(), positions.faces, albedo.detach().clamp(0, 1), light, effects
    )


def _remesh_state(positions, albedo, albedo_optimizer, config, progress, diagonal):
    """Remesh and carry albedo and every optimizer moment across the new topology."""
    verts = positions.verts().detach()
    position_state = positions.optimizer.state[positions.latent]
    albedo_state = albedo_optimizer.state[albedo]
    attributes = {"albedo": albedo.detach()}
    for key in ("exp_avg", "exp_avg_sq"):
        # Latent moments are carried as they are: a fresh start would lose the step scale.
        attributes[f"position_{key}"] = position_state[key]
        attributes[f"albedo_{key}"] = albedo_state[key]
    new_verts, new_faces, carried = _remesh(
        verts,
        positions.faces,
        target_edge_length(config, progress, diagonal),
        attributes=attributes,
    )
    new_positions = _PositionOptimizer(new_verts, new_faces, config)
    new_positions.optimizer.state[new_positions.latent] = {
        "step": position_state["step"],
        "exp_avg": carried["position_exp_avg"].float(),
        "exp_avg_sq": carried["position_exp_avg_sq"].float(),
    }
    new_albedo = torch.nn.Parameter(carried["albedo"].float())
    new_albedo_optimizer = torch.optim.Adam([new_albedo], lr=albedo_optimizer.param_groups[0]["lr"])
    new_albedo_optimizer.state[new_albedo] = {
        "step": albedo_state["step"],
        "exp_avg": carried["albedo_exp_avg"].float(),
        "exp_avg_sq": carried["albedo_exp_avg_sq"].float(),
    }
    return new_positions, new_albedo, new_albedo_optimizer


def _result_from_checkpoint(
    checkpoint: dict, device: torch.device, frame: str = "world"
) -> GeometryResult:
    light = LightModel(frame=frame)
    light.load_state_dict(checkpoint["light"])
    return GeometryResult(
        checkpoint["verts"].to(device),
        checkpoint["faces"].to(device),
        checkpoint["albedo"].to(device).clamp(0, 1),
        light.to(device),
    )
