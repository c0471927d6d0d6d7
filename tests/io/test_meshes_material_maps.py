"""Material maps of the `pbr` material in meshes: OBJ/MTL map_Pr/map_Pm, GLB metallic-roughness."""

from __future__ import annotations

import pytest
import torch

from recon.errors import ReconError
from recon.io.meshes import load_material_maps, load_mesh, save_mesh
from recon.mesh.mesh import Mesh


def _textured_quad() -> tuple[Mesh, torch.Tensor]:
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    generator = torch.Generator().manual_seed(0)
    texture = torch.rand(8, 8, 3, generator=generator)
    maps = torch.rand(8, 8, 2, generator=generator)
    return Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=texture), maps


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_material_maps_round_trip(tmp_path, suffix):
    mesh, maps = _textured_quad()
    path = tmp_path / f"model{suffix}"
    save_mesh(path, mesh, material_maps=maps)
    loaded = load_material_maps(path)
    assert loaded is not None and loaded.shape == (8, 8, 2)
    # 8-bit quantisation of linear data: at most half a step off.
    assert float((loaded - maps).abs().max()) <= 0.5 / 255 + 1e-6
    back = load_mesh(path)
    assert float((back.texture - mesh.texture).abs().max()) < 0.02
    if suffix == ".obj":
        library = (tmp_path / "model.mtl").read_text()
        assert "map_Kd model_texture.png" in library
        assert "map_Pr model_roughness.png" in library and "map_Pm model_metallic.png" in library


def test_meshes_without_material_maps_have_none(tmp_path):
    mesh, _ = _textured_quad()
    save_mesh(tmp_path / "plain.obj", mesh)
    save_mesh(tmp_path / "plain.glb", mesh)
    assert load_material_maps(tmp_path / "plain.obj") is None
    assert load_material_maps(tmp_path / "plain.glb") is None


def test_material_maps_of_the_wrong_shape_are_refused_by_name(tmp_path):
    mesh, maps = _textured_quad()
    with pytest.raises(ReconError, match=r"material_maps: expected \[h, w, 2\].*\(8, 8, 3\)"):
        save_mesh(tmp_path / "bad.obj", mesh, material_maps=torch.cat([maps, maps[..., :1]], -1))
