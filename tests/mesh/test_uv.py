"""Tests for recon.mesh.uv: xatlas unwrapping, the UV rasterizer, baking and dilation.

The texture sampler (recon.render.texture) is used here only as the reader of what bake writes:
recon.mesh itself must not import recon.render.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
import trimesh
import xatlas

from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.mesh.uv import (
    bake_vertex_attribute,
    chart_border_edges,
    chart_border_faces,
    dilate,
    rasterize_uv,
    unwrap,
    uv_coverage_count,
)
from recon.render.texture import texture

RESOLUTION = 512


def icosphere() -> tuple[torch.Tensor, torch.Tensor]:
    mesh = trimesh.creation.icosphere(subdivisions=3)
    return torch.tensor(mesh.vertices, dtype=torch.float32), torch.tensor(mesh.faces)


def torus() -> tuple[torch.Tensor, torch.Tensor]:
    mesh = trimesh.creation.torus(major_radius=1.0, minor_radius=0.35)
    return torch.tensor(mesh.vertices, dtype=torch.float32), torch.tensor(mesh.faces)


MESHES = {"icosphere": icosphere, "torus": torus}


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    """These tensors are small (<= 512^2): on a shared 2-core machine, torch's intra-op
    threads spend more time synchronising than computing (the module runs in ~4 s on one
    thread, 20 s or more on two under load). Restored afterwards for the other modules."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module", params=sorted(MESHES))
def unwrapped(request) -> dict[str, torch.Tensor]:
    """A mesh, a copy of its input arrays, and its layout for a RESOLUTION texture."""
    verts, faces = MESHES[request.param]()
    verts_before, faces_before = verts.clone(), faces.clone()
    uvs, uv_faces = unwrap(verts, faces, resolution=RESOLUTION, padding=2)
    return {
        "verts": verts,
        "faces": faces,
        "verts_before": verts_before,
        "faces_before": faces_before,
        "uvs": uvs,
        "uv_faces": uv_faces,
    }


def smooth_attribute(verts: torch.Tensor) -> torch.Tensor:
    """[V, 3] colours in [0.2, 0.8], smooth over the surface and never 0."""
    return 0.5 + 0.3 * verts / verts.abs().max()


def doubled_uv_areas(uvs: torch.Tensor, uv_faces: torch.Tensor, size: int) -> torch.Tensor:
    """[F] float64 doubled signed UV areas in texels^2."""
    corners = uvs.double()[uv_faces] * size
    first = corners[:, 1] - corners[:, 0]
    second = corners[:, 2] - corners[:, 0]
    return first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0]


def vertex_of_uv(faces: torch.Tensor, uv_faces: torch.Tensor, uv_count: int) -> torch.Tensor:
    """[T] the mesh vertex each uv belongs to (a uv is used by one vertex only)."""
    owner = torch.full((uv_count,), -1, dtype=torch.int64)
    owner[uv_faces.reshape(-1)] = faces.reshape(-1)
    return owner


def sample(tex: torch.Tensor, points: torch.Tensor, level: int | None = None) -> torch.Tensor:
    """Sample tex [h, w, C] at uv points [N, 2]: bilinear, or trilinear at exactly mip level."""
    uv = points[None, None].float()
    if level is None:
        return texture(tex, uv, filter="linear", boundary="clamp")[0, 0]
    height, width = tex.shape[:2]
    derivatives = torch.zeros((*uv.shape[:-1], 4))
    # du/dx = 2^level / w makes a pixel span 2^level texels: level of detail exactly `level`.
    derivatives[..., 0] = 2.0**level / width
    derivatives[..., 3] = 2.0**level / height
    return texture(tex, uv, derivatives, filter="linear-mipmap-linear", boundary="clamp")[0, 0]


# --- unwrap -----------------------------------------------------------------------------------


def test_unwrap_layout_shapes_range_and_inputs_unchanged(unwrapped):
    uvs, uv_faces, faces = unwrapped["uvs"], unwrapped["uv_faces"], unwrapped["faces"]
    assert uv_faces.shape == faces.shape
    assert uvs.dtype == torch.float32 and uv_faces.dtype == torch.int64
    assert uvs.ndim == 2 and uvs.shape[1] == 2
    assert bool((uvs >= 0).all()) and bool((uvs <= 1).all())
    assert int(uv_faces.min()) >= 0 and int(uv_faces.max()) < uvs.shape[0]
    assert torch.equal(unwrapped["verts"], unwrapped["verts_before"])
    assert torch.equal(faces, unwrapped["faces_before"])
    # A uv belongs to one vertex: positions stay shared by index, uvs split at seams only.
    owner = torch.full((uvs.shape[0],), -1, dtype=torch.int64)
    owner[uv_faces.reshape(-1)] = faces.reshape(-1)
    assert torch.equal(owner[uv_faces], faces)
    Mesh(unwrapped["verts"], faces, uvs=uvs, uv_faces=uv_faces)  # validates


