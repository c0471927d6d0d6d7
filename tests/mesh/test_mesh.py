"""recon.mesh.mesh.uv_tangents: the tangent frames a tangent-space normal map is read in."""

from __future__ import annotations

import math

import torch

from recon.mesh.mesh import uv_tangents


def _plane(rotation: torch.Tensor) -> tuple[torch.Tensor, ...]:
    # u grows with x, v (downwards in recon's convention) shrinks with y.
    flat = torch.tensor([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    return flat @ rotation.T, faces, uvs, faces.clone()


def test_plane_tangents_follow_u_and_upward_v():
    angle = 0.7
    rotation = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    )
    verts, faces, uvs, uv_faces = _plane(rotation)
    tangents, bitangents = uv_tangents(verts, faces, uvs, uv_faces)
    tangents = torch.nn.functional.normalize(tangents, dim=-1)
    bitangents = torch.nn.functional.normalize(bitangents, dim=-1)
    torch.testing.assert_close(tangents, rotation[:, 0].expand(4, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(bitangents, rotation[:, 1].expand(4, 3), atol=1e-5, rtol=0)


def test_mirrored_uvs_flip_the_bitangent_and_degenerate_uvs_add_nothing():
    verts, faces, uvs, uv_faces = _plane(torch.eye(3))
    mirrored = uvs.clone()
    mirrored[:, 1] = 1 - mirrored[:, 1]
    _, bitangents = uv_tangents(verts, faces, mirrored, uv_faces)
    assert float(bitangents[:, 1].max()) < 0
    collapsed = torch.zeros_like(uvs)
    tangents, bitangents = uv_tangents(verts, faces, collapsed, uv_faces)
    assert float(tangents.abs().max()) == 0 and float(bitangents.abs().max()) == 0
