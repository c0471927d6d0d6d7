"""Tests for recon.render.texture: filters, boundaries, mip pyramid, level of detail, gradients."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from recon.errors import ReconError
from recon.render.texture import build_mip_pyramid, mip_level, texture

TRILINEAR = "linear-mipmap-linear"


def grid_sample_reference(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear clamp-to-edge lookup by grid_sample: tex [B, h, w, C], uv [B, H, W, 2]."""
    sampled = F.grid_sample(
        tex.permute(0, 3, 1, 2),
        uv * 2.0 - 1.0,
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    )
    return sampled.permute(0, 2, 3, 1)


def coordinates_away_from_kinks(
    count: int, sizes: list[int], low: float, high: float, generator: torch.Generator
) -> torch.Tensor:
    """count coordinates in [low, high] at least 0.1 texel from any texel centre of every size.

    Bilinear lookups are piecewise smooth with kinks at texel centres; finite differences
    across a kink would not match the analytic gradient, so gradchecks stay clear of them.
    """
    candidates = low + (high - low) * torch.rand(
        64 * count, dtype=torch.float64, generator=generator
    )
    keep = torch.ones_like(candidates, dtype=torch.bool)
    for size in sizes:
        fraction = torch.remainder(candidates * size - 0.5, 1.0)
        keep &= (fraction > 0.1) & (fraction < 0.9)
    chosen = candidates[keep][:count]
    assert chosen.numel() == count
    return chosen


def smooth_uv(
    shape: tuple[int, int, int], tex_size: tuple[int, int], levels: int, low: float, high: float
) -> torch.Tensor:
    """uv [B, H, W, 2] float64 clear of the kinks of the first `levels` mip levels."""
    generator = torch.Generator().manual_seed(7)
    count = math.prod(shape)
    height, width = tex_size
    widths = [max(width >> level, 1) for level in range(levels)]
    heights = [max(height >> level, 1) for level in range(levels)]
    u = coordinates_away_from_kinks(count, widths, low, high, generator)
    v = coordinates_away_from_kinks(count, heights, low, high, generator)
    return torch.stack([u, v], dim=-1).reshape(*shape, 2)


def checkerboard(size: int) -> torch.Tensor:
    """[size, size, 1] float32 checkerboard with a period of one texel."""
    rows = torch.arange(size).view(-1, 1)
    columns = torch.arange(size).view(1, -1)
    return ((rows + columns) % 2).to(torch.float32).unsqueeze(-1)


def constant_derivatives(
    shape: tuple[int, int, int], du_dx: float, dv_dx: float, du_dy: float, dv_dy: float
) -> torch.Tensor:
    """uv_derivatives [B, H, W, 4] equal at every pixel."""
    values = torch.tensor([du_dx, dv_dx, du_dy, dv_dy], dtype=torch.float32)
    return values.expand(*shape, 4).clone()


# --- bilinear and nearest ----------------------------------------------------------------------


@pytest.mark.parametrize("channels", [1, 3, 5])
@pytest.mark.parametrize("tex_size", [(4, 4), (5, 7), (1, 6)])
def test_bilinear_clamp_matches_grid_sample(channels: int, tex_size: tuple[int, int]) -> None:
    generator = torch.Generator().manual_seed(0)
    tex = torch.rand(2, *tex_size, channels, generator=generator)
    uv = torch.rand(2, 6, 5, 2, generator=generator)
    uv[0, 0, 0] = torch.tensor([0.0, 0.0])
    uv[0, 0, 1] = torch.tensor([1.0, 1.0])
    result = texture(tex, uv, filter="linear", boundary="clamp")
    assert result.shape == (2, 6, 5, channels)
    torch.testing.assert_close(result, grid_sample_reference(tex, uv), atol=1e-5, rtol=0)


def test_bilinear_clamp_outside_unit_square_is_edge_value() -> None:
    tex = torch.rand(3, 4, 2, generator=torch.Generator().manual_seed(1))
    uv = torch.tensor([[[[-3.0, 0.5 / 3], [7.0, 2.5 / 3], [0.5 / 4, -1.0], [3.5 / 4, 5.0]]]])
    result = texture(tex, uv, boundary="clamp")
    expected = torch.stack([tex[0, 0], tex[2, 3], tex[0, 0], tex[2, 3]]).view(1, 1, 4, 2)
    torch.testing.assert_close(result, expected)


