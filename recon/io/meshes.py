"""Mesh files (OBJ, PLY, GLB, OFF) <-> recon.mesh.Mesh.

Loading goes through trimesh with process=False, which keeps the file's UVs but splits a vertex
wherever it is used with different UVs (or normals). load_mesh undoes that split: positions are
merged by exact value (first occurrence order, which for OBJ is the file's `v` order), faces are
remapped onto them, and the UVs keep their own index buffer (uv_faces). Coincident vertices that a
file keeps apart (such as the teapot's patch borders) are merged as well, which closes such cracks.

UV convention: Mesh.uvs have v = 0 at the TOP of the texture image. OBJ and PLY store v = 0 at
the bottom, and trimesh converts glTF UVs to that bottom-up convention too, so every loaded v is
flipped (v_ours = 1 - v_file) and flipped back on save.

Colour: textures and OBJ/PLY/OFF vertex colours are sRGB-coded in files and linear in Mesh; glTF
vertex colours (COLOR_0) and baseColorFactor are linear by the glTF specification.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image

from recon.errors import ReconError
from recon.io.atomic import atomic_write_bytes, atomic_write_text
from recon.io.images import (
    _pillow_pixels,
    linear_to_srgb,
    read_image,
    read_png,
    srgb_to_linear,
    write_png,
)
from recon.mesh.mesh import Mesh

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
_MATERIAL_NAME = "material_0"


def unique_rows_in_order(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact-value unique rows of rows [N, D], numbered by first occurrence.

    Returns (unique [U, D], first_index [U] into rows, inverse [N] with unique[inverse] == rows).
    Unlike np.unique alone, the order of first appearance is kept, so already-unique input
    comes back unchanged.
    """
    if rows.shape[0] == 0:
        return rows, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    _, first_index, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first_index)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    first_index = first_index[order]
    return rows[first_index], first_index, rank[inverse.reshape(-1)]


def _texture_to_rgb(image: torch.Tensor) -> torch.Tensor:
    """[h, w, C] -> [h, w, 3]: gray is repeated, alpha is dropped (Mesh albedo is RGB)."""
    if image.shape[-1] in (1, 2):
        return image[..., :1].expand(-1, -1, 3).contiguous()
    return image[..., :3].contiguous()


def load_texture_image(path: str | os.PathLike) -> torch.Tensor:
    """A texture file as linear float32 [h, w, 3] (sRGB decoded; EXR as stored; alpha dropped)."""
    return _texture_to_rgb(read_image(path))


def _texture_from_pillow(image: Image.Image) -> torch.Tensor:
    """A Pillow image (sRGB) as linear float32 [h, w, 3]."""
    pixels = _pillow_pixels(image)
    texture = torch.from_numpy(pixels.astype(np.float32) / float(np.iinfo(pixels.dtype).max))
    return srgb_to_linear(_texture_to_rgb(texture))


def _is_placeholder_image(image: Image.Image) -> bool:
    """Whether image is the 2x2 gray texture trimesh invents for UVs without a material."""
    placeholder = np.asarray(trimesh.visual.material.color_image())
    pixels = np.asarray(image)
    return pixels.shape == placeholder.shape and bool(np.array_equal(pixels, placeholder))


def _obj_texture_path(path: Path) -> Path | None:
    """The diffuse texture (map_Kd) of the materials an OBJ uses, from its MTL files.

    Missing MTL or texture files only warn (the geometry is still usable); an OBJ whose used
    materials name several different textures raises ReconError, as a Mesh holds one texture.
    """
    library_names, used_materials = [], set()
    with open(path, encoding="utf-8", errors="replace") as obj_file:
        for line in obj_file:
            if line.startswith("mtllib"):
                library_names.append(line[len("mtllib") :].strip())
            elif line.startswith("usemtl"):
                used_materials.add(line[len("usemtl") :].strip())
    textures: dict[str, Path] = {}
    for library_name in library_names:
        library_path = path.parent / library_name
        if not library_path.is_file():
            warnings.warn(
                f"{path}: material library {library_path} not found; no texture", stacklevel=3
            )
            continue
        material = None
        with open(library_path, encoding="utf-8", errors="replace") as library:
            for line in library:
                tokens = line.split()
                if not tokens:
                    continue
                if tokens[0] == "newmtl":
                    material = " ".join(tokens[1:])
                elif tokens[0] == "map_Kd" and len(tokens) > 1 and material is not None:
                    # Options such as `-s 1 1 1` may precede the file name, which comes last.
                    textures[material] = library_path.parent / tokens[-1]
    if used_materials:
        textures = {name: file for name, file in textures.items() if name in used_materials}
    distinct = sorted({str(file) for file in textures.values()})
    if len(distinct) > 1:
        raise ReconError(
            f"{path}: its materials use {len(distinct)} textures ({', '.join(distinct)}); a Mesh "
            "holds one texture (bake them into one atlas first)"
        )
    if not distinct:
        return None
    texture_path = Path(distinct[0])
    if not texture_path.is_file():
        warnings.warn(
            f"{path}: texture {texture_path} (map_Kd) not found; no texture", stacklevel=3
        )
        return None
    return texture_path


