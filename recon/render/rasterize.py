"""Rasterization: which triangle covers each pixel centre, and differentiable barycentrics.

Two passes, because only the second needs gradients:

1. Visibility (no autograd). Every triangle gets a screen bounding box (clipped against the near
   plane so triangles crossing the camera plane get a finite, correct box). Candidate (triangle,
   pixel) pairs are enumerated from the boxes in bounded chunks, tested with homogeneous edge
   functions, and the nearest triangle per pixel wins through a scatter-min over packed
   (depth bits << 32 | triangle id) keys.
2. Barycentrics (autograd). For covered pixels only, perspective-correct barycentrics are
   recomputed from the clip positions of the winning triangle, so gradients reach clip x, y, w.

Homogeneous edge functions: with the pixel centre f = (f_x, f_y) in NDC and
p_i' = (x_i - f_x w_i, y_i - f_y w_i), a_0 = p_1' x p_2', a_1 = p_2' x p_0', a_2 = p_0' x p_1'.
(a_0, a_1, a_2) / sum(a) are the barycentrics of the point where the pixel's ray meets the
triangle's plane, for any signs of w, so no clipping is needed: a pixel is covered when all
three are >= 0 and that point lies between the near and far planes (interpolated w > 0 and
-1 <= z/w <= 1). Each a_i is affine in f, which is what the code exploits.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.errors import ReconError

# Candidate pairs evaluated per chunk: bounds peak memory (about 100 bytes per candidate).
DEFAULT_CHUNK_CANDIDATES = 1 << 21
# Triangles whose |det[x y w]| is below this (relative to their scale) have no area: skipped.
_DEGENERATE_RELATIVE = 1e-10
_NEAR_W = 1e-6


@dataclass
class Fragments:
    """Result of rasterize.

    tri_id: [B, H, W] int64 triangle index, -1 where no triangle covers the pixel centre.
    barycentrics: [B, H, W, 2] float32 (u, v) of the triangle's first two vertices (the third is
        1 - u - v), perspective-correct, differentiable w.r.t. clip x, y, w; 0 on background.
    depth: [B, H, W] float32 NDC depth z/w in [-1, 1], +inf on background, no gradient.
    barycentric_derivatives: [B, H, W, 4] (du/dx, dv/dx, du/dy, dv/dy) per pixel (x = column,
        y = row), or None when not requested.
    covered_index: [N] int64 flat indices into B*H*W of covered pixels (packed form used by
        interpolate and texture to skip background).
    covered_barycentrics: [N, 2] the differentiable (u, v) of those pixels.
    covered_derivatives: [N, 4] or None, the same for the derivatives.
    """

    tri_id: torch.Tensor
    barycentrics: torch.Tensor
    depth: torch.Tensor
    barycentric_derivatives: torch.Tensor | None
    covered_index: torch.Tensor
    covered_barycentrics: torch.Tensor
    covered_derivatives: torch.Tensor | None

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.tri_id.shape[1], self.tri_id.shape[2])

    @property
    def batch_size(self) -> int:
        return self.tri_id.shape[0]

    @property
    def mask(self) -> torch.Tensor:
        """[B, H, W, 1] float32: 1 where a triangle covers the pixel centre."""
        return (self.tri_id >= 0).unsqueeze(-1).float()

    @property
    def covered_faces(self) -> torch.Tensor:
        """[N] triangle index of each covered pixel."""
        return self.tri_id.reshape(-1)[self.covered_index]

    @property
    def covered_batch(self) -> torch.Tensor:
        """[N] view index of each covered pixel."""
        height, width = self.resolution
        return torch.div(self.covered_index, height * width, rounding_mode="floor")


def validate_clip_and_faces(clip_pos: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Check shapes, dtypes and values; return clip_pos as [B, V, 4]."""
    if not isinstance(clip_pos, torch.Tensor) or clip_pos.ndim not in (2, 3):
        shape = tuple(clip_pos.shape) if isinstance(clip_pos, torch.Tensor) else type(clip_pos)
        raise ReconError(f"clip_pos: expected shape [B, V, 4] or [V, 4], got {shape}")
    if clip_pos.shape[-1] != 4:
        raise ReconError(f"clip_pos: expected last dimension 4, got shape {tuple(clip_pos.shape)}")
    if clip_pos.dtype != torch.float32:
        raise ReconError(f"clip_pos: expected dtype float32, got {clip_pos.dtype}")
    if not isinstance(faces, torch.Tensor) or faces.ndim != 2 or faces.shape[-1] != 3:
        shape = tuple(faces.shape) if isinstance(faces, torch.Tensor) else type(faces)
        raise ReconError(f"faces: expected shape [F, 3], got {shape}")
    if faces.dtype not in (torch.int64, torch.int32):
        raise ReconError(f"faces: expected dtype int64, got {faces.dtype}")
    if faces.device != clip_pos.device:
        raise ReconError(f"faces: on {faces.device}, but clip_pos is on {clip_pos.device}")
    if clip_pos.ndim == 2:
        clip_pos = clip_pos[None]
    vertex_count = clip_pos.shape[1]
    if faces.numel():
        low, high = int(faces.min()), int(faces.max())
        if low < 0 or high >= vertex_count:
            raise ReconError(
                f"faces: indices must lie in [0, {vertex_count - 1}] for {vertex_count} vertices, "
                f"got range [{low}, {high}]"
            )
    if not bool(torch.isfinite(clip_pos.detach()).all()):
        raise ReconError("clip_pos: contains NaN or inf")
    return clip_pos