@pytest.mark.parametrize("channels", [1, 3])
def test_bilinear_wrap_matches_grid_sample_on_tiled_texture(channels: int) -> None:
    generator = torch.Generator().manual_seed(2)
    tex = torch.rand(2, 5, 6, channels, generator=generator)
    # uv across the edges of the unit square, but more than half a texel inside the 3x3 tiling.
    uv = torch.rand(2, 7, 7, 2, generator=generator) * 1.8 - 0.4
    tiled = tex.repeat(1, 3, 3, 1)
    expected = grid_sample_reference(tiled, (uv + 1.0) / 3.0)
    result = texture(tex, uv, filter="linear", boundary="wrap")
    torch.testing.assert_close(result, expected, atol=1e-5, rtol=0)


def test_wrap_is_periodic_for_far_coordinates() -> None:
    tex = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    uv = torch.rand(1, 4, 4, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    shift = torch.tensor([-7.0, 1000.0], dtype=torch.float64)
    for filter in ("nearest", "linear"):
        torch.testing.assert_close(
            texture(tex, uv + shift, filter=filter), texture(tex, uv, filter=filter)
        )


@pytest.mark.parametrize("boundary", ["wrap", "clamp"])
def test_nearest_picks_the_texel_containing_uv(boundary: str) -> None:
    height, width = 5, 7
    # Each texel holds its own (row, column): the lookup says which texel it read.
    rows, columns = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tex = torch.stack([rows, columns], dim=-1).to(torch.float32)
    generator = torch.Generator().manual_seed(5)
    row = torch.randint(0, height, (1, 6, 6), generator=generator)
    column = torch.randint(0, width, (1, 6, 6), generator=generator)
    inside = 0.02 + 0.96 * torch.rand(1, 6, 6, 2, generator=generator)
    uv = torch.stack([(column + inside[..., 0]) / width, (row + inside[..., 1]) / height], -1)
    result = texture(tex, uv, filter="nearest", boundary=boundary)
    assert torch.equal(result, torch.stack([row, column], dim=-1).to(torch.float32))

    outside = torch.tensor([[[[1.0 + 0.5 / width, -0.5 / height]]]])
    expected = [height - 1.0, 0.0] if boundary == "wrap" else [0.0, width - 1.0]
    assert texture(tex, outside, filter="nearest", boundary=boundary).flatten().tolist() == expected


@pytest.mark.parametrize("filter", ["nearest", "linear", TRILINEAR])
@pytest.mark.parametrize("boundary", ["wrap", "clamp"])
@pytest.mark.parametrize("tex_size", [(4, 8), (5, 3)])
def test_texel_centres_return_texel_values(
    filter: str, boundary: str, tex_size: tuple[int, int]
) -> None:
    height, width = tex_size
    tex = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(6))
    rows, columns = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    # v = 0 is the top row: pixel (i, j) samples the centre of texel row i, column j.
    uv = torch.stack([(columns + 0.5) / width, (rows + 0.5) / height], dim=-1).unsqueeze(0)
    derivatives = torch.full((1, height, width, 4), 1e-4)
    result = texture(tex, uv, derivatives, filter=filter, boundary=boundary)[0]
    if (height & (height - 1)) == 0 and (width & (width - 1)) == 0:
        assert torch.equal(result, tex)  # exact: every coordinate is representable
    else:
        torch.testing.assert_close(result, tex, atol=1e-6, rtol=0)


def test_texture_batch_selects_per_element_and_shared_texture_broadcasts() -> None:
    generator = torch.Generator().manual_seed(8)
    tex = torch.rand(3, 4, 5, 2, generator=generator)
    uv = torch.rand(3, 2, 3, 2, generator=generator)
    result = texture(tex, uv)
    for element in range(3):
        torch.testing.assert_close(
            result[element : element + 1], texture(tex[element], uv[element : element + 1])
        )
    shared = texture(tex[1], uv)
    torch.testing.assert_close(shared, texture(tex[1:2], uv))
    torch.testing.assert_close(shared[1], result[1])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_output_dtype_follows_texture(dtype: torch.dtype) -> None:
    tex = torch.rand(4, 4, 3, dtype=dtype)
    uv = torch.rand(1, 2, 2, 2, dtype=dtype)
    derivatives = torch.rand(1, 2, 2, 4, dtype=dtype)
    for filter in ("nearest", "linear", TRILINEAR):
        assert texture(tex, uv, derivatives, filter=filter).dtype == dtype


