"""Procedural albedo textures and per-vertex colour fields.

Every texture is a torch float32 tensor [h, w, 3] of linear albedo in [0.05, 0.95]: physically
plausible albedos, and never pure black or white, so that shading still carries a gradient and
nothing saturates. Row 0 is the top of the image (v = 0), matching recon's UV convention.

The seeded textures (``noise``, ``patches``) are tileable: they wrap around in both directions,
so UV seams that close around a shape (the torus, the sphere's u) show no discontinuity. For
meshes without UVs, ``vertex_color_field`` evaluates the same kinds of pattern in 3D at the
vertex positions.
"""

from __future__ import annotations

import difflib
import inspect
import math
from collections.abc import Callable, Sequence

import numpy as np
import scipy.ndimage
import scipy.spatial
import torch

from recon.errors import ReconError

ALBEDO_MIN = 0.05
ALBEDO_MAX = 0.95

Color = Sequence[float]

DEFAULT_COLOR_A: tuple[float, float, float] = (0.85, 0.6, 0.2)
DEFAULT_COLOR_B: tuple[float, float, float] = (0.1, 0.25, 0.6)


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _check_size(size: int | tuple[int, int], texture: str) -> tuple[int, int]:
    """(height, width) from an int (square) or a (height, width) pair; ReconError otherwise."""
    pair = (size, size) if isinstance(size, int | np.integer) else tuple(size)
    if len(pair) != 2 or not all(
        isinstance(side, int | np.integer) and not isinstance(side, bool) and side >= 1
        for side in pair
    ):
        raise ReconError(
            f"texture '{texture}': size: expected an int >= 1 or (height, width), got {size!r}"
        )
    return int(pair[0]), int(pair[1])


def _check_count(value: int, key: str, texture: str, minimum: int = 1) -> int:
    """Raise ReconError unless ``value`` is an int >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ReconError(f"texture '{texture}': {key}: expected an int >= {minimum}, got {value!r}")
    return int(value)


def _check_color(color: Color, key: str, texture: str) -> np.ndarray:
    """RGB [3] float64 from a colour in [0, 1], clipped to the albedo range [0.05, 0.95]."""
    array = np.asarray(color, dtype=np.float64)
    if array.shape != (3,) or not np.all(np.isfinite(array)) or array.min() < 0 or array.max() > 1:
        raise ReconError(
            f"texture '{texture}': {key}: expected an RGB triple in [0, 1], got {color!r}"
        )
    return np.clip(array, ALBEDO_MIN, ALBEDO_MAX)


def _to_albedo(image: np.ndarray) -> torch.Tensor:
    """torch float32 (contiguous) of ``image`` clipped to [0.05, 0.95]; any shape."""
    clipped = np.clip(image, ALBEDO_MIN, ALBEDO_MAX).astype(np.float32)
    return torch.from_numpy(np.ascontiguousarray(clipped))


def _squash(values: np.ndarray, gain: float = 3.0) -> np.ndarray:
    """Map values around 0.5 smoothly into (0.05, 0.95).

    A fixed curve, not a min-max stretch, so that the colour at a point does not depend on the
    image size or on which vertices were sampled.
    """
    half_range = 0.5 * (ALBEDO_MAX - ALBEDO_MIN)
    return 0.5 + half_range * np.tanh(gain * (values - 0.5))


def _pixel_centres(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) [h, w] each: pixel-centre texture coordinates in (0, 1), v = 0 at the top row."""
    v, u = np.meshgrid(
        (np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width, indexing="ij"
    )
    return u, v


def _unknown_name_error(kind: str, name: object, known: list[str]) -> ReconError:
    """ReconError naming the unknown ``name``, listing ``known`` and suggesting the closest."""
    message = f"unknown {kind} {name!r}; known {kind}s: {', '.join(sorted(known))}"
    close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.0)
    if close:
        message += f"; did you mean {close[0]!r}?"
    return ReconError(message)