def _check_resolution(resolution: tuple[int, int]) -> tuple[int, int]:
    if len(resolution) != 2 or int(resolution[0]) <= 0 or int(resolution[1]) <= 0:
        raise ReconError(f"resolution: expected positive (height, width), got {resolution}")
    return int(resolution[0]), int(resolution[1])


def edge_function_coefficients(triangles: torch.Tensor) -> torch.Tensor:
    """Affine coefficients of the homogeneous edge functions.

    triangles: [..., 3, 4] clip positions. Returns [..., 3, 3]: row i = (constant, d/df_x,
    d/df_y) of a_i, so a_i(f) = row_i . (1, f_x, f_y). Differentiable.
    """
    x, y, w = triangles[..., 0], triangles[..., 1], triangles[..., 3]
    # a_k uses the vertex pair (i, j) = (k+1, k+2).
    i_index = [1, 2, 0]
    j_index = [2, 0, 1]
    xi, yi, wi = x[..., i_index], y[..., i_index], w[..., i_index]
    xj, yj, wj = x[..., j_index], y[..., j_index], w[..., j_index]
    constant = xi * yj - yi * xj
    slope_x = yi * wj - wi * yj
    slope_y = wi * xj - xi * wj
    return torch.stack([constant, slope_x, slope_y], dim=-1)


def _pixel_to_ndc(pixel: torch.Tensor, size: int) -> torch.Tensor:
    return (2.0 * pixel.to(torch.float32) + 1.0) / size - 1.0