@pytest.mark.parametrize("filter", ["nearest", "linear", TRILINEAR])
@pytest.mark.parametrize("boundary", ["wrap", "clamp"])
def test_non_finite_uv_samples_zero_and_passes_no_gradient(filter: str, boundary: str) -> None:
    generator = torch.Generator().manual_seed(9)
    tex = (torch.rand(4, 6, 3, generator=generator) + 1.0).requires_grad_()
    uv = torch.rand(1, 3, 3, 2, generator=generator)
    uv[0, 0, 0, 0] = float("nan")
    uv[0, 1, 1, 1] = float("inf")
    uv[0, 2, 2] = float("-inf")
    uv.requires_grad_()
    derivatives = torch.full((1, 3, 3, 4), 0.3)
    result = texture(tex, uv, derivatives, filter=filter, boundary=boundary)
    bad = torch.zeros(1, 3, 3, dtype=torch.bool)
    bad[0, 0, 0] = bad[0, 1, 1] = bad[0, 2, 2] = True
    assert torch.equal(result[bad], torch.zeros(3, 3))
    assert (result[~bad] >= 1.0).all()
    result.sum().backward()
    assert torch.isfinite(tex.grad).all()
    if filter == "nearest":
        assert uv.grad is None  # nearest is piecewise constant in uv
    else:
        assert torch.isfinite(uv.grad).all()
        assert torch.equal(uv.grad[bad], torch.zeros(3, 2))
    # The texture gradient counts only the valid pixels' weights (each sums to 1).
    torch.testing.assert_close(tex.grad.sum(), torch.tensor(6.0 * 3))


# --- mip pyramid and level of detail ------------------------------------------------------------


@pytest.mark.parametrize(
    ("tex_size", "expected"),
    [
        ((8, 8), [(8, 8), (4, 4), (2, 2), (1, 1)]),
        ((8, 2), [(8, 2), (4, 1), (2, 1), (1, 1)]),
        ((5, 7), [(5, 7), (2, 3), (1, 1)]),
        ((1, 6), [(1, 6), (1, 3), (1, 1)]),
        ((1, 1), [(1, 1)]),
    ],
)
def test_mip_pyramid_level_sizes(
    tex_size: tuple[int, int], expected: list[tuple[int, int]]
) -> None:
    tex = torch.rand(*tex_size, 3)
    assert [tuple(level.shape) for level in build_mip_pyramid(tex)] == [
        (*size, 3) for size in expected
    ]
    batched = torch.rand(2, *tex_size, 3)
    assert [tuple(level.shape) for level in build_mip_pyramid(batched)] == [
        (2, *size, 3) for size in expected
    ]


@pytest.mark.parametrize("tex_size", [(16, 16), (8, 32), (4, 1)])
def test_mip_levels_are_box_averages_of_level_zero(tex_size: tuple[int, int]) -> None:
    height, width = tex_size
    tex = torch.rand(2, height, width, 3, dtype=torch.float64)
    for level in build_mip_pyramid(tex):
        level_height, level_width = level.shape[1:3]
        block_height, block_width = height // level_height, width // level_width
        blocks = tex.reshape(2, level_height, block_height, level_width, block_width, 3)
        torch.testing.assert_close(level, blocks.mean(dim=(2, 4)))


def test_mip_pyramid_of_odd_sizes_averages_and_is_differentiable() -> None:
    tex = torch.rand(7, 5, 2, dtype=torch.float64, requires_grad=True)
    levels = build_mip_pyramid(tex)
    assert all(
        (level >= tex.min() - 1e-12).all() and (level <= tex.max() + 1e-12).all()
        for level in levels
    )
    constant = build_mip_pyramid(torch.full((7, 5, 2), 0.25))
    assert all(torch.equal(level, torch.full_like(level, 0.25)) for level in constant)
    assert torch.autograd.gradcheck(lambda t: build_mip_pyramid(t)[1], (tex,))


def largest_singular_value_level(
    jacobian_uv_per_pixel: torch.Tensor, tex_size: tuple[int, int]
) -> float:
    """Reference level of detail: log2 of the largest singular value of the texel Jacobian."""
    height, width = tex_size
    texel_jacobian = torch.diag(torch.tensor([width, height], dtype=torch.float64))
    texel_jacobian = texel_jacobian @ jacobian_uv_per_pixel.to(torch.float64)
    return math.log2(torch.linalg.svdvals(texel_jacobian).max().item())


