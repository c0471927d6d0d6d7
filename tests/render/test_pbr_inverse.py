"""Inverse rendering through the PBR path: with the environment known, a gradient fit of
roughness and base colour through rasterize -> interpolate -> texture -> shade_pbr recovers
the roughness that rendered the target."""

from __future__ import annotations

import pytest
import torch
import trimesh

from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at
from recon.mesh.mesh import Mesh
from recon.render.environment import latlong_directions, prefilter_environment
from recon.render.renderer import Renderer

SIZE = 24


def _scene():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.8)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    # The material is uniform: every corner may look up the same texel.
    uvs, uv_faces = torch.full((1, 2), 0.5), torch.zeros_like(faces)
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=uv_faces, texture=torch.zeros(8, 8, 3))
    eyes = torch.tensor([[3.0, 0.5, 0.0], [0.0, 0.5, 3.0], [-2.1, 1.5, -2.1], [2.1, -1.0, -2.1]])
    cameras = Cameras(
        look_at(eyes), intrinsics_from_fov(30.0, (SIZE, SIZE)).expand(4, 3, 3), (SIZE, SIZE)
    )
    directions, _ = latlong_directions(16, 32)
    light = torch.nn.functional.normalize(torch.tensor([0.5, 0.7, 0.5]), dim=0)
    environment = 0.2 + 6 * torch.exp((directions @ light - 1) / 0.04)
    return mesh, cameras, environment[..., None].expand(16, 32, 3).contiguous()


def _material(base: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """A uniform [8, 8, 5] material texture (metalness 0)."""
    channels = torch.cat([base, roughness, torch.zeros(1)])
    return channels.expand(8, 8, 5)


@pytest.mark.parametrize("true_roughness", [0.3, 0.55])
def test_known_light_fit_recovers_roughness(true_roughness):
    mesh, cameras, environment = _scene()
    renderer = Renderer(texture_filter="linear")
    buffers = renderer.surface_buffers(mesh, cameras)
    prefiltered = prefilter_environment(environment, 6)
    true_base = torch.tensor([0.6, 0.4, 0.3])
    with torch.no_grad():
        target = renderer.shade_pbr(
            buffers,
            cameras.centers(),
            _material(true_base, torch.tensor([true_roughness])),
            prefiltered,
            antialias_edges=False,
        ).color
    base = torch.full((3,), 0.5, requires_grad=True)
    roughness = torch.tensor([0.8], requires_grad=True)
    optimizer = torch.optim.Adam([base, roughness], lr=0.03)
    for _ in range(80):
        color = renderer.shade_pbr(
            buffers,
            cameras.centers(),
            _material(base, roughness),
            prefiltered,
            antialias_edges=False,
        ).color
        loss = (color - target).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            roughness.clamp_(0.04, 1)
    assert abs(float(roughness.detach()) - true_roughness) < 0.05
    torch.testing.assert_close(base.detach(), true_base, atol=0.05, rtol=0)
