"""Differentiable texture sampling: nearest, bilinear and trilinear (mipmapped) lookups.

Conventions (shared with the rasterizer and Mesh):

- A texture is [h, w, C] or [B, h, w, C], any channel count C, channels last.
- uv is [B, H, W, 2]. u runs along the columns (width), v along the rows (height); (0, 0) is the
  top-left corner of the image, so v = 0 is row 0. Texel (row i, column j) has its centre at
  u = (j + 0.5) / w, v = (i + 0.5) / h, as in grid_sample(align_corners=False).
- boundary 'wrap' repeats the texture with period 1 in u and v; 'clamp' clamps to the edge texel.
- A pixel whose u or v is NaN or infinite samples 0 in every channel (and passes no gradient).

All lookups are flattened index gathers from one [N, C] buffer (index_select), so a bilinear
lookup is 4 gathered rows per pixel and a trilinear one 8, whatever the number of mip levels:
every level of the pyramid lives in one concatenated buffer, addressed by a per-pixel offset.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from recon.errors import ReconError

FILTERS = ("nearest", "linear", "linear-mipmap-linear")
BOUNDARIES = ("wrap", "clamp")


def build_mip_pyramid(tex: torch.Tensor) -> list[torch.Tensor]:
    """Build the mip pyramid of a texture, differentiably.

    tex: [h, w, C] or [B, h, w, C] float.
    Returns the levels [level 0 = tex, level 1, ..., 1x1], each with tex's rank: level k + 1 is
    level k averaged over 2x2 blocks, size floor(size / 2) (at least 1) per axis. Odd sizes use
    adaptive average pooling, whose windows are 2 or 3 texels wide there.
    """
    batched = _check_texture(tex, "tex")
    levels = [batched]
    # [B, h, w, C] permuted to [B, C, h, w] is a channels_last tensor: the pooling kernels
    # handle that layout natively, so no copy is made going in or out.
    current = batched.permute(0, 3, 1, 2)
    height, width = current.shape[-2:]
    while height > 1 or width > 1:
        height, width = max(height // 2, 1), max(width // 2, 1)
        current = F.adaptive_avg_pool2d(current, (height, width))
        levels.append(current.permute(0, 2, 3, 1))
    if tex.ndim == 3:
        return [level[0] for level in levels]
    return levels


def mip_level(
    uv_derivatives: torch.Tensor,
    tex_size: tuple[int, int],
    max_level: float | None = None,
) -> torch.Tensor:
    """Level of detail per pixel from the screen-space derivatives of uv.

    uv_derivatives: [..., 4] = (du/dx, dv/dx, du/dy, dv/dy), per pixel (x = image column,
        y = image row).
    tex_size: (height, width) of mip level 0, in texels.
    max_level: if given, the result is clamped to [0, max_level], and NaN becomes 0.
    Returns [...]: 0.5 * log2 of the largest eigenvalue of J^T J, where
    J = [[du/dx * w, du/dy * w], [dv/dx * h, dv/dy * h]] is the pixel-to-texel Jacobian, i.e.
    log2 of the longest texel-space extent of a pixel. Unclamped, it is -inf for a zero J.
    """
    height, width = tex_size
    derivatives = uv_derivatives.detach()
    du_dx = derivatives[..., 0] * width
    dv_dx = derivatives[..., 1] * height
    du_dy = derivatives[..., 2] * width
    dv_dy = derivatives[..., 3] * height
    # J^T J = [[a, b], [b, c]]; its largest eigenvalue in closed form.
    a = du_dx * du_dx + dv_dx * dv_dx
    c = du_dy * du_dy + dv_dy * dv_dy
    b = du_dx * du_dy + dv_dx * dv_dy
    half_trace = 0.5 * (a + c)
    half_difference = 0.5 * (a - c)
    largest = half_trace + torch.sqrt(half_difference * half_difference + b * b)
    level = 0.5 * torch.log2(largest)
    if max_level is not None:
        level = torch.nan_to_num(level, nan=0.0, posinf=float(max_level), neginf=0.0)
        level = level.clamp(0.0, float(max_level))
    return level


def texture(
    tex: torch.Tensor,
    uv: torch.Tensor,
    uv_derivatives: torch.Tensor | None = None,
    filter: str = "linear",
    boundary: str = "wrap",
    max_mip_level: int | None = None,
    mip_pyramid: list[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Sample a texture at per-pixel uv coordinates.

    tex: [h, w, C] or [B, h, w, C] float. A [h, w, C] or [1, h, w, C] texture serves every
        batch element of uv; otherwise its batch must equal uv's.
    uv: [B, H, W, 2] float, (u, v) in [0, 1] across the texture (see the module docstring).
    uv_derivatives: [B, H, W, 4] float (du/dx, dv/dx, du/dy, dv/dy) per pixel; needed by
        'linear-mipmap-linear' only, and never differentiated.
    filter: 'nearest', 'linear' (bilinear) or 'linear-mipmap-linear' (trilinear).
    boundary: 'wrap' (repeat) or 'clamp' (clamp to edge).
    max_mip_level: trilinear only: the coarsest level used (default: the 1x1 level).
    mip_pyramid: trilinear only: build_mip_pyramid(tex), prebuilt so that fits whose texture
        did not change skip the rebuild; built here when None.
    Returns [B, H, W, C] in tex's dtype, differentiable with respect to tex and uv (the
    nearest filter passes gradients to tex only; no double backward). Pixels with NaN or
    infinite uv get 0.
    """
    batched_tex = _check_texture(tex, "tex")
    _check_uv(uv, batched_tex)
    if filter not in FILTERS:
        raise ReconError(f"texture: filter: expected one of {list(FILTERS)}, got {filter!r}")
    if boundary not in BOUNDARIES:
        raise ReconError(f"texture: boundary: expected one of {list(BOUNDARIES)}, got {boundary!r}")
    if max_mip_level is not None and (
        isinstance(max_mip_level, bool) or not isinstance(max_mip_level, int) or max_mip_level < 0
    ):
        raise ReconError(f"texture: max_mip_level: expected an int >= 0, got {max_mip_level!r}")
    if filter == "linear-mipmap-linear":
        if uv_derivatives is None:
            raise ReconError(
                "texture: uv_derivatives: expected a [B, H, W, 4] tensor for filter "
                "'linear-mipmap-linear', got None"
            )
        _check_uv_derivatives(uv_derivatives, uv)

    tex_batch, height, width, channels = batched_tex.shape
    pixel_shape = uv.shape[:-1]
    wrap = boundary == "wrap"
    flat_uv = uv.reshape(-1, 2)

    if filter == "nearest":
        with torch.no_grad():
            u, v, mask = _prepare_coordinates(flat_uv, wrap)
            index = _nearest_index(u, v, height, width, wrap)
            index += _batch_base(tex_batch, pixel_shape, height * width, uv.device)
        flat = batched_tex.reshape(tex_batch * height * width, channels)
        result = flat.index_select(0, index) * mask.to(flat.dtype).unsqueeze(-1)
        return result.view(*pixel_shape, channels)

    if filter == "linear":
        flat = batched_tex.reshape(tex_batch * height * width, channels)
        base = _batch_base(tex_batch, pixel_shape, height * width, uv.device)
        result = _BilinearSample.apply(flat, flat_uv, base, height, width, None, wrap)
        return result.view(*pixel_shape, channels)

    if mip_pyramid is None:
        levels = build_mip_pyramid(batched_tex)
    else:
        levels = _check_mip_pyramid(mip_pyramid, tex, batched_tex)
    coarsest = len(levels) - 1 if max_mip_level is None else min(len(levels) - 1, max_mip_level)
    result = _sample_trilinear(levels[: coarsest + 1], flat_uv, uv_derivatives, pixel_shape, wrap)
    return result.view(*pixel_shape, channels)


