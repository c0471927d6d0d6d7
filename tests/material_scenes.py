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
