"""antialias: topology, coverage, and visibility gradients against finite differences of an
area-integrated (16x16 supersampled) render.

Agreement measure for gradients: cosine similarity between the analytic gradient (all vertex
clip coordinates x, y, w flattened) and central finite differences of the supersampled image
loss, and the relative error |g - g_fd| / |g_fd|. The antialias blend is a 1D coverage estimate
per pixel pair, so it agrees in direction closely and in magnitude roughly; thresholds below.
"""

from __future__ import annotations

import pytest
import torch
import trimesh
from reference.raycast import supersampled_render

from recon.camera import orbit_cameras
from recon.errors import ReconError
from recon.render.antialias import antialias, build_topology
from recon.render.interpolate import interpolate
from recon.render.rasterize import rasterize

COSINE_THRESHOLD = 0.95
RELATIVE_ERROR_THRESHOLD = 0.35
SUPERSAMPLING = 16


def _shade(clip_pos, faces, colors, resolution, antialiased):
    fragments = rasterize(clip_pos, faces, resolution)
    image = torch.cat([interpolate(colors, fragments, faces), fragments.mask], dim=-1)
    if antialiased:
        image = antialias(image, fragments, clip_pos, faces)
    return image


def _gradient_agreement(clip_pos, faces, colors, resolution, step, seed=0):
    """Analytic gradient of sum(weights * antialiased image) vs central differences of the
    supersampled image, w.r.t. clip x, y, w of every vertex."""
    generator = torch.Generator().manual_seed(seed)
    weights = torch.rand(clip_pos.shape[0], *resolution, colors.shape[-1] + 1, generator=generator)
    weights = weights.to(clip_pos.device)
    variable = clip_pos.clone().requires_grad_(True)
    loss = (_shade(variable, faces, colors, resolution, antialiased=True) * weights).sum()
    loss.backward()
    analytic = variable.grad[..., [0, 1, 3]].flatten()

    def reference_loss(positions):
        image = supersampled_render(
            lambda size: _shade(positions, faces, colors, size, antialiased=False),
            resolution,
            SUPERSAMPLING,
        )
        return float((image * weights).sum())

    numeric = torch.zeros_like(clip_pos)
    for index in torch.cartesian_prod(*(torch.arange(n) for n in clip_pos.shape)):
        index = tuple(int(i) for i in index)
        if index[-1] == 2:
            continue
        plus, minus = clip_pos.clone(), clip_pos.clone()
        plus[index] += step
        minus[index] -= step
        numeric[index] = (reference_loss(plus) - reference_loss(minus)) / (2 * step)
    numeric = numeric[..., [0, 1, 3]].flatten()
    cosine = torch.nn.functional.cosine_similarity(analytic, numeric, dim=0)
    relative = (analytic - numeric).norm() / numeric.norm()
    return float(cosine), float(relative)


def test_single_triangle_over_background_gradient(device):
    clip = torch.tensor(
        [[[-0.6, -0.5, 0.5, 1.0], [0.7, -0.3, 0.5, 1.2], [-0.1, 0.65, 0.5, 0.9]]], device=device
    )
    faces = torch.tensor([[0, 1, 2]], device=device)
    colors = torch.tensor([[1.0, 0.2, 0.3]] * 3, device=device)
    cosine, relative = _gradient_agreement(clip, faces, colors, (24, 24), step=2e-2)
    assert cosine > COSINE_THRESHOLD, cosine
    assert relative < RELATIVE_ERROR_THRESHOLD, relative


def test_occluding_triangle_pair_gradient(device):
    # A near red triangle partly covering a far blue one: the occluding edge is a silhouette over
    # another surface, not over background.
    clip = torch.tensor(
        [
            [
                [-0.8, -0.7, 0.6, 1.0],
                [0.8, -0.7, 0.6, 1.0],
                [0.0, 0.8, 0.6, 1.0],
                [-0.3, -0.2, -0.2, 1.1],
                [0.6, 0.1, -0.2, 0.95],
                [0.05, 0.5, -0.2, 1.05],
            ]
        ],
        device=device,
    )
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]], device=device)
    colors = torch.tensor([[0.1, 0.2, 0.9]] * 3 + [[0.9, 0.3, 0.1]] * 3, device=device)
    cosine, relative = _gradient_agreement(clip, faces, colors, (24, 24), step=2e-2, seed=1)
    assert cosine > COSINE_THRESHOLD, cosine
    assert relative < RELATIVE_ERROR_THRESHOLD, relative


def test_sphere_silhouette_gradient_wrt_translation(device):
    # Gradient of an image loss w.r.t. the sphere's position (silhouette only: constant colour).
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32, device=device)
    faces = torch.tensor(mesh.faces, device=device)
    cameras = orbit_cameras(1, (24, 24), distance=3.0, fov_x_deg=40.0, device=device)
    colors = torch.ones(verts.shape[0], 1, device=device)
    weights = torch.rand(1, 24, 24, 2, generator=torch.Generator().manual_seed(3)).to(device)

    def loss(offset, antialiased=True, supersample=False):
        clip = cameras.project_to_clip(verts + offset)
        if supersample:
            image = supersampled_render(
                lambda size: _shade(
                    cameras.with_image_size(size).project_to_clip(verts + offset),
                    faces,
                    colors,
                    size,
                    False,
                ),
                (24, 24),
                SUPERSAMPLING,
            )
        else:
            image = _shade(clip, faces, colors, (24, 24), antialiased)
        return (image * weights).sum()

    offset = torch.tensor([0.05, -0.03, 0.02], device=device, requires_grad=True)
    loss(offset).backward()
    analytic = offset.grad.clone()
    numeric = torch.zeros(3, device=device)
    step = 0.02
    for axis in range(3):
        delta = torch.zeros(3, device=device)
        delta[axis] = step
        numeric[axis] = (
            loss(offset.detach() + delta, supersample=True)
            - loss(offset.detach() - delta, supersample=True)
        ) / (2 * step)
    cosine = torch.nn.functional.cosine_similarity(analytic, numeric, dim=0)
    relative = (analytic - numeric).norm() / numeric.norm()
    assert cosine > COSINE_THRESHOLD, (analytic, numeric)
    assert relative < RELATIVE_ERROR_THRESHOLD, (analytic, numeric)
    # Without antialias the silhouette contributes nothing: the gradient would be ~0.
    plain = offset.detach().clone().requires_grad_(True)
    loss(plain, antialiased=False).backward()
    assert plain.grad.norm() < 0.05 * numeric.norm()