def _sample_trilinear(
    levels: list[torch.Tensor],
    uv: torch.Tensor,
    uv_derivatives: torch.Tensor,
    pixel_shape: torch.Size,
    wrap: bool,
) -> torch.Tensor:
    """Blend bilinear lookups in the two mip levels nearest each pixel's level of detail.

    levels: the pyramid levels to use, each [B_tex, h_l, w_l, C] (the last is the coarsest
    allowed); uv: [P, 2]; uv_derivatives: [B, H, W, 4]; pixel_shape: [B, H, W], P = B*H*W.
    Returns [P, C].
    """
    tex_batch, height, width, channels = levels[0].shape
    device = uv.device
    coarsest = len(levels) - 1
    # Every level of every batch element in one buffer [B_tex * total, C]: a pixel's taps in
    # any level are then rows of it, found through the level's offset. So the lookup is 8
    # gathers from one tensor, whatever the number of levels.
    sizes = [level.shape[1] * level.shape[2] for level in levels]
    total = sum(sizes)
    flat = torch.cat(
        [
            level.reshape(tex_batch, size, channels)
            for level, size in zip(levels, sizes, strict=True)
        ],
        dim=1,
    ).reshape(tex_batch * total, channels)
    with torch.no_grad():
        offsets = torch.tensor([0, *sizes[:-1]], device=device).cumsum(0)
        level_heights = torch.tensor([level.shape[1] for level in levels], device=device)
        level_widths = torch.tensor([level.shape[2] for level in levels], device=device)
        lod = mip_level(uv_derivatives, (height, width), max_level=coarsest).reshape(-1)
        lower = lod.floor()
        blend = (lod - lower).to(uv.dtype)
        lower_level = lower.long()
        upper_level = (lower_level + 1).clamp_max_(coarsest)
        # Both levels of a pixel go through one bilinear computation: [2, P].
        pixel_levels = torch.stack([lower_level, upper_level])
        level_weight = torch.stack([1.0 - blend, blend])
        base = offsets[pixel_levels] + _batch_base(tex_batch, pixel_shape, total, device)
        pixel_heights = level_heights[pixel_levels]
        pixel_widths = level_widths[pixel_levels]
    return _BilinearSample.apply(flat, uv, base, pixel_heights, pixel_widths, level_weight, wrap)


