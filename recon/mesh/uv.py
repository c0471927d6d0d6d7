"""UV layouts: unwrapping with xatlas, rasterizing in UV space, baking and dilating textures.

Conventions (those of Mesh and recon.render.texture):

- uvs [T, 2]: (u, v) with (0, 0) at the top-left corner of the texture image; u runs along the
  columns, v down the rows. Texel (row i, column j) of an [h, w] texture has its centre at
  u = (j + 0.5) / w, v = (i + 0.5) / h.
- uv_faces [F, 3] index uvs in the same triangle order as faces, so a mesh keeps its positions
  shared by index and only the UVs are split at chart seams.

xatlas's conventions (xatlas 0.0.11, checked in tests/mesh/test_uv.py):

- Its output uvs are texel positions divided by the atlas width and height, and its own atlas
  image (PackOptions.create_image) stores texel row y = v * height from the top: v grows
  downwards there as here, so its uvs are used unchanged. (xatlas.export writes them to OBJ
  as they are, where v is up; recon.io flips v for OBJ itself.)
- atlas[0] returns (vmapping [T], indices [F, 3], uvs [T, 2]): one output triangle per input
  triangle, in input order with the input corner order, so vmapping[indices] == faces and
  indices are uv_faces as they stand. unwrap checks this on every call.
- With PackOptions.resolution alone the atlas only approximates that size (1146 x 1197 for
  1024); with texels_per_unit set too, atlases are exactly resolution x resolution and charts
  that do not fit spill into a second atlas (see _pack_into_one_atlas).
- It has no seed and is deterministic: the same input gives the same layout.

This module imports nothing of recon.render or recon.io (mesh sits below them), so the
UV-space rasterizer here is its own small one.
"""

from __future__ import annotations

import math
import os
import pickle
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from recon.errors import ReconError
from recon.mesh.mesh import Mesh

# Fixed-point sub-texel precision of the UV rasterizer: positions are snapped to 1/256 texel so
# that edge functions are exact integers. Exactness is what makes the fill rule below assign a
# texel centre on an edge (or vertex) shared by several triangles to exactly one of them.
SUBTEXEL_BITS = 8
_SUBTEXEL = 1 << SUBTEXEL_BITS
# Largest |u| * w or |v| * h the rasterizer takes (see _check_layout).
_MAX_TEXEL_COORDINATE = 1 << 15
# Candidate (triangle, texel) pairs tested per chunk: bounds peak memory (~100 bytes each).
DEFAULT_CHUNK_CANDIDATES = 1 << 21
# Packing retries: each shrinks the texel density by this factor until one atlas holds every
# chart.
_SHRINK_PER_RETRY = 0.98
_MAX_PACK_ATTEMPTS = 12