def test_unwrap_charts_do_not_overlap(unwrapped):
    count = uv_coverage_count(unwrapped["uvs"], unwrapped["uv_faces"], (RESOLUTION, RESOLUTION))
    assert int(count.max()) == 1
    # The charts fill a fair part of the square (xatlas packs to about half or more).
    assert float((count > 0).float().mean()) > 0.3


def test_unwrap_triangles_non_degenerate_and_area_distortion_bounded(unwrapped):
    uvs, uv_faces = unwrapped["uvs"], unwrapped["uv_faces"]
    verts, faces = unwrapped["verts"].double(), unwrapped["faces"]
    uv_area = doubled_uv_areas(uvs, uv_faces, RESOLUTION).abs()
    assert float(uv_area.min()) > 0.05 * float(uv_area.median())
    corners = verts[faces]
    surface_area = torch.linalg.cross(
        corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1
    ).norm(dim=-1)
    ratio = (uv_area / uv_area.sum()) / (surface_area / surface_area.sum())
    within = ((ratio > 0.2) & (ratio < 5.0)).double().mean()
    assert float(within) >= 0.95


def test_unwrap_is_deterministic():
    verts, faces = torus()
    first = unwrap(verts, faces, resolution=256, seed=0)
    second = unwrap(verts, faces, resolution=256, seed=1)
    assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])


def test_unwrap_numpy_input_and_degenerate_faces():
    verts, faces = icosphere()
    # A zero-area face and an unreferenced vertex: xatlas ignores the face but keeps its slot.
    verts = torch.cat([verts, torch.tensor([[3.0, 3.0, 3.0]])])
    faces = torch.cat([faces[:5], torch.tensor([[0, 1, 0]]), faces[5:]])
    uvs, uv_faces = unwrap(verts.numpy(), faces.numpy(), resolution=256)
    assert uv_faces.shape == faces.shape and uvs.device.type == "cpu"
    assert float(doubled_uv_areas(uvs, uv_faces[5:6], 256).abs()) == 0.0
    others = torch.cat([uv_faces[:5], uv_faces[6:]])
    assert not bool(torch.isin(uv_faces[5], others).any())
    assert int(uv_coverage_count(uvs, uv_faces, (256, 256)).max()) == 1


def test_unwrap_rejects_bad_input():
    verts, faces = icosphere()
    with pytest.raises(ReconError, match="faces"):
        unwrap(verts, faces[:, :2])
    with pytest.raises(ReconError, match="faces"):
        unwrap(verts, faces + verts.shape[0])
    with pytest.raises(ReconError, match="verts"):
        unwrap(verts[:, :2], faces)


def _atlas_with_image(positions: np.ndarray, indices: np.ndarray):
    from recon.mesh.uv import new_atlas

    atlas = new_atlas(xatlas)
    atlas.add_mesh(positions, indices)
    options = xatlas.PackOptions()
    options.resolution = 256
    options.padding = 2
    options.create_image = True
    atlas.generate(pack_options=options)
    vertex_mapping, faces, uvs = atlas[0]
    return vertex_mapping, faces, uvs, atlas.chart_image, (atlas.height, atlas.width)


def test_xatlas_uv_origin_is_top_left_like_ours():
    """xatlas's own atlas image has row y = v * height from the top, as our textures do."""
    from recon.mesh.uv import run_without_teardown

    verts, faces = torus()
    # In a child: an Atlas torn down in this process can hang (see run_without_teardown).
    vertex_mapping, indices, uvs, image, size = run_without_teardown(
        _atlas_with_image, verts.numpy(), faces.numpy().astype(np.uint32)
    )
    assert np.array_equal(vertex_mapping[indices], faces.numpy())  # same triangles, same order
    # image [height, width, 3]: chart colours, padding blue, bilinear green
    chart = image.any(-1) & ~(image == [0, 0, 255]).all(-1) & ~(image == [0, 255, 0]).all(-1)
    uv_faces = torch.from_numpy(indices.astype(np.int64))
    as_is = rasterize_uv(torch.from_numpy(uvs), uv_faces, size)[0].numpy() >= 0
    flipped_uvs = torch.from_numpy(uvs).clone()
    flipped_uvs[:, 1] = 1.0 - flipped_uvs[:, 1]
    flipped = rasterize_uv(flipped_uvs, uv_faces, size)[0].numpy() >= 0
    # xatlas marks every texel a chart touches; we mark those whose centre it covers.
    assert (as_is & chart).sum() == as_is.sum()
    assert (flipped & chart).sum() < 0.8 * flipped.sum()


