"""Mesh load/save tests for recon.io (a synthetic cube; the shared meshes when present)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from recon.errors import ReconError
from recon.io import load_mesh, load_texture_image, read_png_pixels, save_mesh, srgb_to_linear
from recon.io.meshes import load_material_maps
from recon.mesh.mesh import Mesh

SHARED_MESHES = Path(__file__).parents[2] / ".." / "shared" / "meshes"


def cube_mesh(texture: bool = True, colours: bool = False) -> Mesh:
    """A unit cube: 8 shared corners, 12 outward CCW triangles, each side its own UV square.

    Every corner is used with 3 different UVs (a seam everywhere), so V = 8 while T = 24.
    """
    verts = torch.tensor(
        [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)],
        dtype=torch.float32,
    )
    # Sides as quads (a, b, c, d) counter-clockwise seen from outside.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces, uv_faces, uvs = [], [], []
    for side, (a, b, c, d) in enumerate(quads):
        column, row = side % 3, side // 3
        base = len(uvs)
        for du, dv in ((0, 1), (1, 1), (1, 0), (0, 0)):
            uvs.append(((column + 0.1 + 0.8 * du) / 3, (row + 0.1 + 0.8 * dv) / 2))
        faces += [(a, b, c), (a, c, d)]
        uv_faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    image = None
    if texture:
        # sRGB codes decoded to linear, so an 8-bit PNG stores them without loss.
        codes = torch.randint(0, 256, (8, 12, 3), generator=torch.Generator().manual_seed(0))
        image = srgb_to_linear(codes.float() / 255)
    vertex_colours = (
        torch.rand(8, 3, generator=torch.Generator().manual_seed(1)) if colours else None
    )
    return Mesh(
        verts=verts,
        faces=torch.tensor(faces),
        uvs=torch.tensor(uvs, dtype=torch.float32),
        uv_faces=torch.tensor(uv_faces),
        vertex_colors=vertex_colours,
        texture=image,
    )


def test_cube_faces_point_outwards() -> None:
    mesh = cube_mesh()
    corners = mesh.verts[mesh.faces]
    normals = torch.linalg.cross(
        corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1
    )
    assert bool(((normals * corners.mean(dim=1)).sum(-1) > 0).all())


def test_obj_round_trip(tmp_path: Path) -> None:
    mesh = cube_mesh()
    save_mesh(tmp_path / "cube.obj", mesh)
    assert sorted(entry.name for entry in tmp_path.iterdir()) == [
        "cube.mtl",
        "cube.obj",
        "cube_texture.png",
    ]
    text = (tmp_path / "cube.obj").read_text()
    assert "mtllib cube.mtl" in text and "usemtl material_0" in text
    assert "map_Kd cube_texture.png" in (tmp_path / "cube.mtl").read_text()
    # OBJ's v axis points up: the first vt line is (u, 1 - v).
    first_vt = [line for line in text.splitlines() if line.startswith("vt ")][0].split()[1:]
    assert [float(value) for value in first_vt] == pytest.approx(
        [float(mesh.uvs[0, 0]), 1 - float(mesh.uvs[0, 1])], abs=1e-7
    )
    assert "f 1/1 2/2 4/3" in text  # shared positions, separate UV indices

    back = load_mesh(tmp_path / "cube.obj")
    assert back.verts.shape == (8, 3) and back.uvs.shape == (24, 2)
    assert torch.equal(back.verts, mesh.verts) and torch.equal(back.faces, mesh.faces)
    # trimesh may renumber the UVs; each face corner must keep its UV (bit-exact: 1 - v is exact).
    assert torch.equal(back.uvs[back.uv_faces], mesh.uvs[mesh.uv_faces])
    assert back.faces.dtype == torch.int64 and back.verts.dtype == torch.float32
    assert back.texture.shape == (8, 12, 3)
    assert float((back.texture - mesh.texture).abs().max()) < 1e-6


def test_glb_round_trip(tmp_path: Path) -> None:
    mesh = cube_mesh()
    save_mesh(tmp_path / "cube.glb", mesh)
    assert [entry.name for entry in tmp_path.iterdir()] == ["cube.glb"]
    back = load_mesh(tmp_path / "cube.glb")
    # glTF splits the corners at the seams; load_mesh merges them back by position.
    assert back.verts.shape == (8, 3) and back.uvs.shape[0] > 8
    assert torch.equal(back.verts, mesh.verts) and torch.equal(back.faces, mesh.faces)
    corner_uvs = back.uvs[back.uv_faces]
    assert float((corner_uvs - mesh.uvs[mesh.uv_faces]).abs().max()) < 1e-6
    assert float((back.texture - mesh.texture).abs().max()) < 1e-6


def glb_texcoords(path: Path) -> np.ndarray:
    """The raw TEXCOORD_0 accessor [N, 2] of the first primitive of a GLB, read by hand."""
    data = path.read_bytes()
    json_length = struct.unpack("<I", data[12:16])[0]
    document = json.loads(data[20 : 20 + json_length])
    binary = data[20 + json_length + 8 :]
    accessor = document["accessors"][
        document["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
    ]
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    assert accessor["componentType"] == 5126 and accessor["type"] == "VEC2"  # float32 pairs
    return np.frombuffer(binary, dtype="<f4", count=2 * accessor["count"], offset=start).reshape(
        -1, 2
    )


def test_glb_stores_top_down_uvs(tmp_path: Path) -> None:
    # glTF's UV origin is the image's top-left, like ours: the file must hold our v unflipped.
    mesh = cube_mesh()
    save_mesh(tmp_path / "cube.glb", mesh)
    stored = glb_texcoords(tmp_path / "cube.glb")
    ours = {tuple(row) for row in mesh.uvs.tolist()}
    assert {tuple(row) for row in stored.tolist()} == ours


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_vertex_colours_round_trip(tmp_path: Path, suffix: str) -> None:
    mesh = cube_mesh(texture=False, colours=True)
    mesh = Mesh(mesh.verts, mesh.faces, vertex_colors=mesh.vertex_colors)
    save_mesh(tmp_path / f"cube{suffix}", mesh)
    back = load_mesh(tmp_path / f"cube{suffix}")
    assert torch.equal(back.verts, mesh.verts) and torch.equal(back.faces, mesh.faces)
    assert back.uvs is None and back.texture is None
    # trimesh reads OBJ colours into 8-bit sRGB (slope of sRGB decoding <= 2.4 / 1.055);
    # glTF stores linear colour in 8 bits.
    bound = (2.4 / 1.055 if suffix == ".obj" else 1.0) * 0.5 / 255 + 1e-6
    assert float((back.vertex_colors - mesh.vertex_colors).abs().max()) <= bound


def test_obj_with_uvs_and_no_texture(tmp_path: Path) -> None:
    mesh = cube_mesh(texture=False)
    save_mesh(tmp_path / "plain.obj", mesh)
    assert [entry.name for entry in tmp_path.iterdir()] == ["plain.obj"]
    back = load_mesh(tmp_path / "plain.obj")
    assert back.texture is None
    assert torch.equal(back.uvs[back.uv_faces], mesh.uvs[mesh.uv_faces])


def test_load_hand_written_obj_merges_seams_and_flips_v(tmp_path: Path) -> None:
    path = tmp_path / "quad.obj"
    path.write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
        "f 1/1 2/2 3/3\nf 1/5 3/3 4/4\n"
    )
    mesh = load_mesh(path)
    assert mesh.verts.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    # vertex 0 carries two different UVs: one position, two UVs.
    corner_uvs = mesh.uvs[mesh.uv_faces]
    assert corner_uvs[0].tolist() == [[0, 1], [1, 1], [1, 0]]
    assert corner_uvs[1].tolist() == [[0.5, 0.5], [1, 0], [0, 0]]


def test_texture_path_and_loader(tmp_path: Path) -> None:
    mesh = cube_mesh()
    save_mesh(tmp_path / "cube.obj", mesh)
    (tmp_path / "cube.mtl").unlink()
    with pytest.warns(UserWarning, match=r"cube\.mtl not found"):
        untextured = load_mesh(tmp_path / "cube.obj")
    assert untextured.texture is None
    textured = load_mesh(tmp_path / "cube.obj", texture_path=tmp_path / "cube_texture.png")
    assert float((textured.texture - mesh.texture).abs().max()) < 1e-6
    texture = load_texture_image(tmp_path / "cube_texture.png")
    assert texture.shape == (8, 12, 3) and texture.dtype == torch.float32
    assert read_png_pixels(tmp_path / "cube_texture.png").dtype == np.uint8


def test_ply_and_off_via_trimesh(tmp_path: Path) -> None:
    mesh = cube_mesh(texture=False)
    shape = trimesh.Trimesh(mesh.verts.numpy(), mesh.faces.numpy(), process=False)
    for suffix in (".ply", ".off"):
        shape.export(tmp_path / f"cube{suffix}")
        back = load_mesh(tmp_path / f"cube{suffix}")
        assert torch.equal(back.verts, mesh.verts) and torch.equal(back.faces, mesh.faces)


def test_ply_with_uvs_and_no_texture_has_no_texture(tmp_path: Path) -> None:
    # trimesh gives such files a 2x2 gray placeholder image, which must not become a texture.
    visual = trimesh.visual.TextureVisuals(uv=np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    shape = trimesh.Trimesh(np.eye(3), [[0, 1, 2]], visual=visual, process=False)
    shape.export(tmp_path / "triangle.ply")
    mesh = load_mesh(tmp_path / "triangle.ply")
    assert mesh.texture is None
    assert mesh.uvs[mesh.uv_faces[0]].tolist() == [[0.0, 1.0], [1.0, 1.0], [0.0, 0.0]]


def test_mesh_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ReconError, match=r"missing\.obj: mesh file not found"):
        load_mesh(tmp_path / "missing.obj")
    (tmp_path / "shape.xyz").write_text("0 0 0\n")
    with pytest.raises(ReconError, match=r"shape\.xyz: unsupported mesh format '\.xyz'"):
        load_mesh(tmp_path / "shape.xyz")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ReconError, match=r"points\.obj: expected a triangle mesh, found no faces"):
        load_mesh(tmp_path / "points.obj")
    (tmp_path / "broken.glb").write_bytes(b"glTF garbage")
    with pytest.raises(ReconError, match=r"broken\.glb: cannot load mesh"):
        load_mesh(tmp_path / "broken.glb")
    with pytest.raises(ReconError, match=r"cube\.stl: save_mesh writes \.obj or \.glb"):
        save_mesh(tmp_path / "cube.stl", cube_mesh())


def test_obj_with_two_textures_is_refused(tmp_path: Path) -> None:
    (tmp_path / "two.mtl").write_text("newmtl a\nmap_Kd a.png\nnewmtl b\nmap_Kd -s 1 1 1 b.png\n")
    (tmp_path / "two.obj").write_text(
        "mtllib two.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
        "usemtl a\nf 1/1 2/2 3/3\nusemtl b\nf 1/1 3/3 2/2\n"
    )
    with pytest.raises(ReconError, match=r"two\.obj: its materials use 2 textures"):
        load_mesh(tmp_path / "two.obj")


@pytest.mark.shared
def test_spot_counts() -> None:
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"{SHARED_MESHES} not found")
    mesh = load_mesh(
        SHARED_MESHES / "spot_triangulated.obj", texture_path=SHARED_MESHES / "spot_texture.png"
    )
    assert mesh.verts.shape == (2930, 3) and mesh.faces.shape == (5856, 3)
    assert mesh.uvs.shape == (3225, 2) and mesh.uv_faces.shape == (5856, 3)
    assert mesh.texture.shape == (1024, 1024, 3)
    # The file's vt v lies in [0.111175, 1.00065]; ours is flipped to 1 - v.
    assert float(mesh.uvs[:, 1].min()) == pytest.approx(1 - 1.00065, abs=1e-6)
    assert float(mesh.uvs[:, 1].max()) == pytest.approx(1 - 0.111175, abs=1e-6)


@pytest.mark.shared
def test_bob_counts_and_mtl_texture() -> None:
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"{SHARED_MESHES} not found")
    mesh = load_mesh(SHARED_MESHES / "bob_tri.obj")
    assert mesh.verts.shape == (5344, 3) and mesh.faces.shape == (10688, 3)
    assert mesh.uvs.shape == (5647, 2)
    assert mesh.texture is not None and mesh.texture.shape == (2048, 2048, 3)
    # Genus 1: V - E + F = 0 on the merged positions.
    edges = torch.cat([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]])
    unique_edges = torch.unique(torch.sort(edges, dim=1).values, dim=0)
    assert mesh.verts.shape[0] - unique_edges.shape[0] + mesh.faces.shape[0] == 0


# The pbr material's tangent-space normal map (OBJ norm / map_Bump, GLB normalTexture).
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
