"""Analytic antialiasing of silhouette edges: the visibility (boundary) gradient of the renderer.

Point-sampled images have no gradient with respect to where a silhouette lies. This pass blends
the two pixels on either side of a silhouette edge by how much of the pixel the owning triangle
covers along the line joining the pixel centres; that amount depends continuously on the edge's
vertices, so position gradients appear through the crossing point (the boundary term of the
Reynolds transport theorem). Interior gradients still come from barycentrics.

Topology (which vertex lies across each edge) is computed once per face array and reused.
Every discrete choice (owner triangle, edge, silhouette test, range) is made without autograd;
only the crossing position and the blend are recomputed differentiably.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.errors import ReconError
from recon.render.rasterize import Fragments, gather_rows

# Crossings are accepted slightly outside [0, 1] so edges passing exactly through a pixel centre
# still contribute; beyond that the pair belongs to another configuration.
_CROSSING_MARGIN = 0.02
# Keeps the crossing division finite for edges nearly parallel to the pixel pair.
_EXTENT_EPSILON = 1e-7
# Triangles crossed between the owner and a silhouette edge before giving up.
_MAX_WALK_STEPS = 4


@dataclass
class EdgeTopology:
    """Per face and edge, the vertex opposite the edge in the neighbouring triangle.

    Edge k of face f runs from faces[f, k] to faces[f, (k + 1) % 3]; its own opposite vertex is
    faces[f, (k + 2) % 3].
    neighbor_opposite: [F, 3] int64, -1 for boundary and non-manifold edges (always silhouettes).
    neighbor_face: [F, 3] int64, the face across each edge, -1 where neighbor_opposite is -1.
    """

    neighbor_opposite: torch.Tensor
    neighbor_face: torch.Tensor
    face_count: int
    vertex_count: int


def build_topology(faces: torch.Tensor, vertex_count: int | None = None) -> EdgeTopology:
    """Edge adjacency by sorting undirected edge keys (vectorised).

    faces: [F, 3] int64 with positions shared by index (seam-split copies would turn every seam
    into a false silhouette).
    """
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ReconError(f"faces: expected shape [F, 3], got {tuple(faces.shape)}")
    faces = faces.to(torch.int64)
    face_count = faces.shape[0]
    if vertex_count is None:
        vertex_count = int(faces.max()) + 1 if face_count else 0
    start = faces
    end = faces[:, [1, 2, 0]]
    opposite = faces[:, [2, 0, 1]].reshape(-1)
    low = torch.minimum(start, end).reshape(-1)
    high = torch.maximum(start, end).reshape(-1)
    key = low * max(vertex_count, 1) + high
    order = torch.argsort(key)
    sorted_key = key[order]
    neighbor = torch.full((face_count * 3,), -1, dtype=torch.int64, device=faces.device)
    neighbor_face = torch.full_like(neighbor, -1)
    if face_count:
        same_as_next = sorted_key[1:] == sorted_key[:-1]
        # An edge shared by exactly two faces: equal to its successor, and neither the one
        # before nor the one after the pair carries the same key (that would be non-manifold).
        before_differs = torch.ones_like(same_as_next)
        before_differs[1:] = sorted_key[1:-1] != sorted_key[:-2]
        after_differs = torch.ones_like(same_as_next)
        after_differs[:-1] = sorted_key[2:] != sorted_key[1:-1]
        pair_start = torch.nonzero(same_as_next & before_differs & after_differs).squeeze(1)
        first = order[pair_start]
        second = order[pair_start + 1]
        neighbor[first] = opposite[second]
        neighbor[second] = opposite[first]
        neighbor_face[first] = torch.div(second, 3, rounding_mode="floor")
        neighbor_face[second] = torch.div(first, 3, rounding_mode="floor")
    return EdgeTopology(
        neighbor.view(face_count, 3), neighbor_face.view(face_count, 3), face_count, vertex_count
    )


def _signed_area_2d(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Orientation of screen triangles from clip positions [..., 4], valid for any w signs.

    det[x y w] of the three vertices equals w_a w_b w_c times the NDC signed area, so dividing
    the sign by the w signs gives the sign of the screen-space area.
    """
    determinant = (
        a[..., 0] * (b[..., 1] * c[..., 3] - b[..., 3] * c[..., 1])
        - a[..., 1] * (b[..., 0] * c[..., 3] - b[..., 3] * c[..., 0])
        + a[..., 3] * (b[..., 0] * c[..., 1] - b[..., 1] * c[..., 0])
    )
    return determinant * torch.sign(a[..., 3] * b[..., 3] * c[..., 3])