# --- rasterize_uv -----------------------------------------------------------------------------


def test_rasterize_uv_row_zero_is_v_zero_and_sampler_agrees():
    # One right triangle in the top-left quadrant; a texel painted there is read back there.
    uvs = torch.tensor([[0.1, 0.05], [0.45, 0.05], [0.1, 0.3]])
    uv_faces = torch.tensor([[0, 1, 2]])
    faces = torch.tensor([[0, 1, 2]])
    size = (40, 60)
    face_id, _ = rasterize_uv(uvs, uv_faces, size)
    # Brute force: texel (i, j) is covered iff its centre ((j + 0.5) / 60, (i + 0.5) / 40) is
    # in the triangle (no centre of this layout lies on an edge).
    row = (torch.arange(size[0], dtype=torch.float64)[:, None] + 0.5) / size[0]
    column = (torch.arange(size[1], dtype=torch.float64)[None, :] + 0.5) / size[1]
    x = (column - 0.1) / 0.35
    y = (row - 0.05) / 0.25
    expected = (x >= 0) & (y >= 0) & (x + y <= 1)
    assert torch.equal(face_id >= 0, expected)
    assert int(torch.nonzero(expected)[:, 0].min()) == 2  # v = 0.05 is row 2, from the top
    tex, coverage = bake_vertex_attribute((faces, uvs, uv_faces), torch.ones(3, 1), size)
    assert torch.equal(coverage, face_id >= 0)
    centroid = uvs.mean(0, keepdim=True)
    assert float(sample(tex, centroid)) == pytest.approx(1.0)
    mirrored = centroid.clone()
    mirrored[:, 1] = 1 - mirrored[:, 1]
    assert float(sample(tex, mirrored)) == 0.0


def test_rasterize_uv_shared_edges_and_vertices_counted_once():
    # A grid whose vertices sit on texel centres and whose diagonals pass through centres:
    # many centres lie exactly on shared edges and vertices, each must count exactly once.
    size = 32
    cells = 8
    step = 3  # texels per cell
    grid = torch.arange(cells + 1, dtype=torch.float64) * step + 4.5  # texel centres
    y, x = torch.meshgrid(grid, grid, indexing="ij")
    uvs = (torch.stack([x, y], -1).reshape(-1, 2) / size).float()
    index = torch.arange((cells + 1) ** 2).view(cells + 1, cells + 1)
    top_left = index[:-1, :-1].reshape(-1)
    top_right = index[:-1, 1:].reshape(-1)
    bottom_left = index[1:, :-1].reshape(-1)
    bottom_right = index[1:, 1:].reshape(-1)
    # Mixed orientations and diagonal directions, as charts may be mirrored.
    uv_faces = torch.cat(
        [
            torch.stack([top_left, top_right, bottom_right], -1),
            torch.stack([top_left, bottom_left, bottom_right], -1),
        ]
    )
    count = uv_coverage_count(uvs, uv_faces, (size, size))
    # Centres on the square's left and top edges belong to it, those on its right and bottom
    # edges to the (absent) neighbour beyond: the same rule that counts shared edges once.
    last = 4 + cells * step
    expected = torch.zeros(size, size, dtype=torch.int64)
    expected[4:last, 4:last] = 1
    assert torch.equal(count, expected)


def test_rasterize_uv_barycentrics_reconstruct_texel_centres(unwrapped):
    uvs, uv_faces = unwrapped["uvs"], unwrapped["uv_faces"]
    size = (RESOLUTION, RESOLUTION)
    face_id, barycentrics = rasterize_uv(uvs, uv_faces, size)
    rows, columns = torch.nonzero(face_id >= 0, as_tuple=True)
    weights = barycentrics[rows, columns].double()
    assert bool((weights >= -1e-6).all()) and bool((weights <= 1 + 1e-6).all())
    assert torch.allclose(weights.sum(-1), torch.ones_like(weights[:, 0]), atol=1e-6)
    corners = uvs.double()[uv_faces[face_id[rows, columns]]]  # [N, 3, 2]
    position = (weights[..., None] * corners).sum(1) * RESOLUTION
    centre = torch.stack([columns, rows], -1).double() + 0.5
    # Fixed-point snapping moves corners by at most 1/512 texel.
    assert float((position - centre).abs().max()) < 5e-3
    assert bool((barycentrics[face_id < 0] == 0).all())