# Formats that are text only: a binary file with one of these names is a wrong file (trimesh
# would otherwise fail deep inside its encoding detection).
TEXT_MESH_SUFFIXES = (".obj", ".off")


def _check_text_file(path: Path) -> None:
    """Raise ReconError unless the file's first 64 KiB look like text (no NUL, UTF-8/Latin-1)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(65536)
    except OSError as error:
        raise ReconError(f"{path}: cannot read ({error.strerror})") from error
    if b"\0" in head:
        offset = head.index(b"\0")
        raise ReconError(
            f"{path}: expected a text {path.suffix.lower()[1:].upper()} file, found binary data "
            f"(a NUL byte at offset {offset}); is this the right file?"
        )


def load_mesh(path: str | os.PathLike, texture_path: str | os.PathLike | None = None) -> Mesh:
    """Load an OBJ / PLY / GLB / glTF / OFF / STL file as a Mesh (float32 / int64 on the CPU).

    verts [V, 3] are merged by exact position across UV seams; uvs [T, 2] (v = 0 at the top of the
    image) index through uv_faces [F, 3]; texture [h, w, 3] is linear, taken from texture_path
    when given, else from the OBJ's MTL map_Kd or the GLB/PLY material; vertex_colors [V, 3] (or
    [V, 4] when some alpha is below 1) are linear. Raises ReconError naming the path when the file
    is missing, unreadable or has no triangles.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ReconError(f"{path}: mesh file not found")
    if suffix not in MESH_SUFFIXES:
        raise ReconError(
            f"{path}: unsupported mesh format {suffix!r} (expected one of {MESH_SUFFIXES})"
        )
    if suffix in TEXT_MESH_SUFFIXES:
        _check_text_file(path)
    # For OBJ we read the MTL ourselves: trimesh would decode every texture with Pillow (8 bits
    # only) and invents a 2x2 gray placeholder texture for OBJs that have UVs but no material.
    options = {"skip_materials": True} if suffix == ".obj" else {}
    try:
        loaded = trimesh.load(path, process=False, force="mesh", **options)
    except Exception as error:  # trimesh raises many exception types for malformed files
        raise ReconError(f"{path}: cannot load mesh ({type(error).__name__}: {error})") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ReconError(f"{path}: expected a triangle mesh, found no faces")

    split_positions = np.asarray(loaded.vertices, dtype=np.float64)
    split_faces = np.asarray(loaded.faces, dtype=np.int64)
    positions, first_index, position_of_split = unique_rows_in_order(split_positions)
    faces = position_of_split[split_faces]

    uvs = uv_faces = None
    visual = loaded.visual
    split_uvs = getattr(visual, "uv", None) if visual.kind == "texture" else None
    if split_uvs is not None and len(split_uvs) == len(split_positions):
        flipped = np.asarray(split_uvs, dtype=np.float64).copy()
        flipped[:, 1] = 1.0 - flipped[:, 1]
        unique_uvs, _, uv_of_split = unique_rows_in_order(flipped)
        uvs = torch.from_numpy(unique_uvs.astype(np.float32))
        uv_faces = torch.from_numpy(uv_of_split[split_faces])

    colours_are_srgb = suffix not in (".glb", ".gltf")
    texture = None
    base_colour = None
    if texture_path is not None:
        texture = load_texture_image(texture_path)
    elif suffix == ".obj":
        found = _obj_texture_path(path)
        texture = None if found is None else load_texture_image(found)
    elif visual.kind == "texture" and visual.material is not None:
        material = visual.material
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        if image is not None and not _is_placeholder_image(image):
            texture = _texture_from_pillow(image)
        factor = getattr(material, "baseColorFactor", None)
        if factor is not None:
            base_colour = np.asarray(factor, dtype=np.float32)[:3] / 255.0
    if texture is not None and base_colour is not None:
        texture = texture * torch.from_numpy(base_colour)

    vertex_colours = None
    if visual.kind == "vertex":
        split_colours = np.asarray(visual.vertex_colors, dtype=np.float32) / 255.0
    elif "color" in loaded.vertex_attributes:
        split_colours = np.asarray(loaded.vertex_attributes["color"], dtype=np.float32)
        if split_colours.max(initial=0.0) > 1.0:  # stored as 0..255
            split_colours = split_colours / 255.0
    elif texture is None and base_colour is not None:
        split_colours = np.broadcast_to(base_colour, (len(split_positions), 3))
        colours_are_srgb = False
    else:
        split_colours = None
    if split_colours is not None:
        colours = torch.from_numpy(
            np.ascontiguousarray(split_colours[first_index], dtype=np.float32)
        )
        if colours.shape[-1] == 4 and bool((colours[:, 3] >= 1.0).all()):
            colours = colours[:, :3]
        if colours_are_srgb:
            colours[:, :3] = srgb_to_linear(colours[:, :3])
        vertex_colours = colours

    return Mesh(
        verts=torch.from_numpy(positions.astype(np.float32)),
        faces=torch.from_numpy(faces),
        uvs=uvs,
        uv_faces=uv_faces,
        vertex_colors=vertex_colours,
        texture=texture,
    )