def _check_params(kind: str, name: str, factory: Callable, params: dict, fixed: set[str]) -> None:
    """ReconError for a key of ``params`` that ``factory`` does not accept."""
    accepted = [key for key in inspect.signature(factory).parameters if key not in fixed]
    for key in params:
        if key not in accepted:
            suggestion = difflib.get_close_matches(key, accepted, n=1)
            hint = f"; did you mean {suggestion[0]!r}?" if suggestion else ""
            raise ReconError(
                f"{kind} {name!r}: unknown parameter {key!r}; accepted: "
                f"{', '.join(sorted(fixed) + accepted)}{hint}"
            )


# --------------------------------------------------------------------------------------------
# 2D textures
# --------------------------------------------------------------------------------------------


def checker(
    size: int | tuple[int, int] = 256,
    squares: int = 8,
    color_a: Color = DEFAULT_COLOR_A,
    color_b: Color = DEFAULT_COLOR_B,
) -> torch.Tensor:
    """Checkerboard with ``squares`` squares along each side; the top-left square is color_a.

    size: int or (height, width); a square is height / squares by width / squares pixels (exact
    when size is a multiple of squares). Colours are RGB in [0, 1], clipped to [0.05, 0.95].
    Returns [h, w, 3] float32.
    """
    height, width = _check_size(size, "checker")
    squares = _check_count(squares, "squares", "checker")
    first, second = (
        _check_color(color_a, "color_a", "checker"),
        _check_color(color_b, "color_b", "checker"),
    )
    # Integer arithmetic, so that square boundaries fall exactly on multiples of size / squares.
    row_cell = (np.arange(height) * squares) // height
    column_cell = (np.arange(width) * squares) // width
    odd = (row_cell[:, None] + column_cell[None, :]) % 2 == 1  # [h, w]
    return _to_albedo(np.where(odd[..., None], second, first))


def stripes(
    size: int | tuple[int, int] = 256,
    count: int = 8,
    angle_deg: float = 0.0,
    colors: Sequence[Color] = (DEFAULT_COLOR_A, DEFAULT_COLOR_B),
) -> torch.Tensor:
    """Parallel stripes cycling through ``colors``, ``count`` stripes across the texture.

    The stripe index is floor(count * (u cos(angle) + v sin(angle))) mod len(colors), with (u, v)
    the pixel centre in [0, 1]: angle_deg = 0 gives vertical bands of width / count pixels,
    90 horizontal bands (v grows downwards). Returns [h, w, 3] float32.
    """
    height, width = _check_size(size, "stripes")
    count = _check_count(count, "count", "stripes")
    if isinstance(colors, str) or len(colors) < 2:
        raise ReconError(f"texture 'stripes': colors: expected 2 or more RGB triples, got {colors}")
    palette = np.stack(
        [_check_color(color, f"colors[{index}]", "stripes") for index, color in enumerate(colors)]
    )
    if not math.isfinite(angle_deg):
        raise ReconError(f"texture 'stripes': angle_deg: expected a finite number, got {angle_deg}")
    u, v = _pixel_centres(height, width)
    angle = math.radians(angle_deg)
    coordinate = u * math.cos(angle) + v * math.sin(angle)
    index = np.floor(coordinate * count).astype(np.int64) % len(palette)
    return _to_albedo(palette[index])


def _periodic_value_noise(
    coordinates: np.ndarray, generator: np.random.Generator, cells: int, octaves: int, channels: int
) -> np.ndarray:
    """Sum over octaves of cubic-spline-interpolated random lattices, periodic with period 1.

    coordinates: [D, ...] points in lattice-period units (D = 2 or 3). Octave o uses a lattice of
    cells * 2^o values per axis and weight 2^-o. Returns [..., channels] with mean 0.5.
    """
    dimensions = coordinates.shape[0]
    total = np.zeros((*coordinates.shape[1:], channels))
    weight_sum = 0.0
    for octave in range(octaves):
        lattice_size = cells * 2**octave
        weight = 0.5**octave
        # Lattice values are node-centred ("grid" mode), so position x in [0, 1) maps to
        # x * lattice_size - 0.5 in index units; 'grid-wrap' makes the interpolation periodic.
        points = coordinates * lattice_size - 0.5
        for channel in range(channels):
            lattice = generator.uniform(0.0, 1.0, size=(lattice_size,) * dimensions)
            total[..., channel] += weight * scipy.ndimage.map_coordinates(
                lattice, points, order=3, mode="grid-wrap"
            )
        weight_sum += weight
    return total / weight_sum