def unwrap(
    verts: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    resolution: int = 1024,
    padding: int = 2,
    seed: int | None = None,
    max_iterations: int = 1,
    brute_force: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Compute a UV layout for a mesh with xatlas, packed into one resolution x resolution atlas.

    verts: [V, 3] float positions; faces: [F, 3] int vertex indices (torch or numpy).
    resolution: side of the square texture the layout is made for, in texels.
    padding: empty texels kept between charts at that resolution (xatlas also leaves room for
        bilinear taps around each chart). Baking at a lower resolution shrinks it.
    seed: accepted for symmetry with the pipeline's seeded steps; xatlas has no random seed
        and is deterministic (same input, same layout), so it changes nothing.
    max_iterations: xatlas ChartOptions.max_iterations (chart growing iterations; 1 is the
        fast default, more gives slightly rounder charts).
    brute_force: xatlas PackOptions.bruteForce (tighter packing, much slower).
    Returns uvs [T, 2] float32 in [0, 1] (v down, see the module docstring) and uv_faces
    [F, 3] int64 into uvs, in the same triangle order as faces, on verts' device when verts is
    a tensor (else on the CPU). verts and faces are not changed: positions stay shared by
    index, and a vertex on a seam has one uv per chart.
    """
    import xatlas  # imported here so that modules using only the rasterizer need no xatlas

    del seed  # xatlas is deterministic; see the docstring
    device = verts.device if isinstance(verts, torch.Tensor) else torch.device("cpu")
    positions = _as_numpy(verts, np.float32, "verts")
    indices = _as_numpy(faces, np.int64, "faces")
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ReconError(f"unwrap: verts: expected shape [V, 3], got {positions.shape}")
    if indices.ndim != 2 or indices.shape[1] != 3 or indices.shape[0] == 0:
        raise ReconError(f"unwrap: faces: expected shape [F, 3] with F > 0, got {indices.shape}")
    if not np.isfinite(positions).all():
        raise ReconError("unwrap: verts: contains NaN or inf")
    if indices.min() < 0 or indices.max() >= positions.shape[0]:
        raise ReconError(
            f"unwrap: faces: indices must lie in [0, {positions.shape[0] - 1}], "
            f"got range [{indices.min()}, {indices.max()}]"
        )
    if int(resolution) < 16 or int(padding) < 0:
        raise ReconError(
            f"unwrap: expected resolution >= 16 and padding >= 0, got {resolution}, {padding}"
        )

    chart_options = xatlas.ChartOptions()
    chart_options.max_iterations = int(max_iterations)
    pack_options = xatlas.PackOptions()
    pack_options.padding = int(padding)
    pack_options.resolution = int(resolution)
    pack_options.bruteForce = bool(brute_force)
    vertex_mapping, uv_faces, uvs = run_without_teardown(
        _pack_into_one_atlas,
        xatlas,
        positions,
        indices.astype(np.uint32),
        chart_options,
        pack_options,
    )
    uv_faces = uv_faces.astype(np.int64)
    if uv_faces.shape != indices.shape or not np.array_equal(
        vertex_mapping.astype(np.int64)[uv_faces], indices
    ):
        # uv_faces are only usable alongside the original faces if xatlas kept the triangle
        # and corner order; it does (0.0.11), and this guards against a version that does not.
        raise ReconError(
            "unwrap: xatlas returned triangles in a different order than faces; "
            "uv_faces would not line up with faces"
        )
    uvs = torch.from_numpy(np.ascontiguousarray(uvs, dtype=np.float32))
    return uvs.to(device), torch.from_numpy(uv_faces).to(device)


# Every xatlas Atlas made through new_atlas: referenced here so that none is destroyed while
# the process lives (run_without_teardown's child leaves by os._exit; see there).
_NEVER_DESTROYED: list[Any] = []


def new_atlas(xatlas_module: Any) -> Any:
    """An xatlas Atlas kept alive (never destroyed) for as long as the process runs: create
    Atlases through this inside run_without_teardown."""
    atlas = xatlas_module.Atlas()
    _NEVER_DESTROYED.append(atlas)
    return atlas


def run_without_teardown(function: Callable[..., Any], *arguments: Any) -> Any:
    """function(*arguments) in a forked child process that exits without running destructors;
    its return value (picklable) comes back, and a ReconError it raises is raised here with the
    same message.

    Why: xatlas (0.0.11) can hang for ever when an Atlas is destroyed. Its task scheduler's
    destructor sets each worker's wake-up flag and notifies the worker's condition variable
    without holding the worker's mutex, so a worker that has just found the flag unset and is
    about to block misses the notification, and the destructor's join never returns (seen under
    load: every thread asleep, the main one in std::thread::join inside xatlas::Destroy). The
    child computes the layout with Atlases made by new_atlas, which stay referenced until it
    leaves by os._exit, so none is ever destroyed (an Atlas local to the function would be freed
    when it returns, in the child too). Where there is no fork (Windows), it runs in this
    process and the Atlases are released afterwards, as before.
    """
    if not hasattr(os, "fork"):
        try:
            return function(*arguments)
        finally:
            _NEVER_DESTROYED.clear()
    read_end, write_end = os.pipe()
    child = os.fork()
    if child == 0:  # the child: compute, send, leave without teardown
        try:
            os.close(read_end)
            try:
                outcome = ("value", function(*arguments))
            except ReconError as error:
                outcome = ("recon_error", str(error))
            except BaseException as error:  # noqa: BLE001 - reported to the parent
                outcome = ("error", f"{type(error).__name__}: {error}")
            with os.fdopen(write_end, "wb") as stream:
                pickle.dump(outcome, stream, protocol=pickle.HIGHEST_PROTOCOL)
        finally:
            os._exit(0)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as stream:
        payload = stream.read()
    _, status = os.waitpid(child, 0)
    if not payload:
        raise ReconError(
            f"unwrap: the xatlas child process ended without a result (wait status {status})"
        )
    kind, value = pickle.loads(payload)
    if kind == "recon_error":
        raise ReconError(value)
    if kind == "error":
        raise RuntimeError(f"unwrap: xatlas failed in its child process: {value}")
    return value


def _pack_into_one_atlas(
    xatlas_module: Any,
    positions: np.ndarray,
    indices: np.ndarray,
    chart_options: Any,
    pack_options: Any,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Charts by xatlas, packed into exactly one resolution x resolution atlas.

    xatlas given only a resolution estimates a texel density and returns an atlas of about that
    size, rarely square (1146 x 1197 for 1024). Given a density as well, it packs into atlases
    of exactly that resolution and spills what does not fit into further atlases. Generating
    from 3D repeats the chart computation (seconds for 20k faces), so the charts of the first
    pass are repacked as a UV mesh instead (a tenth of a second): in its texel coordinates,
    with the density that keeps the atlas area, shrunk until one atlas holds every chart.
    Returns (vertex_mapping [T] into positions, uv_faces [F, 3], uvs [T, 2] in [0, 1]).
    """
    resolution = pack_options.resolution
    pack_options.texels_per_unit = 0.0
    atlas = new_atlas(xatlas_module)
    atlas.add_mesh(positions, indices)
    atlas.generate(chart_options=chart_options, pack_options=pack_options)
    vertex_mapping, chart_faces, uvs = atlas[0]
    if atlas.atlas_count == 1 and atlas.width == atlas.height == resolution:
        return vertex_mapping, chart_faces, uvs
    # Back to texel units: xatlas divides by width and height, which differ.
    texels = np.ascontiguousarray(uvs * np.array([atlas.width, atlas.height]), dtype=np.float32)
    texels_per_texel = math.sqrt(resolution * resolution / (atlas.width * atlas.height))
    for _ in range(_MAX_PACK_ATTEMPTS):
        repacked = new_atlas(xatlas_module)
        # Charts are the connected components of the UV mesh: one per chart of the first pass.
        repacked.add_uv_mesh(texels, chart_faces)
        pack_options.texels_per_unit = texels_per_texel
        repacked.generate(pack_options=pack_options)
        if repacked.atlas_count == 1:
            uv_mapping, uv_faces, uvs = repacked[0]
            if not np.array_equal(uv_mapping[uv_faces], chart_faces):
                raise ReconError("unwrap: xatlas reordered the triangles while repacking")
            return vertex_mapping[uv_mapping], uv_faces, uvs
        texels_per_texel *= _SHRINK_PER_RETRY
    raise ReconError(
        f"unwrap: xatlas could not pack the charts into one {resolution}x{resolution} atlas "
        f"after {_MAX_PACK_ATTEMPTS} attempts"
    )