def _format_rows(line_format: str, rows: np.ndarray) -> list[str]:
    return [line_format % tuple(row) for row in rows.tolist()]


def _save_obj(
    path: Path, mesh: Mesh, texture_bits: int, material_maps: torch.Tensor | None = None
) -> None:
    """OBJ (+ STEM.mtl and STEM_texture.png when textured; + STEM_roughness.png and
    STEM_metallic.png as map_Pr / map_Pm, the MTL's PBR extension, and both packed in
    STEM_orm.png (map_ORM, orm_texture), with material_maps). The
    textures and MTL are written first, so the OBJ never names a file that does not exist yet."""
    verts = mesh.verts.detach().cpu().double().numpy()
    faces = mesh.faces.detach().cpu().numpy() + 1  # OBJ indices start at 1
    lines = ["# written by recon.io.save_mesh"]
    if mesh.texture is not None:
        texture_name = f"{path.stem}_texture.png"
        write_png(path.parent / texture_name, mesh.texture, bits=texture_bits)
        pbr_lines = ""
        if material_maps is not None:
            maps = material_maps.detach().cpu().float()
            for channel, (key, suffix) in enumerate((("Pr", "roughness"), ("Pm", "metallic"))):
                name = f"{path.stem}_{suffix}.png"
                # Roughness and metalness are data, not colour: stored linearly.
                write_png(
                    path.parent / name,
                    maps[..., channel : channel + 1],
                    bits=texture_bits,
                    encode_srgb=False,
                )
                pbr_lines += f"{key} 1\nmap_{key} {name}\n"
            # The same maps packed as one ORM texture in glTF's channel order (R occlusion, 1:
            # not fitted; G roughness; B metalness), for engines that take packed maps. No MTL
            # key for it is standard: map_ORM is recon's, which other readers skip
            # (docs/decisions/0195-material-evaluation-orm.md).
            name = f"{path.stem}_orm.png"
            write_png(path.parent / name, orm_texture(maps), bits=texture_bits, encode_srgb=False)
            pbr_lines += f"map_ORM {name}\n"
            if maps.shape[-1] == 5:
                # A tangent-space normal map (+y up in the image), coded (n + 1) / 2 as usual.
                name = f"{path.stem}_normal.png"
                write_png(
                    path.parent / name,
                    (maps[..., 2:5].clamp(-1, 1) + 1) / 2,
                    bits=texture_bits,
                    encode_srgb=False,
                )
                # `norm` is the MTL PBR extension's key; map_Bump is what most importers read.
                pbr_lines += f"norm {name}\nmap_Bump {name}\n"
        atomic_write_text(
            path.parent / f"{path.stem}.mtl",
            f"newmtl {_MATERIAL_NAME}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
            f"map_Kd {texture_name}\n{pbr_lines}",
        )
        lines.append(f"mtllib {path.stem}.mtl")
    # %.9g round-trips float32 exactly; colours are sRGB-coded like textures.
    if mesh.vertex_colors is not None:
        colours = linear_to_srgb(mesh.vertex_colors.detach().cpu().float()[:, :3].clamp(0, 1))
        rows = np.concatenate([verts, colours.double().numpy()], axis=1)
        lines += _format_rows("v %.9g %.9g %.9g %.9g %.9g %.9g", rows)
    else:
        lines += _format_rows("v %.9g %.9g %.9g", verts)
    if mesh.uvs is not None:
        uvs = mesh.uvs.detach().cpu().double().numpy().copy()
        # 1 - v is exact in float64 for float32 v in [0, 1], so the load flips back bit-exactly.
        uvs[:, 1] = 1.0 - uvs[:, 1]
        lines += _format_rows("vt %.17g %.17g", uvs)
        if mesh.texture is not None:
            lines.append(f"usemtl {_MATERIAL_NAME}")
        uv_faces = mesh.uv_faces.detach().cpu().numpy() + 1
        corners = np.stack([faces, uv_faces], axis=-1).reshape(-1, 6)
        lines += _format_rows("f %d/%d %d/%d %d/%d", corners)
    else:
        lines += _format_rows("f %d %d %d", faces)
    atomic_write_text(path, "\n".join(lines) + "\n")