def noise(
    size: int | tuple[int, int] = 256, seed: int = 0, octaves: int = 4, cells: int = 4
) -> torch.Tensor:
    """Smooth seeded colour value noise (fractal: octaves of random lattices), tileable.

    Each RGB channel is an independent sum of ``octaves`` cubic-spline-interpolated random
    lattices, the coarsest with ``cells`` values per side, each octave twice as fine and half as
    strong; the sum is squashed smoothly into [0.05, 0.95]. Returns [h, w, 3] float32.
    """
    height, width = _check_size(size, "noise")
    octaves = _check_count(octaves, "octaves", "noise")
    cells = _check_count(cells, "cells", "noise")
    u, v = _pixel_centres(height, width)
    generator = np.random.default_rng(seed)
    values = _periodic_value_noise(np.stack([v, u]), generator, cells, octaves, channels=3)
    return _to_albedo(_squash(values))


def patches(size: int | tuple[int, int] = 256, count: int = 24, seed: int = 0) -> torch.Tensor:
    """Voronoi patches: ``count`` random sites, each pixel takes its nearest site's colour.

    Distances wrap around the texture edges (a torus), so the patches tile seamlessly. Colours
    are uniform in [0.05, 0.95] per channel. Returns [h, w, 3] float32.
    """
    height, width = _check_size(size, "patches")
    count = _check_count(count, "count", "patches")
    generator = np.random.default_rng(seed)
    sites = generator.uniform(0.0, 1.0, size=(count, 2))  # (u, v) in [0, 1)
    colors = generator.uniform(ALBEDO_MIN, ALBEDO_MAX, size=(count, 3))
    u, v = _pixel_centres(height, width)
    tree = scipy.spatial.cKDTree(sites, boxsize=1.0)  # boxsize: periodic distances
    _, nearest = tree.query(np.stack([u.ravel(), v.ravel()], axis=1))
    return _to_albedo(colors[nearest].reshape(height, width, 3))


TEXTURES: dict[str, Callable[..., torch.Tensor]] = {
    "checker": checker,
    "stripes": stripes,
    "noise": noise,
    "patches": patches,
}
"""Texture name -> factory(size, ...) -> [h, w, 3] float32 linear albedo in [0.05, 0.95]."""


def make_texture(
    name: str, size: int | tuple[int, int] = 256, seed: int = 0, **params: object
) -> torch.Tensor:
    """Build the texture ``name`` (a key of TEXTURES): [h, w, 3] float32 in [0.05, 0.95].

    ``seed`` goes to the seeded textures (noise, patches); checker and stripes are deterministic
    patterns and ignore it. Raises ReconError for an unknown name (suggesting the closest) or an
    unknown parameter.
    """
    if name not in TEXTURES:
        raise _unknown_name_error("texture", name, list(TEXTURES))
    factory = TEXTURES[name]
    _check_params("texture", name, factory, params, fixed={"size", "seed"})
    if "seed" in inspect.signature(factory).parameters:
        params = {**params, "seed": seed}
    return factory(size=size, **params)


# --------------------------------------------------------------------------------------------
# 3D colour fields for meshes without UVs
# --------------------------------------------------------------------------------------------


