"""The Mesh dataclass: geometry shared by index, UVs on their own index buffer."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from recon.errors import ReconError


@dataclass
class Mesh:
    """A triangle mesh.

    verts: [V, 3] float32 positions, shared by index across UV seams (so the topology is whole).
    faces: [F, 3] int64, counter-clockwise seen from outside = front.
    uvs: [T, 2] float32 texture coordinates or None; (0, 0) is the top-left corner of the
        texture image, v grows downwards (OBJ's v is flipped on load and on save).
    uv_faces: [F, 3] int64 indices into uvs, same triangle order as faces, or None.
    vertex_colors: [V, C] float32 linear albedo per vertex, or None.
    texture: [h, w, C] float32 linear albedo texture, or None.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    uvs: torch.Tensor | None = None
    uv_faces: torch.Tensor | None = None
    vertex_colors: torch.Tensor | None = None
    texture: torch.Tensor | None = None

    def __post_init__(self) -> None:
        validate_mesh_tensors(self.verts, self.faces, name="mesh")
        if (self.uvs is None) != (self.uv_faces is None):
            raise ReconError("mesh: uvs and uv_faces must be given together")
        if self.uv_faces is not None:
            if self.uv_faces.shape != self.faces.shape:
                raise ReconError(
                    f"mesh.uv_faces: expected shape {tuple(self.faces.shape)} (like faces), "
                    f"got {tuple(self.uv_faces.shape)}"
                )
            if self.uv_faces.numel() and int(self.uv_faces.max()) >= self.uvs.shape[0]:
                raise ReconError(
                    f"mesh.uv_faces: index {int(self.uv_faces.max())} out of range for "
                    f"{self.uvs.shape[0]} uvs"
                )

    @property
    def device(self) -> torch.device:
        return self.verts.device

    def to(self, device: torch.device | str) -> Mesh:
        def move(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device)

        return replace(
            self,
            verts=self.verts.to(device),
            faces=self.faces.to(device),
            uvs=move(self.uvs),
            uv_faces=move(self.uv_faces),
            vertex_colors=move(self.vertex_colors),
            texture=move(self.texture),
        )


def validate_mesh_tensors(verts: torch.Tensor, faces: torch.Tensor, name: str = "mesh") -> None:
    """Raise ReconError unless verts is [V,3] float finite and faces is [F,3] int64 in range."""
    if not isinstance(verts, torch.Tensor) or verts.ndim != 2 or verts.shape[-1] != 3:
        shape = tuple(verts.shape) if isinstance(verts, torch.Tensor) else type(verts).__name__
        raise ReconError(f"{name}.verts: expected shape [V, 3], got {shape}")
    if not verts.is_floating_point():
        raise ReconError(f"{name}.verts: expected a float tensor, got {verts.dtype}")
    if not isinstance(faces, torch.Tensor) or faces.ndim != 2 or faces.shape[-1] != 3:
        shape = tuple(faces.shape) if isinstance(faces, torch.Tensor) else type(faces).__name__
        raise ReconError(f"{name}.faces: expected shape [F, 3], got {shape}")
    if faces.dtype not in (torch.int64, torch.int32):
        raise ReconError(f"{name}.faces: expected int64 indices, got {faces.dtype}")
    if not bool(torch.isfinite(verts).all()):
        raise ReconError(f"{name}.verts: contains NaN or inf")
    if faces.numel():
        low, high = int(faces.min()), int(faces.max())
        if low < 0 or high >= verts.shape[0]:
            raise ReconError(
                f"{name}.faces: indices must lie in [0, {verts.shape[0] - 1}], "
                f"got range [{low}, {high}]"
            )


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals.

    verts: [V, 3] or [B, V, 3]; faces: [F, 3]. Returns unit normals of the same shape as verts.
    Differentiable; vertices with no face get (0, 0, 0) normalised safely to zero.
    """
    corners = verts[..., faces, :]  # [..., F, 3, 3]
    face_normals = torch.linalg.cross(
        corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :], dim=-1
    )  # length = 2 * area, so the sum below is area-weighted
    normals = torch.zeros_like(verts)
    for corner in range(3):
        normals = normals.index_add(-2, faces[:, corner], face_normals)
    return torch.nn.functional.normalize(normals, dim=-1, eps=1e-20)


def uv_tangents(
    verts: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, uv_faces: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent frames of a UV-mapped mesh for tangent-space normal maps, per UV vertex.

    verts: [V, 3]; faces, uv_faces: [F, 3]; uvs: [T, 2] (recon's convention: v grows
    downwards). Returns (tangents, bitangents), each [T, 3], not normalised: the sums over the
    faces around each UV vertex of dP/du and dP/dv_up (v_up = 1 - v, so a map's +y points up
    in the image, the convention of glTF and most tools). Degenerate UV triangles add nothing.
    Differentiable in verts.
    """
    corners = verts[faces]  # [F, 3, 3]
    coordinates = uvs[uv_faces].to(verts.dtype)  # [F, 3, 2]
    edge_one, edge_two = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    du_one = coordinates[:, 1, 0] - coordinates[:, 0, 0]
    du_two = coordinates[:, 2, 0] - coordinates[:, 0, 0]
    # v_up = 1 - v: its differences are the negated v differences.
    dv_one = coordinates[:, 0, 1] - coordinates[:, 1, 1]
    dv_two = coordinates[:, 0, 1] - coordinates[:, 2, 1]
    determinant = du_one * dv_two - du_two * dv_one
    valid = determinant.abs() > 1e-12
    safe = torch.where(valid, determinant, torch.ones_like(determinant))
    scale = torch.where(valid, 1 / safe, torch.zeros_like(determinant))[:, None]
    face_tangents = (edge_one * dv_two[:, None] - edge_two * dv_one[:, None]) * scale
    face_bitangents = (edge_two * du_one[:, None] - edge_one * du_two[:, None]) * scale
    # Weight each face by its area so that slivers do not dominate a vertex's frame.
    area = torch.linalg.cross(edge_one, edge_two, dim=-1).norm(dim=-1, keepdim=True)
    face_tangents = torch.nn.functional.normalize(face_tangents, dim=-1, eps=1e-20) * area
    face_bitangents = torch.nn.functional.normalize(face_bitangents, dim=-1, eps=1e-20) * area
    tangents = verts.new_zeros(uvs.shape[0], 3)
    bitangents = verts.new_zeros(uvs.shape[0], 3)
    for corner in range(3):
        tangents = tangents.index_add(0, uv_faces[:, corner], face_tangents)
        bitangents = bitangents.index_add(0, uv_faces[:, corner], face_bitangents)
    return tangents, bitangents


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals [..., F, 3] for verts [..., V, 3]."""
    corners = verts[..., faces, :]
    normals = torch.linalg.cross(
        corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :], dim=-1
    )
    return torch.nn.functional.normalize(normals, dim=-1, eps=1e-20)