def orm_texture(material_maps: torch.Tensor) -> torch.Tensor:
    """[h, w, 3] ORM texture (occlusion, roughness, metalness; glTF's channel order, linear) of
    material maps [h, w, >= 2] (roughness, metalness): occlusion is 1 (recon fits none)."""
    maps = material_maps.detach().cpu().float()[..., :2].clamp(0, 1)
    return torch.cat([torch.ones_like(maps[..., :1]), maps], dim=-1)


def _save_glb(path: Path, mesh: Mesh, material_maps: torch.Tensor | None = None) -> None:
    """Binary glTF. glTF has one UV per vertex, so vertices are split where a position is used
    with several UVs; the texture (sRGB PNG inside the GLB) wins over vertex colours.
    material_maps [h, w, 2] (roughness, metalness) become the metallic-roughness texture
    (glTF: green = roughness, blue = metalness, linear; red holds occlusion 1, which glTF
    ignores there, so the image is orm_texture's)."""
    verts = mesh.verts.detach().cpu().float().numpy()
    faces = mesh.faces.detach().cpu().numpy()
    if mesh.uvs is not None:
        corner_pairs = np.stack(
            [faces.reshape(-1), mesh.uv_faces.detach().cpu().numpy().reshape(-1)], 1
        )
        pairs, _, corner_vertex = unique_rows_in_order(corner_pairs)
        # Order the split vertices by position index so that load_mesh's first-occurrence merge
        # gives back the original vertex order (and so identical faces).
        order = np.argsort(pairs[:, 0], kind="stable")
        renumber = np.empty_like(order)
        renumber[order] = np.arange(order.shape[0])
        pairs, corner_vertex = pairs[order], renumber[corner_vertex]
        uvs = mesh.uvs.detach().cpu().double().numpy()[pairs[:, 1]]
        uvs[:, 1] = 1.0 - uvs[:, 1]  # trimesh takes bottom-up UVs and flips them for glTF
        material = None
        if mesh.texture is not None:
            texture = mesh.texture.detach().cpu().float().clamp(0, 1)
            colour = 1 if texture.shape[-1] in (1, 2) else 3
            texture[..., :colour] = linear_to_srgb(texture[..., :colour])
            pixels = torch.round(texture * 255).numpy().astype(np.uint8)
            image = Image.fromarray(pixels[..., 0] if pixels.shape[-1] == 1 else pixels)
            pbr_maps = {"metallicFactor": 0.0, "roughnessFactor": 1.0}
            if material_maps is not None:
                maps = material_maps.detach().cpu().float()
                # glTF reads G and B only; R holds occlusion 1 so the image is the OBJ's ORM.
                packed = np.round(orm_texture(maps).numpy() * 255).astype(np.uint8)
                pbr_maps = {
                    "metallicFactor": 1.0,
                    "roughnessFactor": 1.0,
                    "metallicRoughnessTexture": Image.fromarray(packed),
                }
                if material_maps.shape[-1] == 5:
                    coded = (material_maps.detach().cpu().float()[..., 2:5].clamp(-1, 1) + 1) / 2
                    normal_pixels = np.round(coded.numpy() * 255).astype(np.uint8)
                    pbr_maps["normalTexture"] = Image.fromarray(normal_pixels)
            material = trimesh.visual.material.PBRMaterial(
                name=_MATERIAL_NAME, baseColorTexture=image, **pbr_maps
            )
        visual = trimesh.visual.TextureVisuals(uv=uvs, material=material)
        result = trimesh.Trimesh(
            verts[pairs[:, 0]], corner_vertex.reshape(-1, 3), visual=visual, process=False
        )
    else:
        colours = None
        if mesh.vertex_colors is not None:
            linear = mesh.vertex_colors.detach().cpu().float().clamp(0, 1).numpy()
            colours = np.round(linear * 255).astype(np.uint8)
        result = trimesh.Trimesh(verts, faces, vertex_colors=colours, process=False)
    atomic_write_bytes(path, result.export(file_type="glb"))


