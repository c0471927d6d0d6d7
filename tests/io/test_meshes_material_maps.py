"""Material maps of the `pbr` material in meshes: OBJ/MTL map_Pr/map_Pm, GLB metallic-roughness."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.errors import ReconError
from recon.io.meshes import load_material_maps, load_mesh, save_mesh
from tests.material_scenes import textured_quad


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_material_maps_round_trip(tmp_path, suffix):
    mesh, maps = textured_quad()
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
    mesh, _ = textured_quad()
    save_mesh(tmp_path / "plain.obj", mesh)
    save_mesh(tmp_path / "plain.glb", mesh)
    assert load_material_maps(tmp_path / "plain.obj") is None
    assert load_material_maps(tmp_path / "plain.glb") is None


def test_material_maps_of_the_wrong_shape_are_refused_by_name(tmp_path):
    mesh, maps = textured_quad()
    with pytest.raises(ReconError, match=r"material_maps: expected \[h, w, 2\].*\(8, 8, 3\)"):
        save_mesh(tmp_path / "bad.obj", mesh, material_maps=torch.cat([maps, maps[..., :1]], -1))


def _glb_image(path, texture_info: dict) -> np.ndarray:
    """The pixels [h, w, C] of a glTF texture reference, read from the GLB's own chunks (not
    through recon's loader: the channel convention is checked against the glTF spec)."""
    import io
    import json
    import struct

    from PIL import Image

    data = path.read_bytes()
    json_length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20 : 20 + json_length])
    binary = data[20 + json_length + 8 :]
    source = document["textures"][texture_info["index"]]["source"]
    view = document["bufferViews"][document["images"][source]["bufferView"]]
    start = view.get("byteOffset", 0)
    with Image.open(io.BytesIO(binary[start : start + view["byteLength"]])) as image:
        return np.asarray(image.convert("RGB")).astype(np.float64) / 255


def test_glb_metallic_roughness_follows_the_gltf_channels(tmp_path):
    """glTF 2.0: metallicRoughnessTexture holds roughness in green and metalness in blue
    (linear), scaled by roughnessFactor / metallicFactor; the base colour texture is sRGB."""
    import json
    import struct

    mesh, maps = textured_quad()
    path = tmp_path / "model.glb"
    save_mesh(path, mesh, material_maps=maps)
    data = path.read_bytes()
    json_length = struct.unpack_from("<I", data, 12)[0]
    material = json.loads(data[20 : 20 + json_length])["materials"][0]["pbrMetallicRoughness"]
    assert (
        material.get("metallicFactor", 1.0) == 1.0 and material.get("roughnessFactor", 1.0) == 1.0
    )
    packed = _glb_image(path, material["metallicRoughnessTexture"])
    assert packed.shape[:2] == (8, 8)
    np.testing.assert_allclose(packed[..., 1], maps[..., 0].numpy(), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(packed[..., 2], maps[..., 1].numpy(), atol=0.5 / 255 + 1e-6)
    base = _glb_image(path, material["baseColorTexture"])
    from recon.io.images import linear_to_srgb

    expected = linear_to_srgb(mesh.texture).numpy()
    np.testing.assert_allclose(base, expected, atol=0.5 / 255 + 1e-6)


def test_obj_roughness_and_metallic_files_hold_linear_values(tmp_path):
    """map_Pr / map_Pm are single-channel linear images (no sRGB curve): read back directly."""
    from PIL import Image

    mesh, maps = textured_quad()
    save_mesh(tmp_path / "model.obj", mesh, material_maps=maps)
    for name, channel in (("model_roughness.png", 0), ("model_metallic.png", 1)):
        with Image.open(tmp_path / name) as image:
            values = np.asarray(image.convert("L")).astype(np.float64) / 255
        np.testing.assert_allclose(values, maps[..., channel].numpy(), atol=0.5 / 255 + 1e-6)


def test_obj_orm_texture_packs_occlusion_roughness_metalness_as_gltf_does(tmp_path):
    """The MTL (read by trimesh's MTL parser, not recon's loader) names the ORM texture beside
    map_Pr / map_Pm; its channels are R occlusion 1, G roughness, B metalness, linear."""
    from PIL import Image
    from trimesh.exchange.obj import parse_mtl

    mesh, maps = textured_quad()
    save_mesh(tmp_path / "model.obj", mesh, material_maps=maps)
    (material,) = parse_mtl((tmp_path / "model.mtl").read_text()).values()
    assert material["map_orm"] == ["model_orm.png"]
    assert material["map_pr"] == ["model_roughness.png"]
    assert material["map_pm"] == ["model_metallic.png"]
    with Image.open(tmp_path / "model_orm.png") as image:
        assert image.mode == "RGB"
        orm = np.asarray(image).astype(np.float64) / 255
    np.testing.assert_array_equal(orm[..., 0], 1.0)
    np.testing.assert_allclose(orm[..., 1], maps[..., 0].numpy(), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(orm[..., 2], maps[..., 1].numpy(), atol=0.5 / 255 + 1e-6)
    # The GLB's metallic-roughness image is the same ORM texture (glTF ignores its red).
    save_mesh(tmp_path / "model.glb", mesh, material_maps=maps)
    data = (tmp_path / "model.glb").read_bytes()
    import json
    import struct

    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20 : 20 + length])
    packed = _glb_image(
        tmp_path / "model.glb",
        document["materials"][0]["pbrMetallicRoughness"]["metallicRoughnessTexture"],
    )
    np.testing.assert_array_equal(packed, orm)
