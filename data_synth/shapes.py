"""Built-in procedural shapes, so that the project needs no downloaded mesh.

Every shape is a closed, manifold, consistently outward-oriented triangle mesh (counter-clockwise
seen from outside) with vertices shared by index, centred at the origin and fitting inside the
unit sphere (bounding radius about 0.85). ``SHAPE_GENUS`` states each shape's genus, so that
V - E + F = 2 - 2 * genus.

``resolution`` has one meaning for every shape: the vertex spacing is about 2 / resolution, i.e.
roughly ``resolution`` samples across the [-1, 1] cube. For the SDF shapes it is exactly the number
of marching-cubes cells per axis over [-1, 1].

Shapes and what they exercise:

- ``sphere``: icosphere, genus 0, smooth; equirectangular UVs split along a cut meridian.
- ``torus``: genus 1, smooth; parametric UVs on their own index buffer (seam-split UVs, shared
  positions).
- ``rounded_box``: genus 0, flat sides meeting at sharp (90 degree) edges and corners, softened by
  a narrow bevel so that vertex normals stay well defined.
- ``dumbbell``: genus 0, two balls joined by a thin rod (radius 0.08); SDF + marching cubes.
- ``double_torus``: genus 2; SDF + marching cubes.
- ``blob``: genus 0, smooth, a sphere radially displaced by seeded low-frequency sinusoids; it
  keeps the sphere's UVs.
"""

from __future__ import annotations

import difflib
import inspect
import math
from collections.abc import Callable

import numpy as np
import skimage.measure
import torch
import trimesh

from recon.errors import ReconError
from recon.mesh.mesh import Mesh

DEFAULT_RESOLUTION = 64
"""Default samples across [-1, 1]: about 5k-12k faces per shape, each built well under a second."""

MINIMUM_RESOLUTION = 8
MAXIMUM_RESOLUTION = 512


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _check_resolution(resolution: int, shape: str) -> float:
    """Validate ``resolution`` and return the target vertex spacing 2 / resolution."""
    if isinstance(resolution, bool) or not isinstance(resolution, int | np.integer):
        raise ReconError(
            f"shape '{shape}': resolution: expected an int, got {type(resolution).__name__}"
        )
    if not MINIMUM_RESOLUTION <= resolution <= MAXIMUM_RESOLUTION:
        raise ReconError(
            f"shape '{shape}': resolution: expected {MINIMUM_RESOLUTION}..{MAXIMUM_RESOLUTION}, "
            f"got {resolution}"
        )
    return 2.0 / float(resolution)


def _check_positive(value: float, key: str, shape: str) -> float:
    """Raise ReconError unless ``value`` is a finite number > 0."""
    if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ReconError(f"shape '{shape}': {key}: expected a finite number > 0, got {value!r}")
    return float(value)


def _check_bounded(verts: np.ndarray, shape: str) -> None:
    """Raise ReconError if user parameters pushed the shape out of the unit sphere."""
    radius = float(np.linalg.norm(verts, axis=1).max())
    if radius > 1.0:
        raise ReconError(
            f"shape '{shape}': expected the shape to fit inside the unit sphere, "
            f"got bounding radius {radius:.3f}; reduce its size parameters"
        )


def _to_mesh(
    verts: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray | None = None,
    uv_faces: np.ndarray | None = None,
) -> Mesh:
    """Wrap numpy arrays (verts [V,3], faces [F,3], uvs [T,2], uv_faces [F,3]) into a Mesh."""

    def index_tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.int64))

    def float_tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))

    return Mesh(
        verts=float_tensor(verts),
        faces=index_tensor(faces),
        uvs=None if uvs is None else float_tensor(uvs),
        uv_faces=None if uv_faces is None else index_tensor(uv_faces),
    )


