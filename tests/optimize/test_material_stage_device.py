"""The `pbr` texture stage on every device (CUDA where present, skipped otherwise): a few steps
of the fit keep its parameters on the device, inside their bounds, and lower the loss."""

from __future__ import annotations

import torch
import trimesh

from recon.camera import orbit_cameras
from recon.config.run_config import FitConfig
from recon.io.datasets import CaptureSet
from recon.mesh.mesh import Mesh
from recon.mesh.uv import unwrap
from recon.optimize.checkpoint import History
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.material_stage import MINIMUM_ROUGHNESS, run_pbr_texture_stage
from recon.optimize.scene_model import LightModel
from recon.render.environment import latlong_directions, prefilter_environment
from recon.render.renderer import Renderer

SIZE = 24


def _glossy_captures() -> tuple[Mesh, CaptureSet]:
    """A UV-mapped sphere (uniform base 0.5, roughness 0.3) under one bright window, 6 views."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    uvs, uv_faces = unwrap(verts, faces, resolution=64)
    base = torch.full((64, 64, 3), 0.5)
    mesh = Mesh(verts, faces, uvs=uvs.float(), uv_faces=uv_faces, texture=base)
    texture = torch.cat([base, torch.tensor([0.3, 0.0]).expand(64, 64, 2)], -1)
    directions, _ = latlong_directions(8, 16)
    window = torch.nn.functional.normalize(torch.tensor([0.5, 0.7, 0.5]), dim=0)
    environment = (0.3 + 5 * torch.exp((directions @ window - 1) / 0.1))[..., None]
    cameras = orbit_cameras(6, (SIZE, SIZE), distance=3.0)
    renderer = Renderer(texture_boundary="clamp")
    with torch.no_grad():
        output = renderer.shade_pbr(
            renderer.surface_buffers(mesh, cameras),
            cameras.centers(),
            texture,
            prefilter_environment(environment.expand(8, 16, 3).contiguous(), 4),
        )
    names = [f"train_{index}" for index in range(6)]
    return mesh, CaptureSet(cameras, output.color, output.alpha, names, "train")


def test_pbr_texture_stage_runs_on_the_device(device, tmp_path):
    mesh, train = _glossy_captures()
    config = FitConfig()
    config.material = "pbr"
    config.texture.steps = 8
    config.texture.views_per_step = 2
    config.texture.texture_size = 64
    config.texture.learning_rate = 0.0  # geometry given
    config.checkpoint_every = 1000
    config.pbr.environment_size = [8, 16]
    config.pbr.prefilter_levels = 4
    grey = torch.full((mesh.verts.shape[0], 3), 0.5)
    geometry = GeometryResult(
        mesh.verts.to(device),
        mesh.faces.to(device),
        grey.to(device),
        LightModel(ambient=1.0, with_sun=False).to(device),
    )
    history = History(tmp_path / "history.jsonl")
    torch.manual_seed(0)
    result = run_pbr_texture_stage(train, geometry, config, device, 0, tmp_path / "pbr.pt", history)
    for tensor in (result.mesh.verts, result.mesh.texture, result.material, result.environment):
        assert tensor.device.type == device.type and bool(torch.isfinite(tensor).all())
    roughness = result.material[..., 0]
    assert float(roughness.min()) >= MINIMUM_ROUGHNESS - 1e-6 and float(roughness.max()) <= 1
    with torch.no_grad():
        output = result.render(Renderer(texture_boundary="clamp"), train.cameras.to(device))
    assert output.color.device.type == device.type
    losses = [record["loss"] for record in history.records() if record["stage"] == "texture"]
    assert len(losses) >= 2 and losses[-1] < losses[0]
