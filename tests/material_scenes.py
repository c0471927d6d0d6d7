"""A tiny textured quad with pbr material maps, shared by the export, fitted-scene and report
tests of the pbr material."""

from __future__ import annotations

import torch

from recon.mesh.mesh import Mesh


def textured_quad() -> tuple[Mesh, torch.Tensor]:
    """A unit quad (2 faces) with an 8 x 8 random base colour and its roughness/metalness maps
    [8, 8, 2], both drawn from a fixed seed."""
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    generator = torch.Generator().manual_seed(0)
    texture = torch.rand(8, 8, 3, generator=generator)
    maps = torch.rand(8, 8, 2, generator=generator)
    return Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=texture), maps


def position_material(verts: torch.Tensor) -> torch.Tensor:
    """A material [V, 2] linear in the position (so barycentric blends of it are exact):
    roughness 0.3 + 0.15 x, metalness 0.5 + 0.3 z (on a unit sphere: [0.15, 0.45], [0.2, 0.8])."""
    return torch.stack([0.3 + 0.15 * verts[:, 0], 0.5 + 0.3 * verts[:, 2]], dim=-1)


def unwrapped_sphere(resolution: int, subdivisions: int = 3) -> tuple[Mesh, torch.Tensor]:
    """A unit icosphere unwrapped (xatlas) for a resolution x resolution atlas, with a grey base
    colour and position_material baked onto the atlas (dilated, so that bilinear taps at chart
    borders read the chart's own values): (mesh, maps [resolution, resolution, 2])."""
    import trimesh

    from recon.mesh.uv import bake_vertex_attribute, dilate, unwrap

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    uvs, uv_faces = unwrap(verts, faces, resolution=resolution)
    base = torch.full((resolution, resolution, 3), 0.5)
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=uv_faces, texture=base)
    maps, coverage = bake_vertex_attribute(mesh, position_material(verts), (resolution, resolution))
    return mesh, dilate(maps, coverage)


def material_run(root, material: str, roughness_offset: float = 0.0):
    """A run folder whose fit is done: a synthetic world's reference (a unit sphere carrying
    its true maps, position_material), a tiny dataset of it (2 train and 2 test views, 32 px)
    and a fitted scene: for material 'pbr' the same sphere unwrapped anew, its maps baked
    again with roughness_offset added to the roughness; for 'lambert' the plain textured mesh.
    Returns the run's RunPaths."""
    import math

    from recon.camera import Cameras, intrinsics_from_fov, look_at
    from recon.io.datasets import write_nerf_synthetic
    from recon.io.meshes import save_mesh
    from recon.io.run_folder import prepare_run_folder
    from recon.optimize.material_stage import PbrTextureResult, light_from_environment
    from recon.optimize.scene_model import LightModel
    from recon.optimize.texture_stage import TextureResult
    from recon.render.renderer import Renderer
    from recon.render.shading import Lighting
    from recon.stages.fitted_scene import write_fitted_scene, write_pbr_fit

    paths = prepare_run_folder(root)
    reference, true_maps = unwrapped_sphere(64)
    paths.ground_truth.mkdir(parents=True, exist_ok=True)
    save_mesh(paths.reference_mesh, reference, material_maps=true_maps)
    angles = torch.tensor([0.0, 0.5, 1.0, 1.5]) * math.pi
    eyes = torch.stack([3.5 * angles.sin(), 0.8 * torch.ones(4), 3.5 * angles.cos()], dim=-1)
    cameras = Cameras(
        look_at(eyes, torch.zeros(4, 3)), intrinsics_from_fov(45.0, (32, 32)), (32, 32)
    )
    output = Renderer().render(reference, cameras, Lighting.constant())
    for split, views in (("train", slice(0, 2)), ("test", slice(2, 4))):
        write_nerf_synthetic(
            paths.dataset, split, cameras[views], output.color[views], output.alpha[views]
        )
    fitted, fitted_maps = unwrapped_sphere(48)
    if material == "pbr":
        environment = torch.full((4, 8, 3), 0.5)
        maps = (fitted_maps + torch.tensor([roughness_offset, 0.0])).clamp(0, 1)
        light = light_from_environment(environment)
        write_pbr_fit(paths, PbrTextureResult(fitted, maps, environment, light, 0.5, 4))
    else:
        write_fitted_scene(paths, TextureResult(fitted, LightModel()))
    return paths