def _rotation_between(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation matrix [3,3] taking unit vector ``source`` onto unit vector ``target``."""
    axis = np.cross(source, target)
    sine = float(np.linalg.norm(axis))
    cosine = float(np.dot(source, target))
    if sine < 1e-12:
        if cosine > 0:
            return np.eye(3)
        # Antiparallel: half-turn about any axis perpendicular to source.
        helper = np.array([1.0, 0.0, 0.0]) if abs(source[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(source, helper)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    axis = axis / sine
    cross_matrix = np.array(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]]
    )
    return np.eye(3) + sine * cross_matrix + (1.0 - cosine) * (cross_matrix @ cross_matrix)


def _rotation_about_z(angle: float) -> np.ndarray:
    """Rotation matrix [3,3] by ``angle`` radians about +z."""
    cosine, sine = math.cos(angle), math.sin(angle)
    return np.array([[cosine, -sine, 0.0], [sine, cosine, 0.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------
# Icosphere with an equirectangular UV seam
# --------------------------------------------------------------------------------------------


def _icosphere_subdivisions(spacing: float, radius: float) -> int:
    """Finest subdivision level whose edges are no shorter than ``spacing`` on ``radius``."""
    # The icosahedron inscribed in the unit sphere has edge 1.0515; each subdivision halves it.
    # Rounding down keeps the face count in the same range as the other shapes (each level is 4x).
    return int(np.clip(math.floor(math.log2(1.0515 * radius / spacing)), 1, 7))


def _split_polygon(polygon: list[int], on_seam: list[bool], positions: np.ndarray) -> list[tuple]:
    """Triangles covering a convex face polygon, cut along the chord between its two seam points.

    polygon: vertex indices in the face's counter-clockwise order (3 to 5 of them); on_seam: which
    of them lie on the seam; positions: [N, 3] for every index. Sub-polygons keep the cyclic
    order, so the winding is kept; a quad is split on its shorter diagonal.
    """
    seam_corners = [corner for corner, flag in enumerate(on_seam) if flag]
    count = len(polygon)
    pieces = [polygon]
    if len(seam_corners) == 2:
        first, second = seam_corners
        if (second - first) % count not in (1, count - 1):
            pieces = [polygon[first : second + 1], polygon[second:] + polygon[: first + 1]]
    triangles: list[tuple] = []
    for piece in pieces:
        if len(piece) == 3:
            triangles.append(tuple(piece))
        elif len(piece) == 4:
            a, b, c, d = piece
            if np.linalg.norm(positions[a] - positions[c]) <= np.linalg.norm(
                positions[b] - positions[d]
            ):
                triangles += [(a, b, c), (a, c, d)]
            else:
                triangles += [(a, b, d), (b, c, d)]
        else:
            raise RuntimeError(f"icosphere seam: unexpected {len(piece)}-sided piece")
    return triangles


def _unit_icosphere_with_seam(
    subdivisions: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unit icosphere cut along a meridian, with equirectangular UVs.

    Returns verts [V,3] float64 on the unit sphere, faces [F,3] int64 (outward), uvs [T,2] and
    uv_faces [F,3]. u = longitude / (2 pi) + 1/2 in [0, 1], v = polar angle / pi (v = 0 at the
    north pole, the top of the image). The mesh is made to follow the seam meridian exactly
    (positions stay shared; only the seam's UVs are duplicated at u = 0 and u = 1), so no UV
    triangle wraps around the texture and no wrap-around sampling is needed.
    """
    icosphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    verts = np.asarray(icosphere.vertices, dtype=np.float64)
    faces = np.asarray(icosphere.faces, dtype=np.int64)
    edges = np.unique(
        np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1),
        axis=0,
    )
    edge_length = float(np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1).mean())

    # Put a vertex exactly on each pole: UVs are singular there, and a pole vertex confines the
    # singularity to the one-ring of triangles around it.
    verts = verts @ _rotation_between(verts[0], np.array([0.0, 0.0, 1.0])).T
    north, south = int(np.argmax(verts[:, 2])), int(np.argmin(verts[:, 2]))
    is_pole = np.zeros(len(verts), dtype=bool)
    is_pole[[north, south]] = True
    # Turn the seam (longitude pi, the half-plane y = 0, x < 0) into the widest gap between
    # vertex longitudes, so that few vertices need the snapping below.
    longitudes = np.sort(np.arctan2(verts[~is_pole, 1], verts[~is_pole, 0]))
    gaps = np.diff(np.append(longitudes, longitudes[0] + 2.0 * math.pi))
    widest = int(np.argmax(gaps))
    verts = verts @ _rotation_about_z(math.pi - longitudes[widest] - 0.5 * gaps[widest]).T
    verts[north] = (0.0, 0.0, 1.0)
    verts[south] = (0.0, 0.0, -1.0)

    # Snap vertices within a quarter edge of the seam onto it (same latitude): cutting an edge
    # close to its end would leave a sliver triangle, so the seam passes through them instead.
    # A triangle is wider than half an edge in every direction, so no face gets three snaps.
    is_seam = (verts[:, 0] < 0) & (np.abs(verts[:, 1]) < 0.25 * edge_length) & ~is_pole
    verts[is_seam, 0] = -np.hypot(verts[is_seam, 0], verts[is_seam, 1])
    verts[is_seam, 1] = 0.0
    # Side of the seam plane y = 0 (poles and seam vertices lie on it).
    side = np.where(verts[:, 1] >= 0, 1, -1)
    side[is_pole | is_seam] = 0

    # Each edge between opposite sides that meets y = 0 at x < 0 gets a new seam vertex there
    # (a quarter edge or more from both ends, thanks to the snapping).
    seam_points: dict[tuple[int, int], int] = {}
    new_verts: list[np.ndarray] = []

    def crossing(first: int, second: int) -> int | None:
        """Index of the new seam vertex on edge (first, second), or None if it does not cross."""
        key = (min(first, second), max(first, second))
        if key in seam_points:
            return seam_points[key]
        if side[first] * side[second] >= 0:
            return None
        y_first, y_second = verts[first, 1], verts[second, 1]
        point = verts[first] + y_first / (y_first - y_second) * (verts[second] - verts[first])
        if point[0] >= 0:
            return None  # crosses the opposite meridian, which is not cut
        point[1] = 0.0
        seam_points[key] = len(verts) + len(new_verts)
        new_verts.append(point / np.linalg.norm(point))
        return seam_points[key]

    polygons: list[list[int]] = []
    for face in faces.tolist():
        polygon: list[int] = []
        for corner in range(3):
            polygon.append(face[corner])
            point = crossing(face[corner], face[(corner + 1) % 3])
            if point is not None:
                polygon.append(point)
        polygons.append(polygon)

    verts = np.concatenate([verts, np.asarray(new_verts).reshape(-1, 3)], axis=0)
    is_pole = np.append(is_pole, np.zeros(len(new_verts), dtype=bool))
    is_seam = np.append(is_seam, np.ones(len(new_verts), dtype=bool))
    side = np.append(side, np.zeros(len(new_verts), dtype=side.dtype))
    output_faces: list[tuple] = []
    for polygon in polygons:
        on_seam = [bool(is_pole[index] or is_seam[index]) for index in polygon]
        output_faces += _split_polygon(polygon, on_seam, verts)
    faces = np.asarray(output_faces, dtype=np.int64)

    longitude = np.arctan2(verts[:, 1], verts[:, 0])
    corner_u = (longitude[faces] + math.pi) / (2.0 * math.pi)  # [F, 3]
    corner_v = np.arccos(np.clip(verts[faces, 2], -1.0, 1.0)) / math.pi  # [F, 3]
    # Every face has a corner off the seam plane; its side says whether the face's seam corners
    # are at u = 1 (y > 0, longitude near +pi) or at u = 0 (y < 0, longitude near -pi).
    face_side = side[faces][np.arange(len(faces)), np.argmax(side[faces] != 0, axis=1)]
    if np.any(face_side == 0):
        raise RuntimeError("icosphere seam: a face lies entirely on the seam plane")
    seam_u = np.where(face_side > 0, 1.0, 0.0)[:, None]
    corner_u = np.where(is_seam[faces], seam_u, corner_u)
    # A pole has no longitude: give it the mean u of the face's other corners, the usual choice.
    pole_corner = is_pole[faces]
    other_mean = (corner_u * ~pole_corner).sum(axis=1, keepdims=True) / 2.0
    corner_u = np.where(pole_corner, other_mean, corner_u)

    # One UV per distinct (vertex, u, v): shared away from the seam and the poles.
    keys = np.stack([faces.astype(np.float64), corner_u, corner_v], axis=-1).reshape(-1, 3)
    unique_keys, inverse = np.unique(keys, axis=0, return_inverse=True)
    uvs = unique_keys[:, 1:]
    uv_faces = inverse.reshape(faces.shape).astype(np.int64)
    return verts, faces, uvs, uv_faces