class _BilinearSample(torch.autograd.Function):
    """Blend of bilinear lookups into a flat [N, C] texel buffer, with a hand-written backward.

    forward(flat, uv, base, heights, widths, scale, wrap):
      flat: [N, C] texels, row-major levels stacked; uv: [P, 2] raw coordinates;
      base: int64 [L, P] (or broadcastable, or an int) row of flat where each pixel's level
      starts;
      heights, widths: ints, or int64 [L, P] per-pixel level sizes; scale: [L, P] weight of
      each of the L lookups (the mip blend), or None for 1; wrap: True to repeat, else clamp.
      Returns [P, C] = sum over the L lookups of scale * bilinear(level, uv).

    Why not plain autograd: it would materialise [4L, P, C] tap tensors forward and backward
    and a dozen [P]-sized intermediates for the weights' gradients. Fresh large buffers are
    what costs on CPU (page faults), so here the bookkeeping runs in place without autograd,
    taps are gathered one at a time into a reused [P, C] buffer (gathered again in backward
    rather than saved), and d/du, d/dv come from the closed-form bilinear derivatives.
    """

    @staticmethod
    def forward(
        ctx: torch.autograd.function.FunctionCtx,
        flat: torch.Tensor,
        uv: torch.Tensor,
        base: torch.Tensor | int,
        heights: int | torch.Tensor,
        widths: int | torch.Tensor,
        scale: torch.Tensor | None,
        wrap: bool,
    ) -> torch.Tensor:
        u, v, mask = _prepare_coordinates(uv, wrap)
        # Invalid pixels keep their (0, 0) taps but with zero weight and zero gradient.
        scale = mask.unsqueeze(0) if scale is None else scale * mask
        index, x_fraction, y_fraction = _bilinear_taps(u, v, heights, widths, wrap)
        index += base
        index = index.reshape(4 * scale.shape[0], uv.shape[0])
        weight = _bilinear_weights(x_fraction, y_fraction, scale).reshape(index.shape)

        flat_weight = weight.to(flat.dtype)
        buffer = torch.empty((index.shape[1], flat.shape[1]), dtype=flat.dtype, device=flat.device)
        result = torch.zeros_like(buffer)
        for tap in range(index.shape[0]):
            torch.index_select(flat, 0, index[tap], out=buffer)
            result.addcmul_(buffer, flat_weight[tap].unsqueeze(-1))
        ctx.save_for_backward(flat, index, flat_weight, x_fraction, y_fraction, scale)
        ctx.level_sizes = (heights, widths)
        ctx.uv_dtype = uv.dtype
        return result

    @staticmethod
    @once_differentiable
    def backward(
        ctx: torch.autograd.function.FunctionCtx, grad_result: torch.Tensor
    ) -> tuple[torch.Tensor | None, torch.Tensor | None, None, None, None, None, None]:
        flat, index, weight, x_fraction, y_fraction, scale = ctx.saved_tensors
        heights, widths = ctx.level_sizes
        grad_result = grad_result.contiguous()
        buffer = torch.empty_like(grad_result)
        grad_flat = grad_uv = None
        if ctx.needs_input_grad[0]:
            grad_flat = torch.zeros_like(flat)
            for tap in range(index.shape[0]):
                torch.mul(grad_result, weight[tap].unsqueeze(-1), out=buffer)
                grad_flat.index_add_(0, index[tap], buffer)
        if ctx.needs_input_grad[1]:
            # dots[k] = <grad_result, texel of tap k>: d(result)/d(weight k), per pixel.
            dots = torch.empty(index.shape, dtype=flat.dtype, device=flat.device)
            # The channel sum as a matrix-vector product: a reduction over a 3-wide inner
            # dimension is several times slower than gemv on CPU.
            ones = torch.ones(flat.shape[1], dtype=flat.dtype, device=flat.device)
            for tap in range(index.shape[0]):
                torch.index_select(flat, 0, index[tap], out=buffer)
                buffer.mul_(grad_result)
                torch.mv(buffer, ones, out=dots[tap])
            top_left, top_right, bottom_left, bottom_right = dots.to(ctx.uv_dtype).reshape(
                4, *scale.shape
            )
            # d(bilinear)/dx = (1 - fy)(top_right - top_left) + fy (bottom_right - bottom_left)
            # with x = u * width - 0.5. The wrap shift and the clamp of u have derivative 1
            # wherever the lookup is not constant; where it is, the tap differences are 0.
            grad_x = torch.lerp(top_right - top_left, bottom_right - bottom_left, y_fraction)
            grad_y = torch.lerp(bottom_left - top_left, bottom_right - top_right, x_fraction)
            grad_x *= scale
            grad_y *= scale
            grad_x *= widths
            grad_y *= heights
            grad_uv = torch.stack([grad_x.sum(dim=0), grad_y.sum(dim=0)], dim=-1)
        return grad_flat, grad_uv, None, None, None, None, None


