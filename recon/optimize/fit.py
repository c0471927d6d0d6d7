"""The fit stage: dataset -> normalisation -> geometry stage (remeshing) -> simplify -> unwrap +
bake -> texture stage -> mesh/ (OBJ + MTL + PNG, GLB) and light/ (JSON + EXR environment map).

With dataset.normalize.enabled the fit works in a recentred, rescaled frame
(normalization.json); mesh/model.obj, model.glb and light/light.json are written in the
dataset's own frame (the one its cameras are in, which evaluate, report and diagnose read),
mesh/normalized/ and light/normalized/ in the fit's. Directional and SH light need no
conversion (the transform has no rotation); point lights would move with it."""

from __future__ import annotations

import json
from dataclasses import replace

import torch

from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.datasets import has_split, read_captures
from recon.io.images import write_exr
from recon.io.meshes import save_mesh
from recon.io.run_folder import RunPaths
from recon.optimize.checkpoint import History, load_checkpoint
from recon.optimize.geometry_stage import run_geometry_stage
from recon.optimize.normalize import SceneTransform, estimate_scene_transform
from recon.optimize.scene_model import LightModel
from recon.optimize.texture_stage import run_texture_stage
from recon.render.shading import sh_basis

ENVIRONMENT_SIZE = (64, 128)
# Half-size of the visual hull's grid over the normalised object's half-size.
HULL_MARGIN = 1.5


def environment_map_from_light(light: LightModel, size=ENVIRONMENT_SIZE) -> torch.Tensor:
    """The fitted SH radiance on an equirectangular grid [h, w, 3] (row 0 looks up; azimuth from
    +x toward +z), for viewing the light in any HDR viewer."""
    height, width = size
    theta = (torch.arange(height) + 0.5) * torch.pi / height
    phi = (torch.arange(width) + 0.5) * 2 * torch.pi / width
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.cos(theta), torch.sin(theta) * torch.sin(phi)], -1
    )
    return (sh_basis(directions) @ light.sh.detach().cpu()).clamp_min(0)


def fit_stage(
    config: RunConfig, paths: RunPaths, device: torch.device, resume: bool = False
) -> dict:
    """Entry point 'fit' of the recon.stages group: reads paths.dataset, writes the fitted
    scene, history and checkpoints into the run folder."""
    if not paths.dataset.is_dir() or not has_split(paths.dataset, "train"):
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
    geometry_checkpoint = paths.checkpoints / "geometry.pt"
    texture_checkpoint = paths.checkpoints / "texture.pt"
    truncate = None
    if resume:
        state = load_checkpoint(texture_checkpoint) or load_checkpoint(geometry_checkpoint)
        if state is not None:
            stage = "texture" if state["stage"].startswith("texture") else "geometry"
            truncate = (stage, state["step"] - 1)
    history = History(paths.history, truncate_after=truncate)
    geometry = run_geometry_stage(
        captures,
        config.fit,
        device,
        config.seed,
        geometry_checkpoint,
        history,
        resume=resume,
        hull_radius=hull_radius,
    )
    if config.fit.material == "pbr":
        # The pbr material (base colour, roughness, metalness, environment map): its own stage
        # and writer, recon/optimize/material_stage.py.
        from recon.optimize.material_stage import run_pbr_texture_stage, write_pbr_result

        pbr_result = run_pbr_texture_stage(
            captures,
            geometry,
            config.fit,
            device,
            config.seed,
            texture_checkpoint,
            history,
            resume=resume and texture_checkpoint.exists(),
        )
        if transform is not None:
            # As for the Lambertian material: the dataset's frame for every later stage (the
            # environment is directional, unchanged by a translation and a scale).
            fitted = pbr_result.mesh.to("cpu")
            save_mesh(paths.mesh_folder / "normalized" / "model.obj", fitted)
            pbr_result = replace(
                pbr_result, mesh=replace(fitted, verts=transform.to_dataset(fitted.verts))
            )
        return write_pbr_result(paths, pbr_result)
    result = run_texture_stage(
        captures,
        geometry,
        config.fit,
        device,
        config.seed,
        texture_checkpoint,
        history,
        resume=resume and texture_checkpoint.exists(),
    )
    paths.mesh_folder.mkdir(parents=True, exist_ok=True)
    mesh = result.mesh.to("cpu")
    if transform is not None:
        # The fit's own frame beside the dataset's (which every later stage reads).
        save_mesh(paths.mesh_folder / "normalized" / "model.obj", mesh)
        mesh = replace(mesh, verts=transform.to_dataset(mesh.verts))
    save_mesh(paths.fitted_mesh, mesh)
    save_mesh(paths.mesh_folder / "model.glb", mesh)
    paths.light_folder.mkdir(parents=True, exist_ok=True)
    light_record = result.light.to_json()
    if transform is not None:
        (paths.light_folder / "normalized").mkdir(parents=True, exist_ok=True)
        atomic_write_json(paths.light_folder / "normalized" / "light.json", light_record)
        light_record = transform.light_to_dataset(light_record)
    atomic_write_json(paths.fitted_light, light_record)
    write_exr(paths.light_folder / "environment.exr", environment_map_from_light(result.light))
    if result.effects is not None and result.effects.modules:
        # Shading effects (a specular lobe, shadows) are part of the fitted appearance: the
        # evaluate stage renders held-out views with them. Their parameters are scale- and
        # translation-free, so they hold in the dataset's frame too.
        atomic_write_json(paths.fitted_effects, result.effects.to_json())
    return {"faces": int(mesh.faces.shape[0]), "vertices": int(mesh.verts.shape[0])}


def load_fitted_light(paths: RunPaths, device: torch.device):
    """The fitted light as recon Lighting."""
    from recon.render.shading import Lighting

    return Lighting.from_json(json.loads(paths.fitted_light.read_text()), device)