def sphere(resolution: int = DEFAULT_RESOLUTION, radius: float = 0.9) -> Mesh:
    """Icosphere of ``radius`` (genus 0, smooth) with equirectangular seam-split UVs.

    Returns a Mesh: verts [V,3], faces [F,3], uvs [T,2], uv_faces [F,3].
    """
    spacing = _check_resolution(resolution, "sphere")
    radius = _check_positive(radius, "radius", "sphere")
    verts, faces, uvs, uv_faces = _unit_icosphere_with_seam(
        _icosphere_subdivisions(spacing, radius)
    )
    verts = verts * radius
    _check_bounded(verts, "sphere")
    return _to_mesh(verts, faces, uvs, uv_faces)


def blob(
    resolution: int = DEFAULT_RESOLUTION,
    seed: int = 0,
    amplitude: float = 0.15,
    waves: int = 5,
    radius: float = 0.9,
) -> Mesh:
    """Sphere radially displaced by ``waves`` seeded low-frequency sinusoids (genus 0, smooth).

    The surface is r(d) = 1 + sum_k a_k sin(f_k <w_k, d> + phase_k) along each unit direction d,
    with random unit w_k, frequencies f_k in [1.5, 3.5] and amplitudes summing to ``amplitude``,
    then scaled so that its farthest point lies at ``radius``. A radial graph over the sphere
    with r > 0 cannot self-intersect, so it stays a closed genus-0 surface. Keeps the sphere's
    seam-split UVs. Returns a Mesh: verts [V,3], faces [F,3], uvs [T,2], uv_faces [F,3].
    """
    spacing = _check_resolution(resolution, "blob")
    radius = _check_positive(radius, "radius", "blob")
    if not isinstance(amplitude, int | float) or not 0.0 <= amplitude < 0.5:
        raise ReconError(f"shape 'blob': amplitude: expected a number in [0, 0.5), got {amplitude}")
    if isinstance(waves, bool) or not isinstance(waves, int) or waves < 1:
        raise ReconError(f"shape 'blob': waves: expected an int >= 1, got {waves!r}")
    directions, faces, uvs, uv_faces = _unit_icosphere_with_seam(
        _icosphere_subdivisions(spacing, radius)
    )
    generator = np.random.default_rng(seed)
    wave_directions = generator.normal(size=(waves, 3))
    wave_directions /= np.linalg.norm(wave_directions, axis=1, keepdims=True)
    frequencies = generator.uniform(1.5, 3.5, size=waves)
    phases = generator.uniform(0.0, 2.0 * math.pi, size=waves)
    weights = generator.uniform(0.5, 1.0, size=waves)
    amplitudes = amplitude * weights / weights.sum()
    projections = directions @ wave_directions.T  # [V, waves]
    radial = 1.0 + (amplitudes * np.sin(frequencies * projections + phases)).sum(axis=1)
    verts = directions * radial[:, None]
    # The displacement shifts the bounding box; recentre it before sizing to ``radius``.
    verts -= 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    verts *= radius / np.linalg.norm(verts, axis=1).max()
    return _to_mesh(verts, faces, uvs, uv_faces)