def antialias(
    color: torch.Tensor,
    fragments: Fragments,
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    topology: EdgeTopology | None = None,
) -> torch.Tensor:
    """Blend pixels across silhouette edges by analytic coverage.

    color: [B, H, W, C] final colours (include alpha/coverage as a channel to antialias it too).
    fragments: from rasterize of the same clip_pos and faces.
    clip_pos: [B, V, 4] or [V, 4] clip positions (gradients flow to the silhouette edges' ends).
    faces: [F, 3] int64, positions shared by index.
    topology: build_topology(faces), reusable across calls; built here when None.
    Returns [B, H, W, C].
    """
    if color.ndim != 4:
        raise ReconError(f"color: expected shape [B, H, W, C], got {tuple(color.shape)}")
    batch, height, width, channels = color.shape
    if (batch, height, width) != tuple(fragments.tri_id.shape):
        raise ReconError(
            f"color: expected leading shape {tuple(fragments.tri_id.shape)} (the fragments'), "
            f"got {tuple(color.shape[:3])}"
        )
    if clip_pos.ndim == 2:
        clip_pos = clip_pos[None]
    if clip_pos.shape[0] == 1 and batch > 1:
        clip_pos = clip_pos.expand(batch, -1, -1)
    faces = faces.to(torch.int64)
    if topology is None:
        topology = build_topology(faces, clip_pos.shape[1])
    elif topology.face_count != faces.shape[0]:
        raise ReconError(
            f"topology: built for {topology.face_count} faces, but faces has {faces.shape[0]}"
        )

    with torch.no_grad():
        # Facing of every face in every view: the sign of det[x y w] (see rasterize).
        facing = torch.linalg.det(clip_pos.detach()[:, faces][..., [0, 1, 3]]) > 0  # [B, F]
    flat_color = color.reshape(-1, channels)
    delta_index = []
    delta_value = []
    for horizontal in (True, False):
        found = _silhouette_crossings(
            fragments, clip_pos, faces, topology, facing, horizontal, height, width
        )
        if found is None:
            continue
        own_pixel, other_pixel, crossing = found
        own_color = gather_rows(flat_color, own_pixel)
        other_color = gather_rows(flat_color, other_pixel)
        # The crossing lies in the owner's half (c < 0.5): the owner pixel misses 0.5 - c of
        # its coverage and takes that much of the other colour. Otherwise the triangle spills
        # c - 0.5 into the other pixel.
        in_own_half = crossing < 0.5
        weight = torch.where(in_own_half, 0.5 - crossing, crossing - 0.5)[:, None]
        target = torch.where(in_own_half, own_pixel, other_pixel)
        difference = torch.where(
            in_own_half[:, None], other_color - own_color, own_color - other_color
        )
        delta_index.append(target)
        delta_value.append(weight * difference)
    if not delta_index:
        return color
    delta = torch.zeros_like(flat_color).index_add(
        0, torch.cat(delta_index), torch.cat(delta_value)
    )
    return (flat_color + delta).view(batch, height, width, channels)