def test_rasterize_uv_rejects_bad_input():
    uvs = torch.rand(3, 2)
    with pytest.raises(ReconError, match="uv_faces"):
        rasterize_uv(uvs, torch.tensor([[0, 1, 3]]), (8, 8))
    with pytest.raises(ReconError, match="texture_size"):
        rasterize_uv(uvs, torch.tensor([[0, 1, 2]]), (0, 8))
    with pytest.raises(ReconError, match="uvs"):
        rasterize_uv(uvs * 1e6, torch.tensor([[0, 1, 2]]), (8, 8))


# --- bake and dilate --------------------------------------------------------------------------


def test_bake_then_sample_reproduces_attribute(unwrapped):
    verts, faces = unwrapped["verts"], unwrapped["faces"]
    uvs, uv_faces = unwrapped["uvs"], unwrapped["uv_faces"]
    attribute = smooth_attribute(verts)
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=uv_faces, vertex_colors=attribute)
    tex, coverage = bake_vertex_attribute(mesh, None, (RESOLUTION, RESOLUTION))
    assert tex.shape == (RESOLUTION, RESOLUTION, 3) and coverage.dtype == torch.bool
    filled = dilate(tex, coverage)
    # At every uv vertex (chart corners and borders included, where bilinear taps reach
    # outside the chart): the vertex's attribute.
    owner = vertex_of_uv(faces, uv_faces, uvs.shape[0])
    error = (sample(filled, uvs) - attribute[owner]).abs()
    assert float(error.max()) < 0.01
    # At triangle centroids: the interpolated attribute.
    centroids = uvs[uv_faces].mean(1)
    expected = attribute[faces].mean(1)
    assert float((sample(filled, centroids) - expected).abs().max()) < 0.005


def test_bake_accepts_arrays_and_checks_shapes(unwrapped):
    verts, faces = unwrapped["verts"], unwrapped["faces"]
    uvs, uv_faces = unwrapped["uvs"], unwrapped["uv_faces"]
    attribute = smooth_attribute(verts)
    from_arrays = bake_vertex_attribute((faces, uvs, uv_faces), attribute, (64, 64))
    from_mesh = bake_vertex_attribute(
        Mesh(verts, faces, uvs=uvs, uv_faces=uv_faces), attribute, (64, 64)
    )
    assert torch.equal(from_arrays[0], from_mesh[0])
    with pytest.raises(ReconError, match="attribute"):
        bake_vertex_attribute((faces, uvs, uv_faces), attribute[:10], (64, 64))
    with pytest.raises(ReconError, match="no uvs"):
        bake_vertex_attribute(Mesh(verts, faces), attribute, (64, 64))


def test_dilate_fills_outside_and_keeps_inside(unwrapped):
    verts, faces = unwrapped["verts"], unwrapped["faces"]
    layout = (faces, unwrapped["uvs"], unwrapped["uv_faces"])
    tex, coverage = bake_vertex_attribute(layout, smooth_attribute(verts), (256, 256))
    assert bool((tex[~coverage] == 0).all())
    filled = dilate(tex, coverage)
    assert bool((filled > 0).all())  # every texel now holds some chart's colour
    assert torch.equal(filled[coverage], tex[coverage])
    # A filled texel copies its nearest covered texel: its colour is a chart colour.
    assert float(filled.min()) >= float(tex[coverage].min())
    assert float(filled.max()) <= float(tex[coverage].max())

    ring = dilate(tex, coverage, iterations=2)
    reach = torch.nn.functional.max_pool2d(coverage[None, None].float(), 5, 1, 2)[0, 0] > 0
    assert torch.equal(ring[reach], filled[reach])
    assert bool((ring[~reach] == 0).all()) and bool((~reach).any())
    assert torch.equal(dilate(tex, coverage, iterations=0), tex)
    with pytest.raises(ReconError, match="coverage"):
        dilate(tex, coverage[:10])