def _screen_bounds(triangles: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Pixel-centre index ranges [..., 4] = (x0, x1, y0, y1), inclusive, clamped to the image.

    The box covers the triangle's part in front of the near plane w = _NEAR_W: the in-front
    vertices plus the points where edges cross that plane. Empty boxes have x1 < x0.
    """
    w = triangles[..., 3]
    in_front = w > _NEAR_W
    if bool(in_front.all()):
        # Every vertex in front (every fit and depth map): no edge crosses the plane, and the
        # box is the vertices' alone; the general path below gives the same box, slower.
        return _pixel_ranges(triangles, None, height, width)
    points = [triangles]
    valid = [in_front]
    for i, j in ((0, 1), (1, 2), (2, 0)):
        wi, wj = w[..., i], w[..., j]
        crosses = (wi > _NEAR_W) != (wj > _NEAR_W)
        t = ((_NEAR_W - wi) / torch.where(crosses, wj - wi, torch.ones_like(wi))).clamp(0, 1)
        point = triangles[..., i, :] + t[..., None] * (triangles[..., j, :] - triangles[..., i, :])
        points.append(point[..., None, :])
        valid.append(crosses[..., None])
    return _pixel_ranges(torch.cat(points, dim=-2), torch.cat(valid, dim=-1), height, width)


def _pixel_ranges(
    points: torch.Tensor, valid: torch.Tensor | None, height: int, width: int
) -> torch.Tensor:
    """Pixel-centre index ranges [..., 4] (x0, x1, y0, y1) of the box around the valid points
    [..., P, 4] (valid [..., P], None: all); empty where none is valid."""
    safe_w = points[..., 3].clamp_min(_NEAR_W)
    screen_x = (points[..., 0] / safe_w + 1) * 0.5 * width
    screen_y = (points[..., 1] / safe_w + 1) * 0.5 * height
    big = torch.finfo(torch.float32).max
    # Clamp before rounding so huge projected values cannot overflow int conversion.
    screen_x = screen_x.clamp(-2.0 * width - 2, 3.0 * width + 2)
    screen_y = screen_y.clamp(-2.0 * height - 2, 3.0 * height + 2)
    if valid is not None:
        screen_x_low, screen_x_high = (
            torch.where(valid, screen_x, big),
            torch.where(valid, screen_x, -big),
        )
        screen_y_low, screen_y_high = (
            torch.where(valid, screen_y, big),
            torch.where(valid, screen_y, -big),
        )
    else:
        screen_x_low = screen_x_high = screen_x
        screen_y_low = screen_y_high = screen_y
    min_x, max_x = screen_x_low.amin(-1), screen_x_high.amax(-1)
    min_y, max_y = screen_y_low.amin(-1), screen_y_high.amax(-1)
    # Pixel centre i + 0.5 inside [min, max]  <=>  ceil(min - 0.5) <= i <= floor(max - 0.5).
    x0 = torch.ceil(min_x - 0.5).clamp(0, width).to(torch.int64)
    x1 = torch.floor(max_x - 0.5).clamp(-1, width - 1).to(torch.int64)
    y0 = torch.ceil(min_y - 0.5).clamp(0, height).to(torch.int64)
    y1 = torch.floor(max_y - 0.5).clamp(-1, height - 1).to(torch.int64)
    if valid is not None:
        x1 = torch.where(valid.any(-1), x1, x0 - 1)
    return torch.stack([x0, x1, y0, y1], dim=-1)


@torch.no_grad()
def _visibility(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    height: int,
    width: int,
    cull_backfaces: bool,
    chunk_candidates: int,
) -> torch.Tensor:
    """Winning triangle per pixel: [B, H, W] int64, -1 for background."""
    batch = clip_pos.shape[0]
    device = clip_pos.device
    empty_key = torch.iinfo(torch.int64).max
    keys = torch.full((batch * height * width,), empty_key, dtype=torch.int64, device=device)
    if faces.shape[0] == 0:
        return keys.view(batch, height, width).fill_(-1)

    triangles = clip_pos[:, faces]  # [B, F, 3, 4]
    coefficients = edge_function_coefficients(triangles)  # [B, F, 3, 3]
    # det[x y w] of the three vertices is (up to the positive focal scale) six times the volume
    # of the tetrahedron (camera centre, triangle): zero for degenerate or edge-on triangles, and
    # its sign is the orientation seen from the camera, whatever the signs of w.
    xyw = triangles[..., [0, 1, 3]]
    determinant = torch.linalg.det(xyw)  # [B, F]
    scale = xyw.abs().amax(dim=(-1, -2))
    usable = determinant.abs() > _DEGENERATE_RELATIVE * scale.pow(3).clamp_min(1e-30)
    if cull_backfaces:
        # NDC y points down, so a counter-clockwise-from-outside (front) face has det < 0.
        usable &= determinant < 0
    # Depth numerators: z(f) * S and w(f) * S are affine in f as well.
    z_coefficients = (coefficients * triangles[..., 2, None]).sum(-2)  # [B, F, 3]
    w_coefficients = (coefficients * triangles[..., 3, None]).sum(-2)
    all_coefficients = torch.cat(
        [coefficients.reshape(batch, -1, 9), z_coefficients, w_coefficients], dim=-1
    )  # [B, F, 15]

    bounds = _screen_bounds(triangles, height, width)  # [B, F, 4]
    box_width = (bounds[..., 1] - bounds[..., 0] + 1).clamp_min(0)
    box_height = (bounds[..., 3] - bounds[..., 2] + 1).clamp_min(0)
    usable &= (box_width > 0) & (box_height > 0)
    # Triangles wholly in front of the camera: flip the edge functions by the orientation so
    # "inside" is simply all three >= 0. Triangles crossing the camera plane keep the general
    # test (all three of the sign of their sum, and the hit in front of the camera).
    in_front = (triangles[..., 3] > 0).all(-1)
    orientation = torch.where(determinant < 0, -1.0, 1.0)
    flip = torch.where(in_front, orientation, torch.ones_like(orientation))
    # Flipping all 15 keeps depth = z/w unchanged and w * (sum of edges) sign-correct.
    all_coefficients = all_coefficients * flip[..., None]

    # Bucket triangles by their bounding box rounded up to powers of two, so each bucket is a
    # dense [triangles, box pixels] grid evaluated by broadcasting: no per-candidate gathers.
    flat_usable = torch.nonzero(usable.reshape(-1)).squeeze(1)
    if flat_usable.numel() == 0:
        return keys.view(batch, height, width).fill_(-1)
    grid_width_log = torch.ceil(torch.log2(box_width.reshape(-1)[flat_usable].float())).long()
    grid_height_log = torch.ceil(torch.log2(box_height.reshape(-1)[flat_usable].float())).long()
    bucket = grid_width_log * 64 + grid_height_log
    order = torch.argsort(bucket)
    bucket_sorted = bucket[order]
    unique_buckets, bucket_counts = torch.unique_consecutive(bucket_sorted, return_counts=True)
    flat_coefficients = all_coefficients.reshape(-1, 15)
    flat_bounds = bounds.reshape(-1, 4)
    flat_in_front = in_front.reshape(-1)
    face_count = faces.shape[0]
    start = 0
    for bucket_value, count in zip(unique_buckets.tolist(), bucket_counts.tolist(), strict=True):
        grid_width = 1 << (bucket_value // 64)
        grid_height = 1 << (bucket_value % 64)
        members = flat_usable[order[start : start + count]]
        start += count
        per_chunk = max(1, chunk_candidates // (grid_width * grid_height))
        for chunk_start in range(0, members.numel(), per_chunk):
            _rasterize_bucket(
                members[chunk_start : chunk_start + per_chunk],
                grid_width,
                grid_height,
                flat_coefficients,
                flat_bounds,
                flat_in_front,
                face_count,
                keys,
                height,
                width,
            )

    tri_id = torch.where(keys == empty_key, -1, keys & 0xFFFFFFFF)
    return tri_id.view(batch, height, width)


def _rasterize_bucket(
    members: torch.Tensor,
    grid_width: int,
    grid_height: int,
    flat_coefficients: torch.Tensor,
    flat_bounds: torch.Tensor,
    flat_in_front: torch.Tensor,
    face_count: int,
    keys: torch.Tensor,
    height: int,
    width: int,
) -> None:
    """Test every pixel of a [grid_height, grid_width] box for each member (flat b * F + f) and
    scatter-min the packed depth keys of covered pixels into keys."""
    device = members.device
    coefficients = flat_coefficients[members]  # [M, 15]
    box = flat_bounds[members]  # [M, 4]
    offset_x = torch.arange(grid_width, device=device).repeat(grid_height)
    offset_y = torch.arange(grid_height, device=device).repeat_interleave(grid_width)
    pixel_x = box[:, 0:1] + offset_x  # [M, G]
    pixel_y = box[:, 2:3] + offset_y
    in_box = (pixel_x <= box[:, 1:2]) & (pixel_y <= box[:, 3:4])
    ndc_x = _pixel_to_ndc(pixel_x, width)
    ndc_y = _pixel_to_ndc(pixel_y, height)
    edge = [
        coefficients[:, 3 * k : 3 * k + 1]
        + coefficients[:, 3 * k + 1 : 3 * k + 2] * ndc_x
        + coefficients[:, 3 * k + 2 : 3 * k + 3] * ndc_y
        for k in range(3)
    ]
    front = flat_in_front[members][:, None]
    inside = (edge[0] >= 0) & (edge[1] >= 0) & (edge[2] >= 0)
    all_in_front = bool(front.all())
    if not all_in_front:
        total = edge[0] + edge[1] + edge[2]
        general = (edge[0] * total >= 0) & (edge[1] * total >= 0) & (edge[2] * total >= 0)
        inside = torch.where(front, inside, general)
    inside &= in_box
    # Flat gathers (take / index_select) are several times cheaper than 2D advanced indexing.
    flat = torch.nonzero(inside.reshape(-1)).squeeze(1)
    if flat.numel() == 0:
        return
    grid_size = grid_width * grid_height
    member_index = torch.div(flat, grid_size, rounding_mode="floor")
    x = ndc_x.reshape(-1).take(flat)
    y = ndc_y.reshape(-1).take(flat)
    depth_coefficients = coefficients[:, 9:15].index_select(0, member_index)  # [N, 6]
    z_numerator = (
        depth_coefficients[:, 0] + depth_coefficients[:, 1] * x + depth_coefficients[:, 2] * y
    )
    w_numerator = (
        depth_coefficients[:, 3] + depth_coefficients[:, 4] * x + depth_coefficients[:, 5] * y
    )
    depth = z_numerator / w_numerator
    visible = (depth >= -1) & (depth <= 1)
    if not all_in_front:
        # Interpolated w = w_numerator / (sum of edges) must be positive: the hit is in front.
        edge_sum = (edge[0] + edge[1] + edge[2]).reshape(-1).take(flat)
        visible &= w_numerator * edge_sum > 0
    keep = torch.nonzero(visible).squeeze(1)
    flat_item = members.index_select(0, member_index.index_select(0, keep))
    batch_index = torch.div(flat_item, face_count, rounding_mode="floor")
    face_index = flat_item - batch_index * face_count
    kept_flat = flat.index_select(0, keep)
    pixel_index = (batch_index * height + pixel_y.reshape(-1).take(kept_flat)) * width + (
        pixel_x.reshape(-1).take(kept_flat)
    )
    # Map depth from [-1, 1] to [0, 1]: non-negative float32 bits order like the floats.
    depth01 = ((depth.index_select(0, keep) + 1) * 0.5).clamp(0, 1)
    depth_bits = depth01.contiguous().view(torch.int32).to(torch.int64)
    keys.scatter_reduce_(0, pixel_index, (depth_bits << 32) | face_index, reduce="amin")


def rasterize(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int],
    with_derivatives: bool = False,
    cull_backfaces: bool = False,
    chunk_candidates: int = DEFAULT_CHUNK_CANDIDATES,
) -> Fragments:
    """Rasterize triangles given in homogeneous clip space.

    clip_pos: [B, V, 4] or [V, 4] float32 (see recon.camera for the clip space: NDC y down).
    faces: [F, 3] int64 vertex indices.
    resolution: (H, W). Pixel centres at i + 0.5, row 0 at the top.
    with_derivatives: also compute screen-space derivatives of the barycentrics.
    cull_backfaces: drop triangles facing away (counter-clockwise from outside is the front).
    Returns Fragments. Zero-area triangles never cover a pixel; triangles behind the camera or
    outside [near, far] are clipped per pixel; triangles crossing the camera plane are handled.
    """
    clip_pos = validate_clip_and_faces(clip_pos, faces)
    height, width = _check_resolution(resolution)
    faces = faces.to(torch.int64)
    tri_id = _visibility(clip_pos, faces, height, width, cull_backfaces, chunk_candidates)
    return _fragments_from_tri_id(clip_pos, faces, tri_id, with_derivatives)


def _fragments_from_tri_id(
    clip_pos: torch.Tensor, faces: torch.Tensor, tri_id: torch.Tensor, with_derivatives: bool
) -> Fragments:
    """Differentiable barycentrics (and derivatives) of covered pixels."""
    batch, height, width = tri_id.shape
    flat_tri = tri_id.reshape(-1)
    covered_index = torch.nonzero(flat_tri >= 0).squeeze(1)
    covered_faces = flat_tri[covered_index]
    covered_batch = torch.div(covered_index, height * width, rounding_mode="floor")
    pixel = covered_index - covered_batch * (height * width)
    pixel_y = torch.div(pixel, width, rounding_mode="floor")
    pixel_x = pixel - pixel_y * width
    ndc_x = _pixel_to_ndc(pixel_x, width)
    ndc_y = _pixel_to_ndc(pixel_y, height)

    vertex_index = faces[covered_faces]  # [N, 3]
    vertex_count = clip_pos.shape[1]
    triangles = gather_rows(
        clip_pos.reshape(-1, 4), covered_batch[:, None] * vertex_count + vertex_index
    )  # [N, 3, 4], differentiable
    coefficients = edge_function_coefficients(triangles)  # [N, 3, 3]
    edge_values = (
        coefficients[..., 0]
        + coefficients[..., 1] * ndc_x[:, None]
        + (coefficients[..., 2] * ndc_y[:, None])
    )  # [N, 3]
    total_area = edge_values.sum(-1, keepdim=True)
    covered_barycentrics = edge_values[:, :2] / total_area

    covered_derivatives = None
    if with_derivatives:
        # d(a_k / S)/df = (slope_k S - a_k slope_S) / S^2, then df/dpixel = 2 / size.
        slope_x = coefficients[..., 1]
        slope_y = coefficients[..., 2]
        total_slope_x = slope_x.sum(-1, keepdim=True)
        total_slope_y = slope_y.sum(-1, keepdim=True)
        squared = total_area.square()
        du_dx, dv_dx = ((slope_x * total_area - edge_values * total_slope_x) / squared)[
            :, :2
        ].unbind(-1)
        du_dy, dv_dy = ((slope_y * total_area - edge_values * total_slope_y) / squared)[
            :, :2
        ].unbind(-1)
        covered_derivatives = torch.stack(
            [
                du_dx * (2.0 / width),
                dv_dx * (2.0 / width),
                du_dy * (2.0 / height),
                dv_dy * (2.0 / height),
            ],
            dim=-1,
        )

    with torch.no_grad():
        z_interp = (covered_barycentrics.detach() * triangles[:, :2, 2].detach()).sum(-1) + (
            1 - covered_barycentrics.detach().sum(-1)
        ) * triangles[:, 2, 2].detach()
        w_interp = (covered_barycentrics.detach() * triangles[:, :2, 3].detach()).sum(-1) + (
            1 - covered_barycentrics.detach().sum(-1)
        ) * triangles[:, 2, 3].detach()
        depth = torch.full((batch * height * width,), float("inf"), device=clip_pos.device)
        depth[covered_index] = z_interp / w_interp

    barycentrics = scatter_to_image(covered_barycentrics, covered_index, batch, height, width)
    derivatives = (
        None
        if covered_derivatives is None
        else scatter_to_image(covered_derivatives, covered_index, batch, height, width)
    )
    return Fragments(
        tri_id=tri_id,
        barycentrics=barycentrics,
        depth=depth.view(batch, height, width),
        barycentric_derivatives=derivatives,
        covered_index=covered_index,
        covered_barycentrics=covered_barycentrics,
        covered_derivatives=covered_derivatives,
    )


def gather_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """table[index] for a 2D table [R, C] and any index shape -> [*index.shape, C].

    index_select's backward is an index_add, several times faster on CPU than the accumulating
    index_put that advanced indexing uses.
    """
    return table.index_select(0, index.reshape(-1)).view(*index.shape, table.shape[-1])


def scatter_to_image(
    values: torch.Tensor, covered_index: torch.Tensor, batch: int, height: int, width: int
) -> torch.Tensor:
    """Place packed per-pixel values [N, C] into a zero image [B, H, W, C] (differentiable)."""
    channels = values.shape[-1]
    image = values.new_zeros(batch * height * width, channels)
    image = image.index_copy(0, covered_index, values)
    return image.view(batch, height, width, channels)
