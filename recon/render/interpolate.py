"""Interpolation of per-vertex attributes over rasterized fragments."""

from __future__ import annotations

import torch

from recon.errors import ReconError
from recon.render.rasterize import Fragments, gather_rows, scatter_to_image

# Attributes at least this wide are interpolated a block of INTERPOLATION_BLOCK_ROWS pixels at
# a time when no gradient is needed (interpolate_packed): their temporaries then stay in cache.
WIDE_ATTRIBUTES = 16
INTERPOLATION_BLOCK_ROWS = 1024


def interpolate(
    attributes: torch.Tensor,
    fragments: Fragments,
    faces: torch.Tensor,
    with_derivatives: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Perspective-correct interpolation of vertex attributes at every covered pixel.

    attributes: [V, C] or [B, V, C] float values per vertex (of whatever index buffer faces uses).
    fragments: from rasterize.
    faces: [F, 3] index buffer into attributes, with the same triangle order as the rasterized
        faces (UVs may use their own buffer, split at seams, while positions stay shared).
    with_derivatives: also return screen-space derivatives [B, H, W, 2C] laid out as
        (d/dx of every channel, then d/dy of every channel); needs fragments rasterized
        with_derivatives=True.
    Returns [B, H, W, C] (0 on background), and the derivatives when asked.
    """
    packed = interpolate_packed(attributes, fragments, faces, with_derivatives)
    batch = fragments.batch_size
    height, width = fragments.resolution
    if with_derivatives:
        values, derivatives = packed
        return (
            scatter_to_image(values, fragments.covered_index, batch, height, width),
            scatter_to_image(derivatives, fragments.covered_index, batch, height, width),
        )
    return scatter_to_image(packed, fragments.covered_index, batch, height, width)


def interpolate_packed(
    attributes: torch.Tensor,
    fragments: Fragments,
    faces: torch.Tensor,
    with_derivatives: bool = False,
    pixels: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Like interpolate, but returns only covered pixels: [N, C] (and [N, 2C] derivatives).

    pixels: [N] bool, which covered pixels to interpolate ([M, C] out, in covered order):
    wide attributes at a few pixels cost only those (no derivatives with it)."""
    if not isinstance(attributes, torch.Tensor) or attributes.ndim not in (2, 3):
        raise ReconError(
            f"attributes: expected shape [V, C] or [B, V, C], got "
            f"{tuple(attributes.shape) if isinstance(attributes, torch.Tensor) else type(attributes)}"
        )
    if not attributes.is_floating_point():
        raise ReconError(f"attributes: expected a float tensor, got {attributes.dtype}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ReconError(f"faces: expected shape [F, 3], got {tuple(faces.shape)}")
    if attributes.ndim == 3 and attributes.shape[0] not in (1, fragments.batch_size):
        raise ReconError(
            f"attributes: batch {attributes.shape[0]} does not match the fragments' batch "
            f"{fragments.batch_size}"
        )
    vertex_count = attributes.shape[-2]
    if faces.numel() and int(faces.max()) >= vertex_count:
        raise ReconError(
            f"faces: index {int(faces.max())} out of range for {vertex_count} attribute rows"
        )
    if with_derivatives and fragments.covered_derivatives is None:
        raise ReconError(
            "interpolate: with_derivatives=True needs fragments from rasterize(..., "
            "with_derivatives=True)"
        )
    if pixels is not None and with_derivatives:
        raise ReconError("interpolate: pixels= and with_derivatives=True do not combine")
    covered_faces = fragments.covered_faces
    barycentrics = fragments.covered_barycentrics
    if pixels is not None:
        if pixels.shape != covered_faces.shape or pixels.dtype != torch.bool:
            raise ReconError(
                f"pixels: expected a bool tensor of shape {tuple(covered_faces.shape)}, got "
                f"{pixels.dtype} {tuple(pixels.shape)}"
            )
        covered_faces, barycentrics = covered_faces[pixels], barycentrics[pixels]
    corner_index = faces.to(torch.int64)[covered_faces]  # [N, 3]
    if attributes.ndim == 3 and attributes.shape[0] > 1:
        batch_index = fragments.covered_batch
        if pixels is not None:
            batch_index = batch_index[pixels]
        corner_index = batch_index[:, None] * vertex_count + corner_index
        table = attributes.reshape(-1, attributes.shape[-1])
    else:
        table = attributes.reshape(vertex_count, -1)
    if (
        not with_derivatives
        and table.shape[1] >= WIDE_ATTRIBUTES
        and not (torch.is_grad_enabled() and attributes.requires_grad)
    ):
        return _interpolate_rows(table, corner_index, barycentrics)
    corners = gather_rows(table, corner_index)  # [N, 3, C]
    u, v = barycentrics.unbind(-1)
    # value = u a0 + v a1 + (1 - u - v) a2 = a2 + u (a0 - a2) + v (a1 - a2)
    edge0 = corners[:, 0] - corners[:, 2]
    edge1 = corners[:, 1] - corners[:, 2]
    values = corners[:, 2] + u[:, None] * edge0 + v[:, None] * edge1
    if not with_derivatives:
        return values
    du_dx, dv_dx, du_dy, dv_dy = fragments.covered_derivatives.unbind(-1)
    d_dx = du_dx[:, None] * edge0 + dv_dx[:, None] * edge1
    d_dy = du_dy[:, None] * edge0 + dv_dy[:, None] * edge1
    return values, torch.cat([d_dx, d_dy], dim=-1)


def _interpolate_rows(
    table: torch.Tensor, corner_index: torch.Tensor, barycentrics: torch.Tensor
) -> torch.Tensor:
    """interpolate_packed's values [N, C] for a wide table [V, C] (no autograd), a block of
    pixels at a time: the same arithmetic per element, so the same values, without [N, 3, C]
    temporaries far larger than the cache (a fingerprint's 174 placebo lights at 400 k pixels:
    three times faster)."""
    dtype = torch.promote_types(table.dtype, barycentrics.dtype)
    values = table.new_empty(corner_index.shape[0], table.shape[1], dtype=dtype)
    for start in range(0, corner_index.shape[0], INTERPOLATION_BLOCK_ROWS):
        rows = slice(start, start + INTERPOLATION_BLOCK_ROWS)
        corners = gather_rows(table, corner_index[rows])
        u, v = barycentrics[rows].unbind(-1)
        edge0 = corners[:, 0] - corners[:, 2]
        edge1 = corners[:, 1] - corners[:, 2]
        values[rows] = corners[:, 2] + u[:, None] * edge0 + v[:, None] * edge1
    return values