def _prepare_coordinates(
    uv: torch.Tensor, wrap: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split uv [P, 2] into u, v [P] reduced to [0, 1], and mask [P] (1 = finite uv, else 0).

    Non-finite coordinates would become garbage (or overflowing) indices: they sample (0, 0),
    and the mask zeroes their weight. Wrap keeps the fractional part (the texture has period
    1), which also keeps large coordinates precise and their indices in range; clamp changes
    nothing that matters, since outside [0, 1] both taps of an axis are the edge texel.
    Runs without autograd (the caller supplies the derivatives).
    """
    valid = torch.isfinite(uv).all(dim=-1)
    u = torch.where(valid, uv[:, 0], 0.0)
    v = torch.where(valid, uv[:, 1], 0.0)
    if wrap:
        u -= u.floor()
        v -= v.floor()
    else:
        u.clamp_(0.0, 1.0)
        v.clamp_(0.0, 1.0)
    return u, v, valid.to(uv.dtype)


def _nearest_index(
    u: torch.Tensor, v: torch.Tensor, height: int, width: int, wrap: bool
) -> torch.Tensor:
    """Flat index row * width + column [P] of the texel containing (u, v) in [0, 1]."""
    column = (u * width).floor_().long()
    row = (v * height).floor_().long()
    # u = 1 lands one past the last column: that is column 0 again (wrap) or the edge (clamp).
    if wrap:
        column.remainder_(width)
        row.remainder_(height)
    else:
        column.clamp_max_(width - 1)
        row.clamp_max_(height - 1)
    row *= width
    row += column
    return row


def _bilinear_taps(
    u: torch.Tensor,
    v: torch.Tensor,
    heights: int | torch.Tensor,
    widths: int | torch.Tensor,
    wrap: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The four bilinear taps of (u, v) in [0, 1] in L levels of size heights x widths.

    u, v: [P]; heights, widths: ints, or int64 [L, P] (each pixel's level sizes).
    Returns index [4, L, P] int64 (row * width + column within the level), tap-major in the
    order top-left, top-right, bottom-left, bottom-right, and the fractional positions
    x_fraction, y_fraction [L, P] between the left/right and top/bottom taps.
    """
    x = u.unsqueeze(0) * widths
    y = v.unsqueeze(0) * heights
    x -= 0.5
    y -= 0.5
    left = x.floor()
    top = y.floor()
    x -= left
    y -= top
    left = left.long()
    top = top.long()
    # u, v in [0, 1] put x in [-0.5, w - 0.5]: left in [-1, w - 1] and right in [0, w], so
    # only one side of each axis can leave the level, and by one texel at most.
    right = left + 1
    bottom = top + 1
    if wrap:
        # In place and without integer division (remainder_ costs as much as the gathers).
        left += left.lt(0) * widths
        top += top.lt(0) * heights
        right -= right.ge(widths) * widths
        bottom -= bottom.ge(heights) * heights
    else:
        left.clamp_min_(0)
        top.clamp_min_(0)
        if isinstance(widths, torch.Tensor):
            torch.minimum(right, widths - 1, out=right)
            torch.minimum(bottom, heights - 1, out=bottom)
        else:
            right.clamp_max_(widths - 1)
            bottom.clamp_max_(heights - 1)
    top *= widths
    bottom *= widths
    index = torch.empty((4, *left.shape), dtype=torch.long, device=u.device)
    torch.add(top, left, out=index[0])
    torch.add(top, right, out=index[1])
    torch.add(bottom, left, out=index[2])
    torch.add(bottom, right, out=index[3])
    return index, x, y


def _bilinear_weights(
    x_fraction: torch.Tensor, y_fraction: torch.Tensor, scale: torch.Tensor
) -> torch.Tensor:
    """Bilinear weights [4, L, P] (tap order as _bilinear_taps) times scale [L, P]."""
    top = (1.0 - y_fraction) * scale
    bottom = y_fraction * scale
    left = 1.0 - x_fraction
    weight = torch.empty((4, *x_fraction.shape), dtype=x_fraction.dtype, device=x_fraction.device)
    torch.mul(left, top, out=weight[0])
    torch.mul(x_fraction, top, out=weight[1])
    torch.mul(left, bottom, out=weight[2])
    torch.mul(x_fraction, bottom, out=weight[3])
    return weight


def _batch_base(
    tex_batch: int, pixel_shape: torch.Size, stride: int, device: torch.device
) -> torch.Tensor | int:
    """Per-pixel row offset [P] of the pixel's texture in the flat buffer (0 if shared).

    pixel_shape: [B, H, W]; stride: rows per batch element in the buffer.
    """
    if tex_batch == 1:
        return 0
    batch, pixels = pixel_shape[0], pixel_shape[1:].numel()
    return (torch.arange(batch, device=device) * stride).repeat_interleave(pixels)


def _check_texture(tex: torch.Tensor, name: str) -> torch.Tensor:
    """Validate a texture and return it as [B, h, w, C]."""
    if not isinstance(tex, torch.Tensor):
        raise ReconError(f"texture: {name}: expected a torch.Tensor, got {type(tex).__name__}")
    if tex.ndim not in (3, 4):
        raise ReconError(
            f"texture: {name}: expected shape [h, w, C] or [B, h, w, C], got {tuple(tex.shape)}"
        )
    if not tex.is_floating_point():
        raise ReconError(f"texture: {name}: expected a floating-point tensor, got {tex.dtype}")
    if min(tex.shape) < 1:
        raise ReconError(f"texture: {name}: expected every dimension >= 1, got {tuple(tex.shape)}")
    return tex if tex.ndim == 4 else tex.unsqueeze(0)


def _check_uv(uv: torch.Tensor, batched_tex: torch.Tensor) -> None:
    """Validate uv [B, H, W, 2] against the [B_tex, h, w, C] texture."""
    if not isinstance(uv, torch.Tensor):
        raise ReconError(f"texture: uv: expected a torch.Tensor, got {type(uv).__name__}")
    if uv.ndim != 4 or uv.shape[-1] != 2:
        raise ReconError(f"texture: uv: expected shape [B, H, W, 2], got {tuple(uv.shape)}")
    if not uv.is_floating_point():
        raise ReconError(f"texture: uv: expected a floating-point tensor, got {uv.dtype}")
    if uv.device != batched_tex.device:
        raise ReconError(
            f"texture: uv: expected device {batched_tex.device} (like tex), got {uv.device}"
        )
    tex_batch = batched_tex.shape[0]
    if tex_batch not in (1, uv.shape[0]):
        raise ReconError(
            f"texture: tex: expected batch 1 or {uv.shape[0]} (uv's batch), got {tex_batch}"
        )


def _check_uv_derivatives(uv_derivatives: torch.Tensor, uv: torch.Tensor) -> None:
    """Validate uv_derivatives [B, H, W, 4] against uv [B, H, W, 2]."""
    expected = (*uv.shape[:-1], 4)
    if not isinstance(uv_derivatives, torch.Tensor):
        raise ReconError(
            f"texture: uv_derivatives: expected a torch.Tensor, got {type(uv_derivatives).__name__}"
        )
    if tuple(uv_derivatives.shape) != expected:
        raise ReconError(
            f"texture: uv_derivatives: expected shape {list(expected)}, "
            f"got {list(uv_derivatives.shape)}"
        )
    if not uv_derivatives.is_floating_point():
        raise ReconError(
            f"texture: uv_derivatives: expected a floating-point tensor, got {uv_derivatives.dtype}"
        )
    if uv_derivatives.device != uv.device:
        raise ReconError(
            f"texture: uv_derivatives: expected device {uv.device} (like uv), "
            f"got {uv_derivatives.device}"
        )


def _check_mip_pyramid(
    mip_pyramid: list[torch.Tensor], tex: torch.Tensor, batched_tex: torch.Tensor
) -> list[torch.Tensor]:
    """Validate a prebuilt pyramid against tex's sizes and return its levels as [B, h, w, C]."""
    tex_batch, height, width, channels = batched_tex.shape
    expected = [(height, width)]
    while height > 1 or width > 1:
        height, width = max(height // 2, 1), max(width // 2, 1)
        expected.append((height, width))
    if not isinstance(mip_pyramid, (list, tuple)) or len(mip_pyramid) != len(expected):
        got = len(mip_pyramid) if isinstance(mip_pyramid, (list, tuple)) else type(mip_pyramid)
        raise ReconError(
            f"texture: mip_pyramid: expected a list of {len(expected)} levels "
            f"(build_mip_pyramid(tex)), got {got}"
        )
    levels = []
    for number, (level, (level_height, level_width)) in enumerate(
        zip(mip_pyramid, expected, strict=False)
    ):
        prefix = (tex_batch,) if tex.ndim == 4 else ()
        shape = (*prefix, level_height, level_width, channels)
        if not isinstance(level, torch.Tensor) or tuple(level.shape) != shape:
            got = tuple(level.shape) if isinstance(level, torch.Tensor) else type(level).__name__
            raise ReconError(f"texture: mip_pyramid[{number}]: expected shape {shape}, got {got}")
        if level.device != tex.device or not level.is_floating_point():
            raise ReconError(
                f"texture: mip_pyramid[{number}]: expected a floating-point tensor on "
                f"{tex.device}, got {level.dtype} on {level.device}"
            )
        levels.append(level if level.ndim == 4 else level.unsqueeze(0))
    return levels