def test_antialiased_coverage_is_closer_to_area_coverage(device):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32, device=device)
    faces = torch.tensor(mesh.faces, device=device)
    cameras = orbit_cameras(2, (32, 32), distance=3.0, device=device)
    colors = torch.ones(verts.shape[0], 1, device=device)
    hard = _shade(cameras.project_to_clip(verts), faces, colors, (32, 32), False)[..., 1]
    soft = _shade(cameras.project_to_clip(verts), faces, colors, (32, 32), True)[..., 1]
    truth = supersampled_render(
        lambda size: _shade(
            cameras.with_image_size(size).project_to_clip(verts), faces, colors, size, False
        ),
        (32, 32),
        SUPERSAMPLING,
    )[..., 1]
    hard_error = (hard - truth).abs().sum()
    soft_error = (soft - truth).abs().sum()
    assert soft_error < 0.6 * hard_error
    assert float(soft.min()) >= -1e-6 and float(soft.max()) <= 1 + 1e-6


def test_interior_edges_are_not_blended(device):
    # Two coplanar triangles sharing an edge, same colour: antialias must leave the shared edge
    # alone (it is not a silhouette), so the interior stays exactly the flat colour.
    clip = torch.tensor(
        [
            [-0.8, -0.8, 0.0, 1.0],
            [0.8, -0.8, 0.0, 1.0],
            [0.8, 0.8, 0.0, 1.0],
            [-0.8, 0.8, 0.0, 1.0],
        ],
        device=device,
    )
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]], device=device)
    fragments = rasterize(clip, faces, (20, 20))
    color = torch.cat([fragments.mask * 0.7, fragments.mask], dim=-1)
    out = antialias(color, fragments, clip, faces)
    interior = fragments.mask[0, 3:-3, 3:-3, 0] > 0
    assert torch.equal(out[0, 3:-3, 3:-3][interior], color[0, 3:-3, 3:-3][interior])


def test_topology_of_closed_and_open_meshes():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    faces = torch.tensor(mesh.faces)
    topology = build_topology(faces)
    assert bool((topology.neighbor_opposite >= 0).all())
    # The neighbour's opposite vertex is never on the shared edge and never the own opposite.
    own_opposite = faces[:, [2, 0, 1]]
    assert bool((topology.neighbor_opposite != own_opposite).all())
    for k in range(3):
        assert bool((topology.neighbor_opposite[:, k] != faces[:, k]).all())
        assert bool((topology.neighbor_opposite[:, k] != faces[:, (k + 1) % 3]).all())
    open_faces = faces[:-1]
    open_topology = build_topology(open_faces)
    assert int((open_topology.neighbor_opposite < 0).sum()) == 3
    # A fin (three faces on one edge) is non-manifold: treated as boundary, i.e. silhouette.
    fin = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert int((build_topology(fin).neighbor_opposite < 0).sum()) == 9


def test_color_gradients_are_the_blend_weights(device):
    clip = torch.tensor(
        [[-0.6, -0.5, 0.5, 1.0], [0.7, -0.3, 0.5, 1.2], [-0.1, 0.65, 0.5, 0.9]], device=device
    )
    faces = torch.tensor([[0, 1, 2]], device=device)
    fragments = rasterize(clip, faces, (16, 16))
    color = torch.rand(1, 16, 16, 2, device=device, dtype=torch.float32, requires_grad=True)
    out = antialias(color, fragments, clip, faces)
    out.sum().backward()
    # Blending conserves the total: each moved amount leaves one pixel and enters the other.
    assert torch.allclose(color.grad.sum(), torch.tensor(float(color[0].numel()), device=device))


def test_rejects_mismatched_inputs():
    clip = torch.tensor([[-0.6, -0.5, 0.5, 1.0], [0.7, -0.3, 0.5, 1.2], [-0.1, 0.65, 0.5, 0.9]])
    faces = torch.tensor([[0, 1, 2]])
    fragments = rasterize(clip, faces, (8, 8))
    with pytest.raises(ReconError, match=r"color: expected leading shape \(1, 8, 8\)"):
        antialias(torch.zeros(1, 8, 9, 3), fragments, clip, faces)
    with pytest.raises(ReconError, match=r"color: expected shape \[B, H, W, C\]"):
        antialias(torch.zeros(8, 8, 3), fragments, clip, faces)
    with pytest.raises(ReconError, match="topology: built for 2 faces"):
        antialias(
            torch.zeros(1, 8, 8, 3),
            fragments,
            clip,
            faces,
            topology=build_topology(torch.tensor([[0, 1, 2], [0, 2, 1]])),
        )