def _field_checker(
    points: np.ndarray, generator: np.random.Generator, frequency: float
) -> np.ndarray:
    """3D checkerboard of cubes of side 2 / frequency, lattice offset by the seed; [V,3]."""
    offset = generator.uniform(0.0, 1.0, size=3)
    cell = np.floor((points + 1.0) * 0.5 * frequency + offset).astype(np.int64)
    odd = cell.sum(axis=1) % 2 == 1
    return np.where(odd[:, None], np.asarray(DEFAULT_COLOR_B), np.asarray(DEFAULT_COLOR_A))


def _field_stripes(
    points: np.ndarray, generator: np.random.Generator, frequency: float
) -> np.ndarray:
    """Planar slabs of width 2 / frequency along a seeded random direction; [V,3]."""
    direction = generator.normal(size=3)
    direction /= np.linalg.norm(direction)
    offset = generator.uniform(0.0, 1.0)
    index = np.floor((points @ direction + 1.0) * 0.5 * frequency + offset).astype(np.int64) % 2
    return np.stack([np.asarray(DEFAULT_COLOR_A), np.asarray(DEFAULT_COLOR_B)])[index]


def _field_noise(
    points: np.ndarray, generator: np.random.Generator, frequency: float
) -> np.ndarray:
    """3D colour value noise, ``frequency`` lattice cells across [-1, 1], 3 octaves; [V,3]."""
    cells = max(1, round(frequency))
    # Positions in [-1, 1] map to [0, 1) of one period, so the field does not repeat on the shape.
    coordinates = ((points + 1.0) * 0.5).T  # [3, V]
    values = _periodic_value_noise(coordinates, generator, cells, octaves=3, channels=3)
    return _squash(values)


def _field_patches(
    points: np.ndarray, generator: np.random.Generator, frequency: float
) -> np.ndarray:
    """3D Voronoi cells: about frequency^3 random sites in [-1, 1]^3, random colours; [V,3]."""
    count = max(2, round(frequency**3))
    sites = generator.uniform(-1.0, 1.0, size=(count, 3))
    colors = generator.uniform(ALBEDO_MIN, ALBEDO_MAX, size=(count, 3))
    _, nearest = scipy.spatial.cKDTree(sites).query(points)
    return colors[nearest]


VERTEX_FIELDS: dict[str, Callable[[np.ndarray, np.random.Generator, float], np.ndarray]] = {
    "checker": _field_checker,
    "stripes": _field_stripes,
    "noise": _field_noise,
    "patches": _field_patches,
}
"""Field name -> f(points [V,3] float64, generator, frequency) -> colours [V,3]."""


def vertex_color_field(
    verts: torch.Tensor, name: str = "noise", seed: int = 0, frequency: float = 4.0
) -> torch.Tensor:
    """Per-vertex albedo from a 3D pattern evaluated at the vertex positions.

    verts: [V, 3] positions (the built-in shapes lie in [-1, 1]^3). name: a key of VERTEX_FIELDS
    (the 3D versions of the textures); frequency: features across [-1, 1] (checker cubes,
    stripes, noise lattice cells; patches use about frequency^3 sites). The colour of a point
    depends only on its position, the seed and the frequency, not on the mesh resolution.
    Returns [V, 3] float32 in [0.05, 0.95] on verts' device.
    """
    if name not in VERTEX_FIELDS:
        raise _unknown_name_error("vertex color field", name, list(VERTEX_FIELDS))
    if not isinstance(verts, torch.Tensor) or verts.ndim != 2 or verts.shape[-1] != 3:
        shape = tuple(verts.shape) if isinstance(verts, torch.Tensor) else type(verts).__name__
        raise ReconError(f"vertex_color_field: verts: expected shape [V, 3], got {shape}")
    if not isinstance(frequency, int | float) or not math.isfinite(frequency) or frequency <= 0:
        raise ReconError(
            f"vertex_color_field: frequency: expected a finite number > 0, got {frequency!r}"
        )
    points = verts.detach().to("cpu", torch.float64).numpy()
    generator = np.random.default_rng(seed)
    colors = VERTEX_FIELDS[name](points, generator, float(frequency))
    return _to_albedo(colors).to(verts.device)
