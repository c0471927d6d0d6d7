"""Tiny scenes for the model-effect tests, rendered once per module by recon's Renderer."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
import trimesh

from recon.camera import Cameras, intrinsics_from_fov, look_at, orbit_cameras
from recon.mesh.mesh import Mesh
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import DirectionalLight, Lighting


@pytest.fixture(autouse=True)
def single_thread():
    """These tests run many small tensor ops: one thread avoids inter-thread hand-offs that
    dominate on a shared 2-core machine (tens of times slower)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@dataclass
class Scene:
    mesh: Mesh
    cameras: Cameras
    lighting: Lighting
    output: RenderOutput

    @property
    def views(self) -> torch.Tensor:
        return torch.arange(len(self.cameras))


def sun_lighting(ambient: float = 0.35) -> Lighting:
    """A uniform environment plus a sun from the upper front right."""
    lighting = Lighting.constant(ambient)
    direction = torch.nn.functional.normalize(torch.tensor([0.4, 1.0, 0.3]), dim=0)
    lighting.directional.append(DirectionalLight(direction, torch.tensor([2.5, 2.4, 2.2])))
    return lighting


def smooth_colors(verts: torch.Tensor) -> torch.Tensor:
    """A smooth colourful albedo pattern [V, 3] in [0.15, 0.85]."""
    return 0.5 + 0.35 * torch.stack(
        [
            torch.sin(3 * verts[:, 0] + 1),
            torch.cos(4 * verts[:, 1]),
            torch.sin(2 * verts[:, 2] + 2 * verts[:, 0]),
        ],
        dim=-1,
    )


def _mesh(trimesh_mesh: trimesh.Trimesh) -> Mesh:
    verts = torch.tensor(trimesh_mesh.vertices, dtype=torch.float32)
    return Mesh(verts, torch.tensor(trimesh_mesh.faces), vertex_colors=smooth_colors(verts))


def _render(mesh: Mesh, cameras: Cameras, lighting: Lighting) -> Scene:
    # Module-scoped fixtures run before the autouse single_thread one.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            output = Renderer().render(mesh, cameras, lighting)
    finally:
        torch.set_num_threads(previous)
    return Scene(mesh, cameras, lighting, output)


@pytest.fixture(scope="module")
def sphere_scene() -> Scene:
    """A colourful sphere from 3 views at 40 x 40 under a sun."""
    mesh = _mesh(trimesh.creation.icosphere(subdivisions=2, radius=0.8))
    cameras = orbit_cameras(3, (40, 40), distance=2.6, elevation_deg=20)
    return _render(mesh, cameras, sun_lighting())


@pytest.fixture(scope="module")
def plane_scene() -> Scene:
    """A patterned plane filling the whole 40 x 40 frame of one frontal camera (50 degrees)."""
    count = 24
    axis = torch.linspace(-1.2, 1.2, count)
    grid_y, grid_x = torch.meshgrid(axis, axis, indexing="ij")
    verts = torch.stack([grid_x.reshape(-1), grid_y.reshape(-1), torch.zeros(count * count)], -1)
    index = torch.arange(count * count).reshape(count, count)
    a, b = index[:-1, :-1].reshape(-1), index[:-1, 1:].reshape(-1)
    c, d = index[1:, 1:].reshape(-1), index[1:, :-1].reshape(-1)
    faces = torch.cat([torch.stack([a, b, c], -1), torch.stack([a, c, d], -1)])
    colors = 0.5 + 0.4 * torch.stack(
        [
            torch.sin(5 * verts[:, 0]),
            torch.cos(4 * verts[:, 1] + 1),
            torch.sin(3 * (verts[:, 0] + verts[:, 1])),
        ],
        dim=-1,
    )
    mesh = Mesh(verts, faces, vertex_colors=colors)
    cameras = Cameras(
        look_at(torch.tensor([[0.0, 0.0, 2.5]])), intrinsics_from_fov(50, (40, 40))[None], (40, 40)
    )
    return _render(mesh, cameras, Lighting.constant(1.0))


@pytest.fixture(scope="module")
def torus_scene() -> Scene:
    """A colourful torus from 3 views at 32 x 32 (for pose recovery)."""
    mesh = _mesh(
        trimesh.creation.torus(
            major_radius=0.6, minor_radius=0.25, major_sections=24, minor_sections=12
        )
    )
    cameras = orbit_cameras(3, (32, 32), distance=2.4, elevation_deg=35)
    return _render(mesh, cameras, sun_lighting())


@pytest.fixture(scope="module")
def shadow_scene() -> Scene:
    """A sphere floating over a ground slab, lit by a sun: it casts a shadow on the ground."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    sphere.apply_translation([0.0, 0.5, 0.0])
    ground = trimesh.creation.box(extents=[2.0, 0.1, 2.0])
    ground.apply_translation([0.0, -0.3, 0.0])
    ground = ground.subdivide().subdivide().subdivide()
    mesh = _mesh(trimesh.util.concatenate([sphere, ground]))
    cameras = orbit_cameras(3, (40, 40), distance=3.2, elevation_deg=35)
    return _render(mesh, cameras, sun_lighting())


def _central_difference(
    function, parameter: torch.Tensor, index: tuple, step: float = 1e-6
) -> float:
    """d function() / d parameter[index] by central differences (float64 parameters)."""
    with torch.no_grad():
        original = float(parameter[index])
        parameter[index] = original + step
        plus = float(function())
        parameter[index] = original - step
        minus = float(function())
        parameter[index] = original
    return (plus - minus) / (2 * step)


def _adam_fit(effect, prediction, target, steps: int, groups=None) -> float:
    """Optimise only the effect's parameters (its own learning rates) on the squared error
    between prediction() (a tensor or a tuple of tensors) and target; returns the last loss."""
    optimizer = torch.optim.Adam(effect.parameter_groups() if groups is None else groups)
    targets = target if isinstance(target, tuple) else (target,)
    loss = torch.zeros(())
    for _ in range(steps):
        predicted = prediction()
        predicted = predicted if isinstance(predicted, tuple) else (predicted,)
        loss = sum(((p - t) ** 2).mean() for p, t in zip(predicted, targets, strict=True))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return float(loss.detach())


@pytest.fixture
def central_difference():
    """_central_difference, as a fixture (conftest modules are not importable by name)."""
    return _central_difference


@pytest.fixture
def adam_fit():
    """_adam_fit, as a fixture."""
    return _adam_fit
