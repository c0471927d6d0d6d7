"""recon.io.meshes: the `pbr` material's tangent-space normal map in OBJ/MTL (norm, map_Bump)
and GLB (normalTexture) round-trips with the roughness/metalness maps."""

from __future__ import annotations

import pytest
import torch

from recon.io.meshes import load_material_maps, save_mesh
from recon.mesh.mesh import Mesh


def _quad_with_normal_map() -> tuple[Mesh, torch.Tensor]:
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    generator = torch.Generator().manual_seed(1)
    texture = torch.rand(8, 8, 3, generator=generator)
    slopes = (torch.rand(8, 8, 2, generator=generator) - 0.5) * 1.2
    z = (1 - slopes.square().sum(-1, keepdim=True)).sqrt()
    maps = torch.cat([torch.rand(8, 8, 2, generator=generator), slopes, z], dim=-1)
    return Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=texture), maps


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_normal_map_round_trips_with_the_material_maps(tmp_path, suffix):
    mesh, maps = _quad_with_normal_map()
    path = tmp_path / f"model{suffix}"
    save_mesh(path, mesh, material_maps=maps)
    loaded = load_material_maps(path)
    assert loaded is not None and loaded.shape == (8, 8, 5)
    # 8-bit: half a step of [0, 1] data, a full step of the normal's [-1, 1].
    assert float((loaded[..., :2] - maps[..., :2]).abs().max()) <= 0.5 / 255 + 1e-6
    assert float((loaded[..., 2:] - maps[..., 2:]).abs().max()) <= 1 / 255 + 1e-6
    if suffix == ".obj":
        library = (tmp_path / "model.mtl").read_text()
        assert "norm model_normal.png" in library and "map_Bump model_normal.png" in library


def test_material_maps_without_a_normal_map_stay_two_channels(tmp_path):
    mesh, maps = _quad_with_normal_map()
    save_mesh(tmp_path / "model.obj", mesh, material_maps=maps[..., :2])
    assert load_material_maps(tmp_path / "model.obj").shape == (8, 8, 2)
    assert "norm" not in (tmp_path / "model.mtl").read_text()
