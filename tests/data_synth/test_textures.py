"""Procedural textures and vertex colour fields: shape, range, determinism, periods."""

from __future__ import annotations

import pytest
import torch

from data_synth.shapes import make_shape
from data_synth.textures import (
    ALBEDO_MAX,
    ALBEDO_MIN,
    TEXTURES,
    VERTEX_FIELDS,
    checker,
    make_texture,
    noise,
    patches,
    stripes,
    vertex_color_field,
)
from recon.errors import ReconError

TEXTURE_NAMES = sorted(TEXTURES)
SEEDED_TEXTURES = ["noise", "patches"]
FIELD_NAMES = sorted(VERTEX_FIELDS)


def assert_albedo(image: torch.Tensor, shape: tuple[int, ...]) -> None:
    """float32 of ``shape``, finite, inside [0.05, 0.95], and not constant."""
    assert image.dtype == torch.float32
    assert tuple(image.shape) == shape
    assert bool(torch.isfinite(image).all())
    assert float(image.min()) >= ALBEDO_MIN - 1e-7
    assert float(image.max()) <= ALBEDO_MAX + 1e-7
    assert float(image.std()) > 0.05


@pytest.mark.parametrize("name", TEXTURE_NAMES)
def test_shape_dtype_and_range(name: str) -> None:
    assert_albedo(make_texture(name, size=64), (64, 64, 3))
    assert_albedo(make_texture(name, size=(32, 48)), (32, 48, 3))


@pytest.mark.parametrize("name", TEXTURE_NAMES)
def test_deterministic(name: str) -> None:
    assert torch.equal(make_texture(name, size=64, seed=3), make_texture(name, size=64, seed=3))


@pytest.mark.parametrize("name", SEEDED_TEXTURES)
def test_seeds_differ(name: str) -> None:
    first, second = make_texture(name, size=64, seed=0), make_texture(name, size=64, seed=1)
    assert float((first - second).abs().mean()) > 0.02


def test_checker_period() -> None:
    image = checker(size=64, squares=8)
    row = image[0, :, 0]
    # Squares of 8 pixels: constant inside, alternating between neighbours, period 16.
    for square in range(8):
        block = row[8 * square : 8 * square + 8]
        assert torch.all(block == block[0])
    assert row[0] != row[8]
    assert torch.equal(row[:48], row[16:64])
    assert torch.equal(image[:, 0], image[0, :])  # square cells: same pattern down the column
    assert not torch.equal(image[0], image[8])  # the next row of squares is shifted by one
    assert torch.equal(image[0], image[16])


def test_checker_colours() -> None:
    image = checker(size=16, squares=2, color_a=(0.2, 0.4, 0.6), color_b=(0.0, 1.0, 0.5))
    assert torch.allclose(image[0, 0], torch.tensor([0.2, 0.4, 0.6]))
    # Colours outside the albedo range are clipped into it.
    assert torch.allclose(image[0, 8], torch.tensor([0.05, 0.95, 0.5]))


def test_stripes_period_and_angle() -> None:
    vertical = stripes(size=64, count=4, angle_deg=0.0)
    assert torch.equal(vertical[0], vertical[63])  # every row alike: vertical bands
    row = vertical[0, :, 0]
    assert torch.all(row[:16] == row[0]) and row[15] != row[16]
    assert torch.equal(row[:32], row[32:])  # two colours cycle with period 2 stripes
    horizontal = stripes(size=64, count=4, angle_deg=90.0)
    assert torch.equal(horizontal[:, 0], horizontal[:, 63])
    three = stripes(size=60, count=3, colors=[(0.1, 0.1, 0.1), (0.5, 0.5, 0.5), (0.9, 0.9, 0.9)])
    assert len(torch.unique(three[..., 0])) == 3


def test_noise_is_smooth_and_tileable() -> None:
    image = noise(size=128, seed=5, octaves=3)
    inner_step = (image[:, 1:] - image[:, :-1]).abs().mean()
    wrap_step = (image[:, 0] - image[:, -1]).abs().mean()
    assert float(inner_step) < 0.05  # smooth: neighbouring pixels are close
    assert float(wrap_step) < 3 * float(inner_step)  # no jump across the wrap-around edge
    assert float((image[0] - image[-1]).abs().mean()) < 3 * float(inner_step)
    # More octaves add finer detail, i.e. larger pixel-to-pixel differences.
    detailed = noise(size=128, seed=5, octaves=6)
    assert float((detailed[:, 1:] - detailed[:, :-1]).abs().mean()) > float(inner_step)


def test_patches_are_piecewise_constant() -> None:
    image = patches(size=64, count=10, seed=2)
    colours = torch.unique(image.reshape(-1, 3), dim=0)
    assert 2 <= len(colours) <= 10


def test_make_texture_passes_params() -> None:
    assert torch.equal(make_texture("checker", size=32, squares=4), checker(size=32, squares=4))
    assert torch.equal(make_texture("noise", size=32, seed=7), noise(size=32, seed=7))


def test_unknown_texture_suggests_the_closest() -> None:
    with pytest.raises(ReconError) as error:
        make_texture("chcker")
    assert "did you mean 'checker'" in str(error.value)
    with pytest.raises(ReconError, match="squares"):
        make_texture("checker", squars=4)


def test_bad_texture_arguments_raise_recon_error() -> None:
    with pytest.raises(ReconError, match="size"):
        checker(size=0)
    with pytest.raises(ReconError, match="color_a"):
        checker(color_a=(2.0, 0.0, 0.0))
    with pytest.raises(ReconError, match="colors"):
        stripes(colors=[(0.5, 0.5, 0.5)])


@pytest.fixture(scope="module")
def shape_verts() -> torch.Tensor:
    return make_shape("dumbbell", resolution=24).verts


@pytest.mark.parametrize("name", FIELD_NAMES)
def test_vertex_color_field(name: str, shape_verts: torch.Tensor) -> None:
    colors = vertex_color_field(shape_verts, name, seed=4)
    assert_albedo(colors, (shape_verts.shape[0], 3))
    assert colors.device == shape_verts.device
    assert torch.equal(colors, vertex_color_field(shape_verts, name, seed=4))
    assert not torch.equal(colors, vertex_color_field(shape_verts, name, seed=5))


@pytest.mark.parametrize("name", FIELD_NAMES)
def test_vertex_color_field_depends_only_on_position(name: str, shape_verts: torch.Tensor) -> None:
    # The same points, in another order and fewer of them, get the same colours.
    subset = torch.flip(shape_verts[::3], dims=[0])
    colors = vertex_color_field(shape_verts, name, seed=1)
    assert torch.equal(vertex_color_field(subset, name, seed=1), torch.flip(colors[::3], dims=[0]))


def test_unknown_vertex_field_suggests_the_closest() -> None:
    with pytest.raises(ReconError, match="did you mean 'noise'"):
        vertex_color_field(torch.zeros(4, 3), "nosie")
    with pytest.raises(ReconError, match=r"\[V, 3\]"):
        vertex_color_field(torch.zeros(4, 2), "noise")