def _silhouette_crossings(
    fragments: Fragments,
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    topology: EdgeTopology,
    facing: torch.Tensor,
    horizontal: bool,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Work items of one direction whose owner triangle exits through a silhouette edge.

    Returns (own_pixel [M], other_pixel [M], crossing [M]) with flat pixel indices and the
    differentiable crossing position in [0, 1] from the owner's centre toward the other's.
    """
    tri_id = fragments.tri_id
    depth = fragments.depth
    with torch.no_grad():
        if horizontal:
            differ = tri_id[:, :, :-1] != tri_id[:, :, 1:]
            batch_index, row, column = torch.nonzero(differ, as_tuple=True)
            first = (batch_index * height + row) * width + column
            second = first + 1
        else:
            differ = tri_id[:, :-1, :] != tri_id[:, 1:, :]
            batch_index, row, column = torch.nonzero(differ, as_tuple=True)
            first = (batch_index * height + row) * width + column
            second = first + width
        if first.numel() == 0:
            return None
        flat_tri = tri_id.reshape(-1)
        flat_depth = depth.reshape(-1)
        first_tri, second_tri = flat_tri[first], flat_tri[second]
        # Most differing pairs straddle an interior edge between two triangles facing the same
        # way: such an edge cannot be a silhouette, so those pairs are dropped up front.
        both = (first_tri >= 0) & (second_tri >= 0)
        neighbors = topology.neighbor_face[first_tri.clamp_min(0)]  # [M, 3]
        adjacent = (neighbors == second_tri[:, None]).any(-1)
        face_count = topology.face_count
        first_facing = facing.reshape(-1)[batch_index * face_count + first_tri.clamp_min(0)]
        second_facing = facing.reshape(-1)[batch_index * face_count + second_tri.clamp_min(0)]
        keep = torch.nonzero(~(both & adjacent & (first_facing == second_facing))).squeeze(1)
        if keep.numel() == 0:
            return None
        first, second = first[keep], second[keep]
        first_tri, second_tri = first_tri[keep], second_tri[keep]
        # Owner: the only covered pixel, or the nearer one when both are covered.
        owner_is_first = (second_tri < 0) | (
            (first_tri >= 0) & (flat_depth[first] <= flat_depth[second])
        )
        own_pixel = torch.where(owner_is_first, first, second)
        other_pixel = torch.where(owner_is_first, second, first)
        owner = torch.where(owner_is_first, first_tri, second_tri)
        direction = torch.where(owner_is_first, 1.0, -1.0)  # +1 toward +x (or +y)

        # Owner pixel centre in pixel units.
        pixel_in_image = own_pixel % (height * width)
        own_row = torch.div(pixel_in_image, width, rounding_mode="floor")
        own_column = pixel_in_image - own_row * width
        along = (own_column if horizontal else own_row).to(clip_pos.dtype) + 0.5
        across = (own_row if horizontal else own_column).to(clip_pos.dtype) + 0.5
        batch_of_item = torch.div(own_pixel, height * width, rounding_mode="floor")

        # Walk from the owner across interior edges along the segment between the two pixel
        # centres until a silhouette edge is crossed. Near a silhouette the surface is strongly
        # foreshortened, so the triangle owning the silhouette edge is often a thin sliver that
        # covers no pixel centre; stopping at the owner's own edges would miss most of them.
        item = torch.arange(owner.shape[0], device=owner.device)
        current = owner
        found_item, found_start, found_end = [], [], []
        for _ in range(_MAX_WALK_STEPS):
            corner = faces[current]  # [M, 3]
            triangle = clip_pos.detach()[batch_of_item[item, None], corner]  # [M, 3, 4]
            start = triangle
            end = triangle[:, [1, 2, 0]]
            crossing, edge_valid, edge_steep = _edge_crossings(
                start,
                end,
                along[item],
                across[item],
                direction[item],
                horizontal,
                height,
                width,
            )
            # The exit edge is the crossing farthest toward the other pixel.
            crossing = torch.where(edge_valid, crossing, torch.full_like(crossing, -1e30))
            best_value, best_edge = crossing.max(dim=1)
            steep = edge_steep.gather(1, best_edge[:, None]).squeeze(1)
            in_range = (best_value >= -_CROSSING_MARGIN) & (best_value <= 1 + _CROSSING_MARGIN)
            neighbor_vertex = topology.neighbor_opposite[current].gather(1, best_edge[:, None])
            neighbor_vertex = neighbor_vertex.squeeze(1)
            edge_index = best_edge[:, None, None].expand(-1, 1, 4)
            edge_start = start.gather(1, edge_index).squeeze(1)
            edge_end = end.gather(1, edge_index).squeeze(1)
            own_opposite = triangle[:, [2, 0, 1]].gather(1, edge_index).squeeze(1)
            neighbor_position = clip_pos.detach()[batch_of_item[item], neighbor_vertex.clamp_min(0)]
            # Same side = the neighbour folds back behind this triangle: a silhouette edge.
            silhouette = (neighbor_vertex < 0) | (
                _signed_area_2d(edge_start, edge_end, own_opposite)
                * _signed_area_2d(edge_start, edge_end, neighbor_position)
                > 0
            )
            # Edges running more along the pair than across it are left to the items of the
            # other direction, which measure them better.
            accept = in_range & silhouette & steep
            found_item.append(item[accept])
            found_start.append(corner.gather(1, best_edge[:, None]).squeeze(1)[accept])
            found_end.append(corner.gather(1, ((best_edge + 1) % 3)[:, None]).squeeze(1)[accept])
            # Continue through interior edges that are crossed before the other pixel centre.
            walk_on = in_range & ~silhouette & (best_value < 1)
            item = item[walk_on]
            current = topology.neighbor_face[current[walk_on], best_edge[walk_on]]
            if item.numel() == 0:
                break
        keep = torch.cat(found_item)
        if keep.numel() == 0:
            return None
        edge_start_vertex = torch.cat(found_start)
        edge_end_vertex = torch.cat(found_end)
        own_pixel, other_pixel = own_pixel[keep], other_pixel[keep]
        batch_of_item = batch_of_item[keep]
        along, across, direction = along[keep], across[keep], direction[keep]

    # Differentiable recomputation of the chosen edge's crossing from clip positions.
    flat_clip = clip_pos.reshape(-1, 4)
    vertex_count = clip_pos.shape[1]
    start_clip = gather_rows(flat_clip, batch_of_item * vertex_count + edge_start_vertex)  # [K, 4]
    end_clip = gather_rows(flat_clip, batch_of_item * vertex_count + edge_end_vertex)
    crossing = _crossing_along_pair(
        start_clip, end_clip, along, across, direction, horizontal, height, width
    )
    return own_pixel, other_pixel, crossing.clamp(-_CROSSING_MARGIN, 1 + _CROSSING_MARGIN)


def _to_pixels(clip: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (column, row) of clip positions [..., 4] (w must be positive)."""
    w = clip[..., 3]
    column = (clip[..., 0] / w + 1) * (0.5 * width)
    row = (clip[..., 1] / w + 1) * (0.5 * height)
    return column, row


def _along_across(
    start: torch.Tensor, end: torch.Tensor, horizontal: bool, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Edge end points in pair coordinates: (start along, start across, end along, end across),
    where 'along' is the pixel-pair direction (x for horizontal pairs, y for vertical ones)."""
    start_column, start_row = _to_pixels(start, height, width)
    end_column, end_row = _to_pixels(end, height, width)
    if horizontal:
        return start_column, start_row, end_column, end_row
    return start_row, start_column, end_row, end_column


def _crossing(
    start: torch.Tensor,
    end: torch.Tensor,
    along: torch.Tensor,
    across: torch.Tensor,
    direction: torch.Tensor,
    horizontal: bool,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where each edge (start, end clip positions [..., 4]) crosses the line through the pair's
    centres, as a position from the owner's centre toward the other pixel; also the edge's
    extents across and along the pair direction and its parameter t along the edge.

    along, across, direction broadcast against the edges' leading shape."""
    start_along, start_across, end_along, end_across = _along_across(
        start, end, horizontal, height, width
    )
    extent_across = end_across - start_across
    extent_along = end_along - start_along
    # A tiny epsilon keeps the division finite for edges nearly parallel to the pair.
    safe_extent = torch.where(
        extent_across.abs() < _EXTENT_EPSILON,
        torch.full_like(extent_across, _EXTENT_EPSILON),
        extent_across,
    )
    t = (across - start_across) / safe_extent
    crossing = (start_along + t * extent_along - along) * direction
    return crossing, extent_across, extent_along, t


def _edge_crossings(
    start: torch.Tensor,
    end: torch.Tensor,
    along: torch.Tensor,
    across: torch.Tensor,
    direction: torch.Tensor,
    horizontal: bool,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Crossing position of each of the three edges [M, 3], whether the edge crosses the pair's
    line at all (both ends in front of the camera), and whether it runs more across the pair
    direction than along it."""
    crossing, extent_across, extent_along, t = _crossing(
        start, end, along[:, None], across[:, None], direction[:, None], horizontal, height, width
    )
    in_front = (start[..., 3] > 0) & (end[..., 3] > 0)
    steep = extent_across.abs() >= extent_along.abs()
    spans = (t >= 0) & (t <= 1)
    crosses = in_front & spans & (extent_across.abs() >= _EXTENT_EPSILON)
    return crossing, crosses, steep


def _crossing_along_pair(
    start_clip: torch.Tensor,
    end_clip: torch.Tensor,
    along: torch.Tensor,
    across: torch.Tensor,
    direction: torch.Tensor,
    horizontal: bool,
    height: int,
    width: int,
) -> torch.Tensor:
    """Differentiable crossing [K] of one edge per item (see _edge_crossings)."""
    return _crossing(start_clip, end_clip, along, across, direction, horizontal, height, width)[0]