def _as_numpy(array: torch.Tensor | np.ndarray, dtype: type, name: str) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    if not isinstance(array, np.ndarray):
        raise ReconError(f"unwrap: {name}: expected a tensor or array, got {type(array).__name__}")
    return np.ascontiguousarray(array, dtype=dtype)


def _check_layout(
    uvs: torch.Tensor, uv_faces: torch.Tensor, texture_size: tuple[int, int], caller: str
) -> tuple[int, int]:
    if not isinstance(uvs, torch.Tensor) or uvs.ndim != 2 or uvs.shape[-1] != 2:
        shape = tuple(uvs.shape) if isinstance(uvs, torch.Tensor) else type(uvs).__name__
        raise ReconError(f"{caller}: uvs: expected shape [T, 2], got {shape}")
    if not isinstance(uv_faces, torch.Tensor) or uv_faces.ndim != 2 or uv_faces.shape[-1] != 3:
        shape = tuple(uv_faces.shape) if isinstance(uv_faces, torch.Tensor) else type(uv_faces)
        raise ReconError(f"{caller}: uv_faces: expected shape [F, 3], got {shape}")
    if uv_faces.numel() and (int(uv_faces.min()) < 0 or int(uv_faces.max()) >= uvs.shape[0]):
        raise ReconError(
            f"{caller}: uv_faces: indices must lie in [0, {uvs.shape[0] - 1}], "
            f"got range [{int(uv_faces.min())}, {int(uv_faces.max())}]"
        )
    if not bool(torch.isfinite(uvs).all()):
        raise ReconError(f"{caller}: uvs: contains NaN or inf")
    if len(texture_size) != 2 or int(texture_size[0]) <= 0 or int(texture_size[1]) <= 0:
        raise ReconError(f"{caller}: texture_size: expected positive (h, w), got {texture_size}")
    height, width = int(texture_size[0]), int(texture_size[1])
    # Keeps fixed-point positions below 2^23, so the int64 edge values stay below 2^50.
    if uvs.numel() and float(uvs.detach().abs().max()) * max(height, width) > _MAX_TEXEL_COORDINATE:
        raise ReconError(
            f"{caller}: uvs: |u|, |v| times the texture size must stay below "
            f"{_MAX_TEXEL_COORDINATE}, got {float(uvs.detach().abs().max())} for {texture_size}"
        )
    return height, width


