"""The fitted scene in a run folder: mesh/ and light/, written by the fit stage and read by the
evaluate and report stages.

A Lambertian fit writes mesh/model.obj (+ .mtl, texture PNG), mesh/model.glb, light/light.json
(SH coefficients, directional lights) and light/environment.exr (the SH radiance, for viewing);
a `pbr` fit adds its roughness and metallic maps to the mesh and writes its own environment.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace

import torch

from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.images import write_exr
from recon.io.meshes import load_mesh, save_mesh
from recon.io.run_folder import RunPaths
from recon.mesh.mesh import Mesh
from recon.optimize.fit import environment_map_from_light, read_fitted_light
from recon.optimize.material_stage import PbrTextureResult, pbr_light_record, read_pbr_result
from recon.optimize.normalize import SceneTransform
from recon.optimize.scene_model import FitEffects
from recon.optimize.texture_stage import TextureResult
from recon.render.environment import add_suns
from recon.render.shading import Lighting


@dataclass
class FittedScene:
    """A run's fitted scene: mesh (dataset frame), lighting, and the pbr fit when it has one."""

    mesh: Mesh
    lighting: Lighting
    pbr: PbrTextureResult | None = None
    # The fit's effect modules (fit.effects), [] when it had none.
    effects: list = field(default_factory=list)


def write_fitted_scene(
    paths: RunPaths, result: TextureResult, transform: SceneTransform | None = None
) -> dict:
    """Write a Lambertian fit. With a normalising transform the mesh goes to the dataset's own
    frame (the one its cameras are in, which every later stage reads), and the fit's frame
    beside it (mesh/normalized/, light/normalized/). Directional and SH light are the same in
    both frames (the transform has no rotation); point lights move with it. The fit's effect
    modules, when it had any, go to effects.json (their parameters hold in both frames)."""
    paths.mesh_folder.mkdir(parents=True, exist_ok=True)
    mesh = result.mesh.to("cpu")
    if transform is not None:
        save_mesh(paths.normalized_mesh, mesh)
        mesh = replace(mesh, verts=transform.to_dataset(mesh.verts))
    save_mesh(paths.fitted_mesh, mesh)
    save_mesh(paths.fitted_glb, mesh)
    paths.light_folder.mkdir(parents=True, exist_ok=True)
    light_record = result.light.to_json()
    if transform is not None:
        paths.normalized_light.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(paths.normalized_light, light_record)
        light_record = transform.light_to_dataset(light_record)
    atomic_write_json(paths.fitted_light, light_record)
    if result.effects is not None and result.effects.modules:
        atomic_write_json(paths.fitted_effects, result.effects.to_json())
    write_exr(paths.fitted_environment, environment_map_from_light(result.light))
    return {"faces": int(mesh.faces.shape[0]), "vertices": int(mesh.verts.shape[0])}


def write_pbr_fit(
    paths: RunPaths, result: PbrTextureResult, transform: SceneTransform | None = None
) -> dict:
    """Write a `pbr` fit: mesh/model.obj (+ base colour, roughness and metallic PNGs, map_Kd /
    map_Pr / map_Pm, and the normal map when fitted), mesh/model.glb (metallic-roughness
    material), light/environment.exr (the fitted environment itself; with suns also
    light/environment_with_suns.exr, the map with the suns added) and light/light.json (its
    order-2 SH, for Lambertian consumers, plus the pbr settings, the environment's file name and
    its frame). With a normalising transform the mesh goes to the dataset's own frame, as
    write_fitted_scene does; the environment needs no conversion (the transform has no
    rotation)."""
    paths.mesh_folder.mkdir(parents=True, exist_ok=True)
    mesh = result.mesh.to("cpu")
    maps = result.material.detach().cpu()
    if transform is not None:
        paths.normalized_mesh.parent.mkdir(parents=True, exist_ok=True)
        save_mesh(paths.normalized_mesh, mesh, material_maps=maps)
        mesh = replace(mesh, verts=transform.to_dataset(mesh.verts))
    save_mesh(paths.fitted_mesh, mesh, material_maps=maps)
    save_mesh(paths.fitted_glb, mesh, material_maps=maps)
    paths.light_folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(paths.fitted_light, pbr_light_record(result, paths.fitted_environment.name))
    environment = result.environment.detach().cpu()
    write_exr(paths.fitted_environment, environment)
    if result.suns:
        # environment.exr stays sun-free (the fit reads it back beside light.json's suns); the
        # combined map is the one light other renderers can take.
        write_exr(paths.fitted_environment_with_suns, add_suns(environment, result.suns))
    return {
        "faces": int(mesh.faces.shape[0]),
        "vertices": int(mesh.verts.shape[0]),
        "material": "pbr",
    }


def load_fitted_light(paths: RunPaths, device: torch.device | str) -> Lighting:
    """The fitted light as recon Lighting."""
    return read_fitted_light(paths.fitted_light, torch.device(device))


def load_pbr_fit(paths: RunPaths, device: torch.device | str = "cpu") -> PbrTextureResult | None:
    """The run's `pbr` fit, or None when it fitted the Lambertian material."""
    return read_pbr_result(paths.fitted_light, paths.fitted_mesh, device)


def load_fitted_effects(paths: RunPaths, device: torch.device | str) -> list:
    """The run's fitted effect modules (effects.json, written when fit.effects was set), or []
    when it has none."""
    if not paths.fitted_effects.exists():
        return []
    try:
        data = json.loads(paths.fitted_effects.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ReconError(f"{paths.fitted_effects}: unreadable effects record: {error}") from error
    return FitEffects.modules_from_json(data, torch.device(device))


def load_fitted_scene(paths: RunPaths, device: torch.device) -> FittedScene:
    """The run's fitted mesh (on the CPU), light, pbr fit and effect modules (on device)."""
    return FittedScene(
        load_mesh(paths.fitted_mesh),
        load_fitted_light(paths, device),
        load_pbr_fit(paths, device),
        load_fitted_effects(paths, device),
    )