@pytest.mark.parametrize(
    ("jacobian", "tex_size", "expected"),
    [
        # [[du/dx, du/dy], [dv/dx, dv/dy]] per pixel; expected level where known by hand.
        ([[4 / 64, 0.0], [0.0, 4 / 64]], (64, 64), 2.0),  # isotropic, 4 texels per pixel
        ([[8 / 64, 0.0], [0.0, 2 / 64]], (64, 64), 3.0),  # anisotropic: the long axis counts
        ([[0.0, 1 / 64], [1 / 32, 0.0]], (32, 64), 0.0),  # transposed axes, non-square texture
        ([[1 / 256, 0.0], [0.0, 1 / 256]], (64, 64), -2.0),  # magnified: below level 0
        ([[0.3, -0.05], [0.1, 0.2]], (16, 32), None),  # general shear
    ],
)
def test_mip_level_on_analytic_uv_fields(
    jacobian: list[list[float]], tex_size: tuple[int, int], expected: float | None
) -> None:
    # uv = J @ (x, y) + offset over a pixel grid; the derivatives come from finite differences
    # of that field, so the convention (x = column, y = row, per pixel) is tested too.
    jacobian = torch.tensor(jacobian, dtype=torch.float64)
    rows, columns = torch.meshgrid(
        torch.arange(6, dtype=torch.float64), torch.arange(5, dtype=torch.float64), indexing="ij"
    )
    pixels = torch.stack([columns, rows], dim=-1)
    uv = pixels @ jacobian.T + 0.1
    d_dx = uv[:, 1:] - uv[:, :-1]
    d_dy = uv[1:, :] - uv[:-1, :]
    derivatives = torch.cat([d_dx[:-1], d_dy[:, :-1]], dim=-1).unsqueeze(0)
    reference = largest_singular_value_level(jacobian, tex_size)
    if expected is not None:
        assert reference == pytest.approx(expected, abs=1e-12)
    level = mip_level(derivatives, tex_size)
    assert level.shape == (1, 5, 4)
    torch.testing.assert_close(level, torch.full_like(level, reference), atol=1e-9, rtol=0)


@pytest.mark.parametrize("angle", [0.3, 1.0, 2.5])
def test_mip_level_of_rotated_anisotropic_jacobian(angle: float) -> None:
    # J = R(angle) diag(8, 2) texels per pixel: the level is log2 8 = 3 at every rotation.
    cosine, sine = math.cos(angle), math.sin(angle)
    rotation = torch.tensor([[cosine, -sine], [sine, cosine]], dtype=torch.float64)
    texel_jacobian = rotation @ torch.diag(torch.tensor([8.0, 2.0], dtype=torch.float64))
    uv_jacobian = texel_jacobian / 32.0  # 32 x 32 texture
    derivatives = torch.stack(
        [uv_jacobian[0, 0], uv_jacobian[1, 0], uv_jacobian[0, 1], uv_jacobian[1, 1]]
    ).view(1, 1, 1, 4)
    assert mip_level(derivatives, (32, 32)).item() == pytest.approx(3.0, abs=1e-12)


def test_mip_level_clamps_and_handles_degenerate_derivatives() -> None:
    derivatives = torch.tensor(
        [[[[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0, 0.0]]]]
    )
    raw = mip_level(derivatives, (8, 8))
    assert raw[0, 0, 0].item() == pytest.approx(3.0)
    assert raw[0, 0, 1].item() == -math.inf
    clamped = mip_level(derivatives, (8, 8), max_level=2)
    assert clamped.flatten().tolist() == [2.0, 0.0, 0.0]


def test_trilinear_blend_weights_follow_the_level_of_detail() -> None:
    # A pyramid whose level k is the constant k: the trilinear result is then exactly the
    # blend position, i.e. the level of detail clamped to [0, coarsest].
    tex = torch.rand(16, 16, 1)
    pyramid = [
        torch.full_like(level, float(number)) for number, level in enumerate(build_mip_pyramid(tex))
    ]
    generator = torch.Generator().manual_seed(10)
    uv = torch.rand(1, 8, 8, 2, generator=generator)
    # Derivatives spanning levels -2 .. 6 (texture has 5 levels, 0 .. 4), in random directions.
    scale = torch.exp2(torch.rand(1, 8, 8, 1, generator=generator) * 8.0 - 2.0) / 16.0
    direction = torch.randn(1, 8, 8, 4, generator=generator)
    derivatives = scale * direction / direction.norm(dim=-1, keepdim=True)
    lod = mip_level(derivatives, (16, 16))
    for max_mip_level, coarsest in [(None, 4), (2, 2), (0, 0), (9, 4)]:
        result = texture(
            tex, uv, derivatives, filter=TRILINEAR, max_mip_level=max_mip_level, mip_pyramid=pyramid
        )
        torch.testing.assert_close(result[..., 0], lod.clamp(0, coarsest), atol=1e-5, rtol=0)