def _edge_coefficients(
    uvs: torch.Tensor, uv_faces: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact integer edge functions of every UV triangle, in fixed-point texel units.

    Positions are x = u * width, y = v * height snapped to 1/_SUBTEXEL texel. Edge k (opposite
    corner k, from corner k + 1 to corner k + 2) is e_k(p) = A_k p_x + B_k p_y + C_k, scaled so
    that e_k is positive inside: e_k / (e_0 + e_1 + e_2) is the barycentric of corner k.
    Returns coefficients [F, 3, 3] int64 ((A, B, C) per edge), doubled areas [F] int64 (>= 0;
    0 for degenerate triangles) and the fixed-point corners [F, 3, 2] int64.
    """
    scale = torch.tensor([width, height], dtype=torch.float64, device=uvs.device) * _SUBTEXEL
    fixed = torch.round(uvs.to(torch.float64) * scale).to(torch.int64)
    corners = fixed[uv_faces]  # [F, 3, 2]
    x, y = corners[..., 0], corners[..., 1]
    i_index = [1, 2, 0]
    j_index = [2, 0, 1]
    xi, yi, xj, yj = x[:, i_index], y[:, i_index], x[:, j_index], y[:, j_index]
    coefficients = torch.stack([yi - yj, xj - xi, xi * yj - xj * yi], dim=-1)  # [F, 3, 3]
    doubled_area = coefficients[..., 2].sum(-1)  # e_0 + e_1 + e_2 is constant: 2 * signed area
    # Orient every triangle positively (charts may be mirrored): inside is then all e_k >= 0.
    orientation = torch.where(doubled_area < 0, -1, 1)
    coefficients = coefficients * orientation[:, None, None]
    return coefficients, doubled_area.abs(), corners


def _texel_bounds(corners: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Inclusive texel index ranges [F, 4] = (column0, column1, row0, row1) whose centres lie
    in each triangle's bounding box, clamped to the texture (empty when column1 < column0)."""
    half = _SUBTEXEL // 2
    low = corners.amin(dim=1) - half  # [F, 2]
    high = corners.amax(dim=1) - half
    # Centre j * S + S / 2 inside [low', high'] <=> ceil(low / S) <= j <= floor(high / S).
    first = -torch.div(-low, _SUBTEXEL, rounding_mode="floor")
    last = torch.div(high, _SUBTEXEL, rounding_mode="floor")
    column0 = first[:, 0].clamp(0, width)
    column1 = last[:, 0].clamp(-1, width - 1)
    row0 = first[:, 1].clamp(0, height)
    row1 = last[:, 1].clamp(-1, height - 1)
    return torch.stack([column0, column1, row0, row1], dim=-1)


def _covered_candidates(
    uvs: torch.Tensor,
    uv_faces: torch.Tensor,
    height: int,
    width: int,
    chunk_candidates: int = DEFAULT_CHUNK_CANDIDATES,
) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Yield (face [N] int64, texel [N] int64 = row * width + column) for every texel centre
    covered by a UV triangle, in chunks.

    A centre exactly on an edge goes to the triangle it is inside after an infinitesimal shift
    (+eps, +eps^2): with e_k = 0 it is inside iff A_k > 0, or A_k = 0 and B_k > 0. With exact
    integer edges this gives a centre on an edge or vertex shared by non-overlapping triangles
    to exactly one of them, so a coverage count above 1 means real overlap.

    Triangles are bucketed by their texel box rounded up to powers of two, so each bucket is a
    dense [triangles, box rows, box columns] broadcast with no per-texel loop. Over a box, edge
    k is affine: e_k = (base_k + A_k S column_offset) + B_k S row_offset, a sum of a
    [M, 1, columns] and a [M, rows, 1] term, so each edge costs one full-size add; columns and
    rows past the triangle's box get a large negative term and so fail the test for free.
    """
    coefficients, doubled_area, corners = _edge_coefficients(uvs, uv_faces, height, width)
    bounds = _texel_bounds(corners, height, width)
    box_width = (bounds[:, 1] - bounds[:, 0] + 1).clamp_min(0)
    box_height = (bounds[:, 3] - bounds[:, 2] + 1).clamp_min(0)
    usable = torch.nonzero((doubled_area > 0) & (box_width > 0) & (box_height > 0)).squeeze(1)
    if usable.numel() == 0:
        return
    width_log = torch.ceil(torch.log2(box_width[usable].double())).long()
    height_log = torch.ceil(torch.log2(box_height[usable].double())).long()
    bucket = width_log * 64 + height_log
    order = torch.argsort(bucket, stable=True)
    unique_buckets, counts = torch.unique_consecutive(bucket[order], return_counts=True)

    a, b, c = coefficients.unbind(-1)  # [F, 3] each
    # Integer e: "e > 0, or e == 0 and the tie goes inside" is e + tie > 0.
    tie = ((a > 0) | ((a == 0) & (b > 0))).to(torch.int64)
    half = _SUBTEXEL // 2
    origin_x = (bounds[:, 0] * _SUBTEXEL + half)[:, None]  # centre of the box's first texel
    origin_y = (bounds[:, 2] * _SUBTEXEL + half)[:, None]
    base = a * origin_x + b * origin_y + c + tie  # [F, 3]: e_k + tie at the box origin
    step_x = a * _SUBTEXEL  # [F, 3]: change of e_k per texel to the right
    step_y = b * _SUBTEXEL
    # Edge values stay below 2^50 (_check_layout bounds the positions); this dominates them,
    # and twice it still fits in int64.
    outside = -(1 << 56)
    start = 0
    for bucket_value, count in zip(unique_buckets.tolist(), counts.tolist(), strict=True):
        grid_width = 1 << (bucket_value // 64)
        grid_height = 1 << (bucket_value % 64)
        members_all = usable[order[start : start + count]]
        start += count
        per_chunk = max(1, chunk_candidates // (grid_width * grid_height))
        offset_x = torch.arange(grid_width, device=uvs.device)
        offset_y = torch.arange(grid_height, device=uvs.device)
        for chunk_start in range(0, members_all.numel(), per_chunk):
            members = members_all[chunk_start : chunk_start + per_chunk]
            past_column = (offset_x > (box_width[members, None] - 1))[:, None, :]  # [M, 1, gw]
            past_row = (offset_y > (box_height[members, None] - 1))[:, :, None]  # [M, gh, 1]
            smallest = None
            buffer = None
            for k in range(3):
                column_term = base[members, k, None] + step_x[members, k, None] * offset_x
                row_term = step_y[members, k, None] * offset_y
                column_term = column_term[:, None, :].masked_fill(past_column, outside)
                row_term = row_term[:, :, None].masked_fill(past_row, outside)
                if smallest is None:
                    smallest = column_term + row_term  # [M, gh, gw]
                    buffer = torch.empty_like(smallest)
                else:
                    torch.add(column_term, row_term, out=buffer)
                    torch.minimum(smallest, buffer, out=smallest)
            member_index, row_offset, column_offset = torch.nonzero(smallest > 0, as_tuple=True)
            if member_index.numel():
                member = members[member_index]
                row = bounds[member, 2] + row_offset
                column = bounds[member, 0] + column_offset
                yield member, row * width + column


def rasterize_uv(
    uvs: torch.Tensor,
    uv_faces: torch.Tensor,
    texture_size: tuple[int, int],
    chunk_candidates: int = DEFAULT_CHUNK_CANDIDATES,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which UV triangle covers each texel centre, and where in it.

    uvs: [T, 2] float (v down, texel centres at (j + 0.5) / w, (i + 0.5) / h); uv_faces:
        [F, 3] int indices into uvs; texture_size: (h, w).
    Returns face_id [h, w] int64 (-1 where no triangle covers the centre; where triangles
    overlap, the lowest index wins) and barycentrics [h, w, 3] float32 of the centre in that
    triangle, weights of its three uv_faces corners (0 on empty texels). Degenerate triangles
    cover nothing; parts of triangles outside [0, 1]^2 are dropped, not wrapped.
    """
    height, width = _check_layout(uvs, uv_faces, texture_size, "rasterize_uv")
    uv_faces = uv_faces.to(torch.int64)
    empty = torch.iinfo(torch.int64).max
    winner = torch.full((height * width,), empty, dtype=torch.int64, device=uvs.device)
    for face, texel in _covered_candidates(uvs, uv_faces, height, width, chunk_candidates):
        winner.scatter_reduce_(0, texel, face, reduce="amin")
    covered = torch.nonzero(winner != empty).squeeze(1)
    face_id = torch.where(winner == empty, -1, winner)
    barycentrics = torch.zeros((height * width, 3), dtype=torch.float32, device=uvs.device)
    if covered.numel():
        coefficients, doubled_area, _ = _edge_coefficients(uvs, uv_faces, height, width)
        face = face_id[covered]
        point_x = (covered % width) * _SUBTEXEL + _SUBTEXEL // 2
        point_y = torch.div(covered, width, rounding_mode="floor") * _SUBTEXEL + _SUBTEXEL // 2
        c = coefficients[face]  # [N, 3, 3]
        edge = c[..., 0] * point_x[:, None] + c[..., 1] * point_y[:, None] + c[..., 2]
        # Exact integers until here; the ratio in float64 keeps 1/2^53 relative precision.
        barycentrics[covered] = (edge.double() / doubled_area[face, None].double()).float()
    return face_id.view(height, width), barycentrics.view(height, width, 3)


def uv_coverage_count(
    uvs: torch.Tensor,
    uv_faces: torch.Tensor,
    texture_size: tuple[int, int],
    chunk_candidates: int = DEFAULT_CHUNK_CANDIDATES,
) -> torch.Tensor:
    """Number of UV triangles covering each texel centre: [h, w] int64.

    Same coverage rule as rasterize_uv, under which a centre on an edge or vertex shared by
    adjacent triangles counts once: a count above 1 means charts (or triangles) overlap.
    """
    height, width = _check_layout(uvs, uv_faces, texture_size, "uv_coverage_count")
    count = torch.zeros(height * width, dtype=torch.int64, device=uvs.device)
    for _, texel in _covered_candidates(
        uvs, uv_faces.to(torch.int64), height, width, chunk_candidates
    ):
        count += torch.bincount(texel, minlength=height * width)
    return count.view(height, width)


def bake_vertex_attribute(
    mesh_or_arrays: Mesh | tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    attribute: torch.Tensor | None,
    texture_size: tuple[int, int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Interpolate a per-vertex attribute into a texture through the UV layout.

    mesh_or_arrays: a Mesh with uvs and uv_faces, or (faces [F, 3], uvs [T, 2],
        uv_faces [F, 3]).
    attribute: [V, C] float per vertex (indexed by faces), e.g. albedo; None takes the
        Mesh's vertex_colors.
    texture_size: (h, w); bake at the resolution the layout was unwrapped for, or the padding
        between charts shrinks.
    Returns texture [h, w, C] (attribute's dtype; at each covered texel centre, the
    barycentric blend of attribute[faces] of the triangle covering it, else 0) and coverage
    [h, w] bool. Fill the uncovered texels with dilate before sampling the texture bilinearly
    or with mipmaps.
    """
    if isinstance(mesh_or_arrays, Mesh):
        faces, uvs, uv_faces = mesh_or_arrays.faces, mesh_or_arrays.uvs, mesh_or_arrays.uv_faces
        if uvs is None:
            raise ReconError("bake_vertex_attribute: the mesh has no uvs (run unwrap first)")
        if attribute is None:
            attribute = mesh_or_arrays.vertex_colors
    else:
        faces, uvs, uv_faces = mesh_or_arrays
    if attribute is None:
        raise ReconError("bake_vertex_attribute: attribute: expected a [V, C] tensor, got None")
    if not isinstance(attribute, torch.Tensor) or attribute.ndim != 2:
        shape = tuple(attribute.shape) if isinstance(attribute, torch.Tensor) else type(attribute)
        raise ReconError(f"bake_vertex_attribute: attribute: expected shape [V, C], got {shape}")
    if faces.shape != uv_faces.shape:
        raise ReconError(
            f"bake_vertex_attribute: uv_faces: expected shape {tuple(faces.shape)} (like "
            f"faces), got {tuple(uv_faces.shape)}"
        )
    if faces.numel() and int(faces.max()) >= attribute.shape[0]:
        raise ReconError(
            f"bake_vertex_attribute: attribute has {attribute.shape[0]} rows, but faces index "
            f"vertex {int(faces.max())}"
        )
    face_id, barycentrics = rasterize_uv(uvs, uv_faces, texture_size)
    height, width = face_id.shape
    flat_face = face_id.reshape(-1)
    covered = torch.nonzero(flat_face >= 0).squeeze(1)
    texture = attribute.new_zeros((height * width, attribute.shape[1]))
    corner_values = attribute[faces.to(torch.int64)[flat_face[covered]]]  # [N, 3, C]
    weights = barycentrics.reshape(-1, 3)[covered].to(attribute.dtype)
    texture[covered] = (weights.unsqueeze(-1) * corner_values).sum(dim=1)
    return texture.view(height, width, -1), (face_id >= 0)


def dilate(
    texture: torch.Tensor, coverage: torch.Tensor, iterations: int | None = None
) -> torch.Tensor:
    """Fill texels outside the charts with the colour of the nearest covered texel.

    texture: [h, w, C] float; coverage: [h, w] bool (True = texel holds chart data).
    iterations: None fills every texel (the default, and what mipmapping needs: coarse levels
        average blocks up to the whole texture, so any texel left at background bleeds into
        them). An int k fills only the texels within k texels (Chebyshev distance, what k
        3x3 dilation passes reach) of a covered one; the rest keep their value.
    Returns a new [h, w, C] texture; covered texels are unchanged. Each filled texel copies its
    nearest covered texel (Euclidean, exact), so a chart's border colour extends outwards
    without blending neighbouring charts, which keeps bilinear taps at chart borders close to
    the chart's own values. Not differentiable (the fill pattern is a lookup).
    """
    from scipy.ndimage import distance_transform_edt

    if not isinstance(texture, torch.Tensor) or texture.ndim != 3:
        shape = tuple(texture.shape) if isinstance(texture, torch.Tensor) else type(texture)
        raise ReconError(f"dilate: texture: expected shape [h, w, C], got {shape}")
    if not isinstance(coverage, torch.Tensor) or tuple(coverage.shape) != tuple(texture.shape[:2]):
        shape = tuple(coverage.shape) if isinstance(coverage, torch.Tensor) else type(coverage)
        raise ReconError(
            f"dilate: coverage: expected shape {tuple(texture.shape[:2])} (texture's h, w), "
            f"got {shape}"
        )
    if iterations is not None and (isinstance(iterations, bool) or int(iterations) < 0):
        raise ReconError(f"dilate: iterations: expected None or an int >= 0, got {iterations!r}")
    coverage = coverage.to(torch.bool)
    if not bool(coverage.any()) or bool(coverage.all()) or iterations == 0:
        return texture.clone()
    height, width = coverage.shape
    # The exact Euclidean distance transform also returns, for every texel, the indices of its
    # nearest covered texel (a feature transform): the whole fill is then one gather.
    nearest = distance_transform_edt(
        ~coverage.cpu().numpy(), return_distances=False, return_indices=True
    )
    nearest_flat = torch.from_numpy(nearest[0] * width + nearest[1]).to(texture.device)
    filled = texture.reshape(height * width, -1)[nearest_flat.reshape(-1)].view_as(texture)
    if iterations is None:
        return filled
    # Texels k 3x3 dilation passes reach = within Chebyshev distance k = one (2k+1)^2 max-pool.
    kernel = 2 * int(iterations) + 1
    reach = F.max_pool2d(
        coverage[None, None].float(), kernel_size=kernel, stride=1, padding=int(iterations)
    )[0, 0].bool()
    return torch.where(reach.unsqueeze(-1), filled, texture)


def chart_border_edges(uv_faces: torch.Tensor) -> torch.Tensor:
    """UV edges on a chart border: [F, 3] bool, entry k for the edge from corner k to corner
    (k + 1) % 3, True where no other face shares that edge.

    uv_faces: [F, 3] int. unwrap splits uv indices at seams, so the open UV edges are exactly
    the chart outlines (and the mesh's own boundary): beyond them lie uncovered texels. (Faces
    xatlas ignores, those of zero area, get uvs of their own: all their edges are open.)
    """
    uv_faces = uv_faces.to(torch.int64)
    edges = torch.stack([uv_faces, uv_faces.roll(-1, dims=1)], dim=-1)  # [F, 3, 2]
    edges = edges.sort(dim=-1).values.reshape(-1, 2)  # undirected
    _, inverse, counts = torch.unique(edges, dim=0, return_inverse=True, return_counts=True)
    return (counts[inverse] == 1).view(-1, 3)


def chart_border_faces(uv_faces: torch.Tensor) -> torch.Tensor:
    """Faces with at least one edge on a chart border: [F] bool (see chart_border_edges)."""
    return chart_border_edges(uv_faces).any(dim=1)