def save_mesh(
    path: str | os.PathLike,
    mesh: Mesh,
    texture_bits: int = 8,
    material_maps: torch.Tensor | None = None,
) -> None:
    """Write a Mesh as OBJ (with MTL and STEM_texture.png when textured) or GLB, atomically.

    OBJ keeps the shared positions and the separate UV indices (`f v/vt`), flips v back to OBJ's
    bottom-up convention and writes vertex colours as sRGB `v x y z r g b`. GLB splits vertices at
    UV seams (glTF has one index buffer). texture_bits (8 or 16) is the OBJ texture PNG depth.
    material_maps: [h, w, 2] roughness and metalness on the texture's UVs (the `pbr` material;
    needs mesh.texture as base colour): OBJ map_Pr / map_Pm and the packed map_ORM, GLB
    metallicRoughnessTexture;
    [h, w, 5] adds a tangent-space normal map (x, y, z in [-1, 1]): OBJ norm / map_Bump, GLB
    normalTexture.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if material_maps is not None and (
        mesh.texture is None or material_maps.ndim != 3 or material_maps.shape[-1] not in (2, 5)
    ):
        raise ReconError(
            f"{path}: material_maps: expected [h, w, 2] (roughness, metalness) or [h, w, 5] "
            "(+ a tangent-space normal map) with a textured mesh, got "
            f"{tuple(material_maps.shape)} (texture: {mesh.texture is not None})"
        )
    if suffix == ".obj":
        _save_obj(path, mesh, texture_bits, material_maps)
    elif suffix == ".glb":
        _save_glb(path, mesh, material_maps)
    else:
        raise ReconError(f"{path}: save_mesh writes .obj or .glb, got {suffix!r}")


def load_material_maps(path: str | os.PathLike) -> torch.Tensor | None:
    """Roughness and metalness [h, w, 2] (float32, linear) that save_mesh wrote with
    material_maps: OBJ's map_Pr / map_Pm, GLB's metallicRoughnessTexture (green, blue); [h, w, 5]
    with the tangent-space normal map (OBJ's norm, GLB's normalTexture) after them. None when
    the file has none."""
    path = Path(path)
    if path.suffix.lower() == ".glb":
        scene = trimesh.load(path, force="scene")
        for geometry in scene.geometry.values():
            material = getattr(geometry.visual, "material", None)
            image = getattr(material, "metallicRoughnessTexture", None)
            if image is not None:
                pixels = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
                maps = torch.from_numpy(pixels[..., 1:3].copy())
                normal = getattr(material, "normalTexture", None)
                if normal is not None:
                    coded = np.asarray(normal.convert("RGB"), dtype=np.float32) / 255.0
                    maps = torch.cat([maps, torch.from_numpy(coded * 2 - 1)], dim=-1)
                return maps
        return None
    maps: dict[str, Path] = {}
    library = path.with_suffix(".mtl")
    if not library.is_file():
        return None
    for line in library.read_text(encoding="utf-8", errors="replace").splitlines():
        tokens = line.split()
        if len(tokens) > 1 and tokens[0] in ("map_Pr", "map_Pm", "norm"):
            maps[tokens[0]] = library.parent / tokens[-1]
    if not {"map_Pr", "map_Pm"} <= set(maps):
        return None
    channels = [read_png(maps[key], decode_srgb=False)[..., :1] for key in ("map_Pr", "map_Pm")]
    if "norm" in maps:
        channels.append(read_png(maps["norm"], decode_srgb=False)[..., :3] * 2 - 1)
    return torch.cat(channels, dim=-1).float()