def test_checkerboard_averages_to_half_above_level_zero() -> None:
    tex = checkerboard(8)
    rows, columns = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    uv = torch.stack([(columns + 0.5) / 8, (rows + 0.5) / 8], dim=-1).unsqueeze(0)
    for level in (1.0, 1.6, 2.5, 3.0, 7.0):
        step = 2.0**level / 8.0
        derivatives = constant_derivatives((1, 8, 8), step, 0.0, 0.0, step)
        result = texture(tex, uv, derivatives, filter=TRILINEAR)
        torch.testing.assert_close(result, torch.full_like(result, 0.5))
    # At level 0.25 the blend is 3/4 of the texel plus 1/4 of the level-1 average.
    step = 2.0**0.25 / 8.0
    derivatives = constant_derivatives((1, 8, 8), step, 0.0, 0.0, step)
    result = texture(tex, uv, derivatives, filter=TRILINEAR)
    torch.testing.assert_close(result, 0.75 * tex.unsqueeze(0) + 0.25 * 0.5)


@pytest.mark.parametrize("boundary", ["wrap", "clamp"])
def test_trilinear_matches_bilinear_of_the_selected_level(boundary: str) -> None:
    generator = torch.Generator().manual_seed(11)
    tex = torch.rand(2, 16, 8, 3, generator=generator)
    uv = torch.rand(2, 5, 5, 2, generator=generator) * 1.4 - 0.2
    levels = build_mip_pyramid(tex)
    tiny = constant_derivatives((2, 5, 5), 1e-6, 0.0, 0.0, 1e-6)
    torch.testing.assert_close(
        texture(tex, uv, tiny, filter=TRILINEAR, boundary=boundary),
        texture(tex, uv, filter="linear", boundary=boundary),
    )
    for number, level in enumerate(levels):
        # Longest axis (v, 16 texels) steps 2^number texels per pixel: the lod is `number`.
        derivatives = constant_derivatives((2, 5, 5), 0.0, 2.0**number / 16, 2.0**number / 32, 0.0)
        result = texture(tex, uv, derivatives, filter=TRILINEAR, boundary=boundary)
        expected = texture(level, uv, filter="linear", boundary=boundary)
        torch.testing.assert_close(result, expected, atol=1e-6, rtol=0)


def test_prebuilt_pyramid_gives_the_same_result_and_gradient() -> None:
    generator = torch.Generator().manual_seed(12)
    tex = torch.rand(8, 8, 3, generator=generator, requires_grad=True)
    uv = torch.rand(1, 4, 4, 2, generator=generator)
    derivatives = torch.rand(1, 4, 4, 4, generator=generator) * 0.4
    built = texture(tex, uv, derivatives, filter=TRILINEAR)
    (gradient_built,) = torch.autograd.grad(built.sum(), tex)
    reused = texture(tex, uv, derivatives, filter=TRILINEAR, mip_pyramid=build_mip_pyramid(tex))
    (gradient_reused,) = torch.autograd.grad(reused.sum(), tex)
    torch.testing.assert_close(built, reused)
    torch.testing.assert_close(gradient_built, gradient_reused)


# --- gradients ----------------------------------------------------------------------------------


@pytest.mark.parametrize("filter", ["linear", TRILINEAR])
@pytest.mark.parametrize("boundary", ["wrap", "clamp"])
@pytest.mark.parametrize(("channels", "tex_batch"), [(1, 0), (3, 2), (5, 1)])
def test_gradcheck_texture_and_uv(
    filter: str, boundary: str, channels: int, tex_batch: int
) -> None:
    height, width = 4, 6
    generator = torch.Generator().manual_seed(13)
    tex_shape = (
        (height, width, channels) if tex_batch == 0 else (tex_batch, height, width, channels)
    )
    tex = torch.rand(*tex_shape, dtype=torch.float64, generator=generator, requires_grad=True)
    low, high = (-0.6, 1.6) if boundary == "wrap" else (0.0, 1.0)
    uv = smooth_uv((2, 2, 3), (height, width), 4, low, high).requires_grad_()
    # Levels of detail between 0 and 2.5, so up to three levels take part.
    derivatives = torch.rand(2, 2, 3, 4, dtype=torch.float64, generator=generator) * 0.5
    assert torch.autograd.gradcheck(
        lambda t, c: texture(t, c, derivatives, filter=filter, boundary=boundary), (tex, uv)
    )