def test_full_dilation_stops_mip_levels_bleeding_background(unwrapped):
    """Trilinear lookups just inside chart borders at mip levels 1..3: background zeros
    averaged into the coarse levels pull them far off; a full nearest-chart fill keeps them
    close, and a fill of a couple of rings only helps the finest levels."""
    verts, faces = unwrapped["verts"], unwrapped["faces"]
    uvs, uv_faces = unwrapped["uvs"], unwrapped["uv_faces"]
    attribute = smooth_attribute(verts).double()
    tex, coverage = bake_vertex_attribute(
        (faces, uvs, uv_faces), attribute.float(), (RESOLUTION, RESOLUTION)
    )
    filled = dilate(tex, coverage)
    two_rings = dilate(tex, coverage, iterations=2)
    # One point per chart-border edge, 1 texel inside the chart: from the edge's midpoint
    # towards the opposite corner, with the attribute interpolated there.
    face, edge = torch.nonzero(chart_border_edges(uv_faces), as_tuple=True)
    assert face.numel() > 0
    first, second, opposite = edge, (edge + 1) % 3, (edge + 2) % 3
    start = uvs.double()[uv_faces[face, first]] * RESOLUTION
    end = uvs.double()[uv_faces[face, second]] * RESOLUTION
    apex = uvs.double()[uv_faces[face, opposite]] * RESOLUTION
    along, to_apex = end - start, apex - start
    height = (along[:, 0] * to_apex[:, 1] - along[:, 1] * to_apex[:, 0]).abs() / along.norm(dim=1)
    step = (1.0 / height).clamp(max=0.5)[:, None]
    points = ((1 - step) * 0.5 * (start + end) + step * apex) / RESOLUTION
    expected = (1 - step) * 0.5 * (
        attribute[faces[face, first]] + attribute[faces[face, second]]
    ) + step * attribute[faces[face, opposite]]
    for level in (1, 2, 3):
        background_error = float((sample(tex, points, level) - expected).abs().mean())
        rings_error = float((sample(two_rings, points, level) - expected).abs().mean())
        filled_error = float((sample(filled, points, level) - expected).abs().mean())
        assert background_error > 0.05, level
        assert filled_error < 0.05 * background_error, level
        assert filled_error < 0.005, level
        if level == 3:  # 8 x 8 blocks reach past two rings of fill
            assert filled_error < 0.1 * rings_error


def test_chart_border_faces_on_simple_layouts():
    quad = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert bool(chart_border_faces(quad).all())
    # Edge k runs from corner k to corner k + 1: only the diagonal (0, 2) is shared.
    assert chart_border_edges(quad).tolist() == [[True, True, False], [False, True, True]]
    # A closed mesh whose uvs share its vertex indexing has no open UV edge.
    _, faces = icosphere()
    assert not bool(chart_border_faces(faces).any())


def _raise_recon_error() -> None:
    raise ReconError("unwrap: a message from the child")


def _raise_other_error() -> None:
    raise ValueError("something else")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_xatlas_runs_in_a_child_that_never_tears_an_atlas_down():
    """xatlas 0.0.11 can hang in an Atlas's destructor (a lost wake-up of its workers): the
    layout is computed in a forked child that leaves without destructors. The value comes back,
    and errors come back by message."""
    from recon.mesh.uv import run_without_teardown

    assert run_without_teardown(os.getpid) != os.getpid()
    assert run_without_teardown(lambda a, b: {"sum": a + b}, 2, 3) == {"sum": 5}
    with pytest.raises(ReconError, match="unwrap: a message from the child"):
        run_without_teardown(_raise_recon_error)
    with pytest.raises(RuntimeError, match="ValueError: something else"):
        run_without_teardown(_raise_other_error)
    # The Atlases the layout makes outlive the function in the child (freed on return, their
    # destructor would run there): the child still holds them when it answers.
    held = run_without_teardown(_atlases_held_after_unwrap)
    assert held >= 1
    assert _atlases_held() == 0  # none was made in this process


def _atlases_held() -> int:
    from recon.mesh import uv

    return len(uv._NEVER_DESTROYED)


def _atlases_held_after_unwrap() -> int:
    from recon.mesh import uv

    verts, faces = torus()
    pack = xatlas.PackOptions()
    pack.resolution = 64
    uv._pack_into_one_atlas(
        xatlas, verts.numpy(), faces.numpy().astype(np.uint32), xatlas.ChartOptions(), pack
    )
    return _atlases_held()