# --------------------------------------------------------------------------------------------
# Torus with parametric UVs
# --------------------------------------------------------------------------------------------


def torus(
    resolution: int = DEFAULT_RESOLUTION,
    major_radius: float = 0.6,
    minor_radius: float = 0.25,
) -> Mesh:
    """Ring torus about the z axis (genus 1, smooth) with parametric UVs.

    Position index i * minor_segments + j is the point at angle 2 pi i / major_segments around z
    and 2 pi j / minor_segments around the tube. Positions are shared by index across both seams;
    the UVs live on their own (major_segments + 1) x (minor_segments + 1) grid, so the seams are
    split only in UV space: u = i / major_segments, v = j / minor_segments, both covering [0, 1].
    Returns a Mesh: verts [V,3], faces [F,3], uvs [T,2], uv_faces [F,3].
    """
    spacing = _check_resolution(resolution, "torus")
    major_radius = _check_positive(major_radius, "major_radius", "torus")
    minor_radius = _check_positive(minor_radius, "minor_radius", "torus")
    if minor_radius >= major_radius:
        raise ReconError(
            f"shape 'torus': minor_radius: expected < major_radius ({major_radius}) for a ring "
            f"torus, got {minor_radius}"
        )
    major_segments = max(8, round(2.0 * math.pi * major_radius / spacing))
    minor_segments = max(4, round(2.0 * math.pi * minor_radius / spacing))

    around = 2.0 * math.pi * np.arange(major_segments) / major_segments  # [M]
    tube = 2.0 * math.pi * np.arange(minor_segments) / minor_segments  # [N]
    ring = major_radius + minor_radius * np.cos(tube)  # [N]
    verts = np.stack(
        [
            np.cos(around)[:, None] * ring[None, :],
            np.sin(around)[:, None] * ring[None, :],
            np.broadcast_to(minor_radius * np.sin(tube)[None, :], (major_segments, minor_segments)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    _check_bounded(verts, "torus")

    major_index, minor_index = np.meshgrid(
        np.arange(major_segments), np.arange(minor_segments), indexing="ij"
    )
    major_index, minor_index = major_index.ravel(), minor_index.ravel()

    def quads(rows: int, columns: int, wrap: bool) -> np.ndarray:
        """Faces [2*M*N, 3] over a grid of rows x columns points (wrapping or not)."""
        i0, j0 = major_index, minor_index
        i1, j1 = i0 + 1, j0 + 1
        if wrap:
            i1, j1 = i1 % rows, j1 % columns
        corner_00, corner_10 = i0 * columns + j0, i1 * columns + j0
        corner_11, corner_01 = i1 * columns + j1, i0 * columns + j1
        # d/d(around) x d/d(tube) points outward, so (00, 10, 11) is counter-clockwise outside.
        return np.concatenate(
            [
                np.stack([corner_00, corner_10, corner_11], axis=1),
                np.stack([corner_00, corner_11, corner_01], axis=1),
            ]
        )

    faces = quads(major_segments, minor_segments, wrap=True)
    uv_faces = quads(major_segments + 1, minor_segments + 1, wrap=False)
    u_grid, v_grid = np.meshgrid(
        np.linspace(0.0, 1.0, major_segments + 1),
        np.linspace(0.0, 1.0, minor_segments + 1),
        indexing="ij",
    )
    uvs = np.stack([u_grid.ravel(), v_grid.ravel()], axis=1)
    return _to_mesh(verts, faces, uvs, uv_faces)


# --------------------------------------------------------------------------------------------
# Rounded box
# --------------------------------------------------------------------------------------------


def _box_axis_coordinates(
    half_extent: float, bevel_radius: float, bevel_steps: int, spacing: float
) -> np.ndarray:
    """Grid coordinates [n] along one box axis, from -half_extent to +half_extent.

    The flat part is sampled uniformly at about ``spacing``; each bevel band of width
    ``bevel_radius`` gets ``bevel_steps`` samples at offsets bevel_radius * tan(alpha) with alpha
    uniform in (0, 45 degrees], which the rounding map below turns into equal angular steps.
    """
    inner = half_extent - bevel_radius
    segments = max(1, round(2.0 * inner / spacing))
    coordinates = np.linspace(-inner, inner, segments + 1)
    if bevel_radius > 0:
        angles = np.linspace(0.0, math.pi / 4.0, bevel_steps + 1)[1:]
        offsets = bevel_radius * np.tan(angles)
        coordinates = np.concatenate([-inner - offsets[::-1], coordinates, inner + offsets])
    # Exact ends, so that points of adjacent box faces coincide bit for bit and merge.
    coordinates[0], coordinates[-1] = -half_extent, half_extent
    return coordinates


def rounded_box(
    resolution: int = DEFAULT_RESOLUTION,
    half_extents: tuple[float, float, float] = (0.6, 0.45, 0.35),
    bevel_radius: float = 0.03,
    bevel_steps: int = 1,
) -> Mesh:
    """Box with flat sides and sharp 90-degree edges and corners (genus 0).

    Each box edge is rounded with a cylinder of ``bevel_radius`` sampled at 2 * ``bevel_steps``
    segments (the default one step per side makes a narrow 45-degree chamfer, about one vertex
    spacing wide: a sharp feature at working scale that still has well-defined vertex normals).
    ``bevel_radius=0`` gives exact 90-degree dihedral edges. Unequal default half extents avoid the
    cube's rotational symmetries, so pose stays identifiable.

    Built as a grid on the box surface, with the rounding map p -> clamp(p, -inner, inner)
    + bevel_radius * normalize(p - clamp(p, -inner, inner)) (inner = half_extents - bevel_radius),
    which is the identity on the flat parts. Returns a Mesh: verts [V,3], faces [F,3], no UVs.
    """
    spacing = _check_resolution(resolution, "rounded_box")
    if len(half_extents) != 3:
        raise ReconError(
            f"shape 'rounded_box': half_extents: expected 3 numbers, got {half_extents!r}"
        )
    extents = np.array([_check_positive(e, "half_extents", "rounded_box") for e in half_extents])
    if not isinstance(bevel_radius, int | float) or not 0.0 <= bevel_radius < extents.min():
        raise ReconError(
            f"shape 'rounded_box': bevel_radius: expected a number in [0, {extents.min()}), "
            f"got {bevel_radius!r}"
        )
    if isinstance(bevel_steps, bool) or not isinstance(bevel_steps, int) or bevel_steps < 1:
        raise ReconError(
            f"shape 'rounded_box': bevel_steps: expected an int >= 1, got {bevel_steps!r}"
        )
    axis_coordinates = [
        _box_axis_coordinates(float(e), float(bevel_radius), bevel_steps, spacing) for e in extents
    ]

    points: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    offset = 0
    for normal_axis in range(3):
        # (first, second, normal) is a cyclic permutation of (x, y, z), so first x second = normal.
        first, second = (normal_axis + 1) % 3, (normal_axis + 2) % 3
        first_values, second_values = axis_coordinates[first], axis_coordinates[second]
        rows, columns = len(first_values), len(second_values)
        grid_first, grid_second = np.meshgrid(first_values, second_values, indexing="ij")
        i, j = np.meshgrid(np.arange(rows - 1), np.arange(columns - 1), indexing="ij")
        corner_00 = (i * columns + j).ravel()
        corner_10 = ((i + 1) * columns + j).ravel()
        corner_11 = ((i + 1) * columns + j + 1).ravel()
        corner_01 = (i * columns + j + 1).ravel()
        quads = np.concatenate(
            [
                np.stack([corner_00, corner_10, corner_11], axis=1),
                np.stack([corner_00, corner_11, corner_01], axis=1),
            ]
        )
        for sign in (1.0, -1.0):
            side = np.empty((rows * columns, 3))
            side[:, normal_axis] = sign * extents[normal_axis]
            side[:, first] = grid_first.ravel()
            side[:, second] = grid_second.ravel()
            points.append(side)
            # The grid's own winding faces +normal; reverse it on the negative side.
            faces.append(offset + (quads if sign > 0 else quads[:, ::-1]))
            offset += len(side)

    all_points = np.concatenate(points)
    all_faces = np.concatenate(faces)
    # Box-edge points repeat exactly (same coordinate arrays), so exact merging shares them.
    verts, inverse = np.unique(all_points, axis=0, return_inverse=True)
    all_faces = inverse.reshape(-1)[all_faces]

    if bevel_radius > 0:
        inner = extents - bevel_radius
        clamped = np.clip(verts, -inner, inner)
        outward = verts - clamped
        verts = clamped + bevel_radius * outward / np.linalg.norm(outward, axis=1, keepdims=True)
    _check_bounded(verts, "rounded_box")
    return _to_mesh(verts, all_faces)


# --------------------------------------------------------------------------------------------
# Signed-distance shapes (marching cubes)
# --------------------------------------------------------------------------------------------


def _smooth_union(first: np.ndarray, second: np.ndarray, blend: float) -> np.ndarray:
    """Polynomial smooth minimum of two SDFs; ``blend`` is the width of the fillet."""
    if blend <= 0:
        return np.minimum(first, second)
    weight = np.clip(0.5 + 0.5 * (second - first) / blend, 0.0, 1.0)
    return second + (first - second) * weight - blend * weight * (1.0 - weight)


def _torus_distance(points: np.ndarray, major_radius: float, minor_radius: float) -> np.ndarray:
    """SDF [N] of a torus about z at the origin for points [N,3]."""
    ring = np.hypot(points[:, 0], points[:, 1]) - major_radius
    return np.hypot(ring, points[:, 2]) - minor_radius


def _mesh_from_sdf(
    distance: Callable[[np.ndarray], np.ndarray], resolution: int, shape: str, genus: int
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of ``distance`` (points [N,3] -> SDF [N], negative inside) over [-1, 1]^3.

    Returns verts [V,3] and outward faces [F,3]: duplicate vertices merged, degenerate faces
    removed, one connected component of the given ``genus`` (else ReconError).
    """
    spacing = _check_resolution(resolution, shape)
    axis = np.linspace(-1.0, 1.0, resolution + 1)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1)
    values = distance(grid.reshape(-1, 3)).reshape(grid.shape[:3])
    boundary = np.concatenate(
        [values[[0, -1]].ravel(), values[:, [0, -1]].ravel(), values[:, :, [0, -1]].ravel()]
    )
    if boundary.min() <= 0:
        # A surface cut open by the grid boundary would not be closed.
        raise ReconError(
            f"shape '{shape}': expected the shape inside [-1, 1]^3, got it reaching the boundary"
        )
    # Marching cubes puts a vertex where the SDF crosses zero along a grid edge; a grid value at
    # (nearly) zero puts it at the grid point, collapsing triangles into slivers or zero area.
    # Holding grid values a tenth of a cell off zero moves the surface by at most that much
    # (0.003 at the default resolution) and keeps vertices about a tenth of a cell from grid
    # points, hence smallest triangle angles of about 7 degrees instead of about 1.
    margin = 0.1 * spacing
    values = np.where(np.abs(values) < margin, np.where(values < 0, -margin, margin), values)
    verts, faces, _, _ = skimage.measure.marching_cubes(
        values.astype(np.float64), level=0.0, spacing=(spacing, spacing, spacing)
    )
    verts = verts - 1.0
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=True)  # merges duplicates
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        # The marching-cubes winding depends on the sign convention; make it CCW from outside.
        mesh.invert()
    # A too coarse grid can cut a thin part or close a hole: refuse rather than return a shape
    # of another topology than SHAPE_GENUS states.
    euler = len(mesh.vertices) - len(mesh.edges_unique) + len(mesh.faces)
    if not (
        mesh.is_watertight
        and mesh.is_winding_consistent
        and mesh.body_count == 1
        and euler == 2 - 2 * genus
    ):
        raise ReconError(
            f"shape '{shape}': marching cubes at resolution {resolution}: expected one closed "
            f"manifold surface of genus {genus}, got watertight={mesh.is_watertight}, "
            f"bodies={mesh.body_count}, Euler characteristic {euler}; raise the resolution "
            f"or thicken the shape"
        )
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)


def dumbbell(
    resolution: int = DEFAULT_RESOLUTION,
    ball_radius: float = 0.32,
    rod_radius: float = 0.08,
    separation: float = 1.04,
    blend: float = 0.08,
) -> Mesh:
    """Two balls on the x axis joined by a thin rod (genus 0): a thin part for the optimiser.

    Balls of ``ball_radius`` centred ``separation`` apart, rod (a capsule) of ``rod_radius``,
    joined by a smooth union with fillet width ``blend``. Keep rod_radius >= 1.5 * 2 / resolution
    so that marching cubes resolves the rod. Returns a Mesh: verts [V,3], faces [F,3], no UVs.
    """
    ball_radius = _check_positive(ball_radius, "ball_radius", "dumbbell")
    rod_radius = _check_positive(rod_radius, "rod_radius", "dumbbell")
    separation = _check_positive(separation, "separation", "dumbbell")
    blend = float(blend)
    half = 0.5 * separation

    def distance(points: np.ndarray) -> np.ndarray:
        left = np.linalg.norm(points - np.array([-half, 0.0, 0.0]), axis=1) - ball_radius
        right = np.linalg.norm(points - np.array([half, 0.0, 0.0]), axis=1) - ball_radius
        along = np.clip(points[:, 0], -half, half)
        rod = np.linalg.norm(points - np.stack([along, 0 * along, 0 * along], axis=1), axis=1)
        rod = rod - rod_radius
        return _smooth_union(_smooth_union(left, rod, blend), right, blend)

    verts, faces = _mesh_from_sdf(distance, resolution, "dumbbell", genus=0)
    _check_bounded(verts, "dumbbell")
    return _to_mesh(verts, faces)


def double_torus(
    resolution: int = DEFAULT_RESOLUTION,
    major_radius: float = 0.33,
    minor_radius: float = 0.14,
    separation: float = 0.8,
    blend: float = 0.1,
) -> Mesh:
    """Two tori side by side on the x axis, fused in the middle (genus 2).

    Tori about z with ``major_radius`` / ``minor_radius``, centres ``separation`` apart; the tubes
    overlap where they meet (separation < 2 * (major_radius + minor_radius)) while the holes stay
    open. Smooth union with fillet width ``blend``. Returns a Mesh: verts [V,3], faces [F,3],
    no UVs.
    """
    major_radius = _check_positive(major_radius, "major_radius", "double_torus")
    minor_radius = _check_positive(minor_radius, "minor_radius", "double_torus")
    separation = _check_positive(separation, "separation", "double_torus")
    if minor_radius >= major_radius:
        raise ReconError(
            f"shape 'double_torus': minor_radius: expected < major_radius ({major_radius}), "
            f"got {minor_radius}"
        )
    if not 2 * (major_radius - minor_radius) < separation < 2 * (major_radius + minor_radius):
        raise ReconError(
            f"shape 'double_torus': separation: expected in "
            f"({2 * (major_radius - minor_radius)}, {2 * (major_radius + minor_radius)}) so that "
            f"the tori fuse without closing their holes, got {separation}"
        )
    half = 0.5 * separation
    blend = float(blend)

    def distance(points: np.ndarray) -> np.ndarray:
        shift = np.array([half, 0.0, 0.0])
        left = _torus_distance(points + shift, major_radius, minor_radius)
        right = _torus_distance(points - shift, major_radius, minor_radius)
        return _smooth_union(left, right, blend)

    verts, faces = _mesh_from_sdf(distance, resolution, "double_torus", genus=2)
    _check_bounded(verts, "double_torus")
    return _to_mesh(verts, faces)


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

SHAPES: dict[str, Callable[..., Mesh]] = {
    "sphere": sphere,
    "torus": torus,
    "rounded_box": rounded_box,
    "dumbbell": dumbbell,
    "double_torus": double_torus,
    "blob": blob,
}
"""Shape name -> factory(resolution: int = DEFAULT_RESOLUTION, **params) -> Mesh."""

SHAPE_GENUS: dict[str, int] = {
    "sphere": 0,
    "torus": 1,
    "rounded_box": 0,
    "dumbbell": 0,
    "double_torus": 2,
    "blob": 0,
}
"""Shape name -> genus of the surface (V - E + F = 2 - 2 * genus)."""


def _unknown_name_error(kind: str, name: object, known: list[str]) -> ReconError:
    """ReconError naming the unknown ``name``, listing ``known`` and suggesting the closest."""
    message = f"unknown {kind} {name!r}; known {kind}s: {', '.join(sorted(known))}"
    close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.0)
    if close:
        message += f"; did you mean {close[0]!r}?"
    return ReconError(message)


def make_shape(name: str, resolution: int = DEFAULT_RESOLUTION, **params: object) -> Mesh:
    """Build the built-in shape ``name`` (a key of SHAPES) at ``resolution`` with ``params``.

    Raises ReconError for an unknown name (with the closest known name suggested) or an unknown
    or invalid parameter.
    """
    if name not in SHAPES:
        raise _unknown_name_error("shape", name, list(SHAPES))
    factory = SHAPES[name]
    accepted = [key for key in inspect.signature(factory).parameters if key != "resolution"]
    for key in params:
        if key not in accepted:
            suggestion = difflib.get_close_matches(key, accepted, n=1)
            hint = f"; did you mean {suggestion[0]!r}?" if suggestion else ""
            raise ReconError(
                f"shape {name!r}: unknown parameter {key!r}; accepted: "
                f"{', '.join(['resolution', *accepted])}{hint}"
            )
    return factory(resolution=resolution, **params)