def test_gradcheck_nearest_texture() -> None:
    tex = torch.rand(2, 3, 4, 3, dtype=torch.float64, requires_grad=True)
    uv = smooth_uv((2, 3, 3), (3, 4), 1, -0.5, 1.5)
    assert torch.autograd.gradcheck(lambda t: texture(t, uv, filter="nearest"), (tex,))


def test_uv_gradient_is_the_texture_slope() -> None:
    # A ramp along u: value = x in texel units, so d/du = width inside the ramp's linear part.
    width = 8
    tex = (torch.arange(width, dtype=torch.float32).view(1, width, 1)).expand(3, width, 1).clone()
    uv = torch.tensor([[[[0.3, 0.5], [0.55, 0.2]]]], requires_grad=True)
    texture(tex, uv, boundary="clamp").sum().backward()
    torch.testing.assert_close(uv.grad, torch.tensor([[[[8.0, 0.0], [8.0, 0.0]]]]))


# --- bad input ----------------------------------------------------------------------------------


def good_inputs() -> dict:
    return {
        "tex": torch.rand(4, 4, 3),
        "uv": torch.rand(2, 3, 3, 2),
        "uv_derivatives": torch.rand(2, 3, 3, 4),
        "filter": TRILINEAR,
    }


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"tex": torch.rand(4, 4)}, ["tex", "[h, w, C]", "(4, 4)"]),
        ({"tex": torch.rand(1, 2, 4, 4, 3)}, ["tex", "[B, h, w, C]", "(1, 2, 4, 4, 3)"]),
        ({"tex": torch.zeros(4, 4, 3, dtype=torch.int64)}, ["tex", "floating", "int64"]),
        ({"tex": torch.rand(0, 4, 3)}, ["tex", ">= 1", "(0, 4, 3)"]),
        ({"tex": torch.rand(3, 4, 4, 3)}, ["tex", "batch 1 or 2", "3"]),
        ({"uv": torch.rand(3, 3, 2)}, ["uv", "[B, H, W, 2]", "(3, 3, 2)"]),
        ({"uv": torch.rand(2, 3, 3, 3)}, ["uv", "[B, H, W, 2]", "(2, 3, 3, 3)"]),
        ({"uv": torch.zeros(2, 3, 3, 2, dtype=torch.int32)}, ["uv", "floating", "int32"]),
        ({"uv": [[0.5, 0.5]]}, ["uv", "torch.Tensor", "list"]),
        ({"filter": "cubic"}, ["filter", "linear-mipmap-linear", "'cubic'"]),
        ({"boundary": "mirror"}, ["boundary", "clamp", "'mirror'"]),
        ({"uv_derivatives": None}, ["uv_derivatives", "[B, H, W, 4]", "None"]),
        (
            {"uv_derivatives": torch.rand(2, 3, 3, 2)},
            ["uv_derivatives", "[2, 3, 3, 4]", "[2, 3, 3, 2]"],
        ),
        (
            {"uv_derivatives": torch.zeros(2, 3, 3, 4, dtype=torch.int64)},
            ["uv_derivatives", "floating", "int64"],
        ),
        ({"max_mip_level": -1}, ["max_mip_level", ">= 0", "-1"]),
        ({"max_mip_level": 1.5}, ["max_mip_level", "int", "1.5"]),
        ({"mip_pyramid": [torch.rand(4, 4, 3)]}, ["mip_pyramid", "3 levels", "1"]),
        (
            {"mip_pyramid": [torch.rand(4, 4, 3), torch.rand(2, 3, 3), torch.rand(1, 1, 3)]},
            ["mip_pyramid[1]", "(2, 2, 3)", "(2, 3, 3)"],
        ),
    ],
)
def test_bad_input_raises_recon_error_naming_the_tensor(change: dict, words: list[str]) -> None:
    arguments = good_inputs() | change
    with pytest.raises(ReconError) as raised:
        texture(**arguments)
    message = str(raised.value)
    assert isinstance(raised.value, ValueError)
    assert "expected" in message and "got" in message
    for word in words:
        assert word in message, (word, message)


def test_bad_texture_in_build_mip_pyramid_raises() -> None:
    with pytest.raises(ReconError, match="tex"):
        build_mip_pyramid(torch.zeros(4, 4, 3, dtype=torch.uint8))
