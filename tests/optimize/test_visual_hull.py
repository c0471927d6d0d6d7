"""Visual hull: carving keeps the object, and keeps the hole of a genus-1 shape."""

from __future__ import annotations

import torch
import trimesh

from recon.camera import Cameras, intrinsics_from_fov, look_at
from recon.mesh.mesh import Mesh
from recon.optimize.visual_hull import visual_hull
from recon.render.renderer import Renderer
from recon.render.shading import Lighting


def _fibonacci_cameras(count: int, size: int = 48) -> Cameras:
    index = torch.arange(count, dtype=torch.float32) + 0.5
    height = 1 - 2 * index / count
    radius = (1 - height**2).sqrt()
    angle = index * 2.399963
    eyes = 3.0 * torch.stack([radius * torch.cos(angle), height, radius * torch.sin(angle)], -1)
    return Cameras(
        look_at(eyes), intrinsics_from_fov(40.0, (size, size)).expand(count, 3, 3), (size, size)
    )


def _masks(mesh: Mesh, cameras: Cameras) -> torch.Tensor:
    with torch.no_grad():
        return Renderer().render(mesh, cameras, Lighting.constant()).alpha


def test_hull_of_a_sphere_is_close_and_contains_it():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    mesh = Mesh(torch.tensor(sphere.vertices, dtype=torch.float32), torch.tensor(sphere.faces))
    cameras = _fibonacci_cameras(24)
    hull = visual_hull(cameras, _masks(mesh, cameras), resolution=48)
    radii = hull.verts.norm(dim=-1)
    # A hull contains the object: no vertex much inside the sphere, and not far outside.
    assert float(radii.min()) > 0.64 and float(radii.max()) < 0.85
    assert trimesh.Trimesh(hull.verts.numpy(), hull.faces.numpy()).is_watertight


def test_hull_keeps_the_hole_of_a_torus():
    torus = trimesh.creation.torus(major_radius=0.6, minor_radius=0.22)
    mesh = Mesh(torch.tensor(torus.vertices, dtype=torch.float32), torch.tensor(torus.faces))
    cameras = _fibonacci_cameras(32)
    hull = visual_hull(cameras, _masks(mesh, cameras), resolution=48)
    result = trimesh.Trimesh(hull.verts.numpy(), hull.faces.numpy())
    assert result.is_watertight
    assert result.euler_number == 0  # genus 1: the hole survives
