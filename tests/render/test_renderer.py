"""Renderer: composition, outputs, devices, and a silhouette-only optimisation."""

from __future__ import annotations

import pytest
import torch
import trimesh

from recon.camera import orbit_cameras
from recon.errors import ReconError
from recon.mesh.mesh import Mesh
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer
from recon.render.shading import Lighting


def _sphere(device, subdivisions=3, radius=0.7) -> Mesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(
        verts=torch.tensor(mesh.vertices, dtype=torch.float32, device=device),
        faces=torch.tensor(mesh.faces, device=device),
    )


def test_outputs_have_documented_shapes_and_ranges(device):
    mesh = _sphere(device)
    mesh.vertex_colors = torch.rand(mesh.verts.shape[0], 3, device=device)
    cameras = orbit_cameras(3, (32, 40), distance=3.0, device=device)
    output = Renderer().render(mesh, cameras, Lighting.constant(1.0, device=device), background=0.2)
    assert output.color.shape == (3, 32, 40, 3) and output.color.device.type == device.type
    assert output.alpha.shape == (3, 32, 40, 1)
    assert output.normals.shape == (3, 32, 40, 3) and output.depth.shape == (3, 32, 40, 1)
    assert float(output.alpha.min()) >= -1e-6 and float(output.alpha.max()) <= 1 + 1e-6
    background = output.mask[..., 0] == 0
    # Background far from the silhouette is exactly the background colour.
    assert torch.allclose(output.color[:, :2, :2], torch.full_like(output.color[:, :2, :2], 0.2))
    normal_length = output.normals.norm(dim=-1)[~background]
    torch.testing.assert_close(normal_length, torch.ones_like(normal_length), atol=1e-4, rtol=0)
    # Depth is the camera-space z: for a sphere of radius 0.7 at distance 3, within [2.3, 3].
    depth = output.depth[..., 0][~background]
    assert float(depth.min()) > 2.29 and float(depth.max()) < 3.0


def test_textured_mesh_uses_its_own_uv_index_buffer(device):
    # A quad whose UVs are split from its positions: the left half of the texture is red.
    verts = torch.tensor(
        [[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]], device=device
    )
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]], device=device)
    uvs = torch.tensor([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], device=device)
    texture_image = torch.zeros(8, 8, 3, device=device)
    texture_image[:, :4, 0] = 1.0
    texture_image[:, 4:, 2] = 1.0
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=texture_image)
    cameras = orbit_cameras(1, (32, 32), distance=2.0, elevation_deg=0.0, device=device)
    for filter_mode in ("linear", "linear-mipmap-linear", "nearest"):
        output = Renderer(texture_filter=filter_mode, texture_boundary="clamp").render(
            mesh, cameras, Lighting.constant(1.0, device=device)
        )
        albedo = output.albedo[0]
        assert albedo[16, 11, 0] > 0.9 and albedo[16, 11, 2] < 0.1  # left: red
        assert albedo[16, 21, 2] > 0.9 and albedo[16, 21, 0] < 0.1  # right: blue


def test_shading_cached_surface_buffers_equals_a_full_render(device):
    # A frozen-geometry fit re-shades the same buffers with a new texture at every step.
    from data_synth.shapes import torus

    mesh = torus(resolution=16).to(device)
    generator = torch.Generator().manual_seed(0)
    mesh.texture = torch.rand(16, 16, 3, generator=generator).to(device)
    other = torch.rand(16, 16, 3, generator=generator).to(device)
    cameras = orbit_cameras(2, (24, 24), distance=2.4, device=device)
    lighting = Lighting.constant(0.8, device=device)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    buffers = renderer.surface_buffers(mesh, cameras)
    shaded = renderer.shade(buffers, lighting)
    full = renderer.render(mesh, cameras, lighting)
    torch.testing.assert_close(shaded.color, full.color)
    torch.testing.assert_close(shaded.alpha, full.alpha)
    retextured = renderer.shade(buffers, lighting, texture=other)
    mesh.texture = other
    torch.testing.assert_close(retextured.color, renderer.render(mesh, cameras, lighting).color)
    assert not torch.allclose(retextured.color, shaded.color)
    hard = renderer.shade(buffers, lighting, antialias_edges=False)
    assert torch.equal(hard.alpha, hard.mask)


def test_render_rejects_bad_meshes():
    mesh = _sphere("cpu")
    cameras = orbit_cameras(1, (8, 8))
    # Mesh validates on construction; a mesh edited afterwards is checked again by render.
    broken = Mesh(mesh.verts, mesh.faces)
    broken.faces = mesh.faces.clone()
    broken.faces[0, 0] = mesh.verts.shape[0] + 5
    with pytest.raises(
        ReconError, match=r"mesh.faces: indices must lie in \[0, 641\], got range \[0, 647\]"
    ):
        Renderer().render(broken, cameras, Lighting.constant())
    with pytest.raises(ReconError, match="mesh.verts: contains NaN or inf"):
        Mesh(torch.full((3, 3), float("nan")), torch.tensor([[0, 1, 2]]))
    with pytest.raises(ReconError, match=r"mesh.verts: expected shape \[V, 3\]"):
        Mesh(torch.zeros(3, 2), torch.tensor([[0, 1, 2]]))


def test_silhouette_only_fit_moves_a_displaced_sphere_onto_its_target(device):
    """Only the antialiased coverage is compared (no shading): every gradient is a visibility
    gradient. The sphere starts displaced and shrunk and must land on the target."""
    torch.manual_seed(0)
    target = _sphere(device, subdivisions=2, radius=0.6)
    cameras = orbit_cameras(4, (32, 32), distance=3.0, elevation_deg=25.0, device=device)
    renderer = Renderer()
    lighting = Lighting.constant(1.0, device=device)
    topology = build_topology(target.faces)
    with torch.no_grad():
        target_alpha = renderer.render(target, cameras, lighting, topology=topology).alpha
    offset = torch.tensor([0.25, -0.15, 0.1], device=device, requires_grad=True)
    log_scale = torch.tensor(-0.25, device=device, requires_grad=True)
    optimizer = torch.optim.Adam([offset, log_scale], lr=0.02)
    start_error = None
    for _ in range(80):
        mesh = Mesh(target.verts * log_scale.exp() + offset, target.faces)
        alpha = renderer.render(mesh, cameras, lighting, topology=topology).alpha
        loss = (alpha - target_alpha).abs().mean()
        start_error = float(loss.detach()) if start_error is None else start_error
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert float(offset.detach().norm()) < 0.03
    assert abs(float(log_scale)) < 0.03
    assert float(loss) < 0.2 * start_error


def _glossy_scene(device="cpu", size: int = 32):
    """A lumpy UV-mapped shape (not a sphere: shading depends on its orientation), a uniform
    glossy material [4, 4, 5] and a directional studio environment [8, 16, 3]."""
    from recon.render.environment import latlong_directions

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32) * torch.tensor([1.0, 0.7, 0.85])
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    uvs, uv_faces = torch.full((1, 2), 0.5), torch.zeros_like(faces)
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=uv_faces, texture=torch.zeros(4, 4, 3)).to(device)
    material = torch.tensor([0.6, 0.4, 0.3, 0.3, 0.2]).expand(4, 4, 5).contiguous().to(device)
    directions, _ = latlong_directions(8, 16)
    light = torch.nn.functional.normalize(torch.tensor([0.5, -0.6, -0.6]), dim=0)
    environment = (
        0.2
        + 0.1 * directions[..., 1:2]
        + 4 * torch.exp((directions @ light - 1) / 0.1)[..., None] * torch.tensor([1.0, 0.8, 0.6])
    )
    return mesh, material, environment.to(device)


def _pbr_render(renderer, mesh, cameras, material, environment, frame, world_to_cam=None):
    from recon.render.environment import prefilter_environment

    buffers = renderer.surface_buffers(mesh, cameras)
    if world_to_cam is not None:
        buffers.world_to_cam = world_to_cam  # only the camera-frame look-up reads it
    return renderer.shade_pbr(
        buffers,
        cameras.centers(),
        material,
        prefilter_environment(environment, 4),
        antialias_edges=False,
        light_frame=frame,
    )


def test_camera_frame_environment_equals_world_frame_for_an_unrotated_camera():
    from recon.camera.cameras import Cameras, intrinsics_from_fov

    mesh, material, environment = _glossy_scene()
    world_to_cam = torch.eye(4)[None].repeat(2, 1, 1)
    world_to_cam[:, :3, 3] = torch.tensor([[0.0, 0.0, 3.0], [0.4, -0.2, 2.5]])
    cameras = Cameras(world_to_cam, intrinsics_from_fov(40.0, (32, 32)).expand(2, 3, 3), (32, 32))
    renderer = Renderer(texture_filter="linear")
    world = _pbr_render(renderer, mesh, cameras, material, environment, "world")
    camera = _pbr_render(renderer, mesh, cameras, material, environment, "camera")
    assert float(world.mask.sum()) > 300
    torch.testing.assert_close(camera.color, world.color, atol=1e-5, rtol=0)


def test_camera_frame_environment_turns_with_the_camera():
    # Object and camera turned together (a turntable seen from the turning object's side):
    # the camera-frame environment renders the same image, the world-frame one does not.
    import math

    from recon.camera.cameras import Cameras

    mesh, material, environment = _glossy_scene()
    cameras = orbit_cameras(1, (32, 32), distance=3.0)
    angle = 1.1
    axis = torch.nn.functional.normalize(torch.tensor([0.2, 1.0, 0.3]), dim=0)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = torch.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
    rigid = torch.eye(4)
    rigid[:3, :3] = rotation.T
    moved = Mesh(
        mesh.verts @ rotation.T,
        mesh.faces,
        uvs=mesh.uvs,
        uv_faces=mesh.uv_faces,
        texture=mesh.texture,
    )
    moved_cameras = Cameras(
        cameras.world_to_cam @ rigid, cameras.intrinsics, cameras.image_size, cameras.near
    )
    renderer = Renderer(texture_filter="linear")
    before, after = (
        _pbr_render(renderer, shape, view, material, environment, "camera")
        for shape, view in ((mesh, cameras), (moved, moved_cameras))
    )
    assert float((before.color - after.color).abs().max()) < 2e-3
    world_before, world_after = (
        _pbr_render(renderer, shape, view, material, environment, "world")
        for shape, view in ((mesh, cameras), (moved, moved_cameras))
    )
    assert float((world_before.color - world_after.color).abs().max()) > 0.05


def test_camera_frame_environment_gradients_match_finite_differences():
    # Gradients reach the environment texels and the camera rotation through the look-up.
    mesh, material, environment = _glossy_scene()
    cameras = orbit_cameras(2, (24, 24), distance=3.0)
    renderer = Renderer(texture_filter="linear")
    weights = torch.rand(2, 24, 24, 3, generator=torch.Generator().manual_seed(0))

    def loss(light: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
        # A turn of the cameras' axes about their own y: only the shading's frame moves.
        cosine, sine = torch.cos(angle), torch.sin(angle)
        zero, one = torch.zeros_like(angle), torch.ones_like(angle)
        turn = torch.stack(
            [
                torch.stack([cosine, zero, sine, zero]),
                torch.stack([zero, one, zero, zero]),
                torch.stack([-sine, zero, cosine, zero]),
                torch.stack([zero, zero, zero, one]),
            ]
        )
        world_to_cam = turn @ cameras.world_to_cam
        output = _pbr_render(renderer, mesh, cameras, material, light, "camera", world_to_cam)
        return (output.color * weights).sum()

    light = environment.clone().requires_grad_(True)
    angle = torch.tensor(0.3, requires_grad=True)
    loss(light, angle).backward()
    assert float(light.grad.abs().sum()) > 0 and float(angle.grad.abs()) > 0
    step = 1e-2
    with torch.no_grad():
        numeric_angle = (loss(light, angle + step) - loss(light, angle - step)) / (2 * step)
        torch.testing.assert_close(angle.grad, numeric_angle, rtol=0.03, atol=1e-3)
        # The render is linear in the environment: a finite difference on texels is exact.
        for texel in [(1, 3, 0), (5, 10, 2), (3, 7, 1)]:
            bumped = environment.clone()
            bumped[texel] += 0.5
            numeric = (loss(bumped, angle) - loss(environment, angle)) / 0.5
            torch.testing.assert_close(light.grad[texel], numeric, rtol=0.01, atol=1e-3)


def _lit_plane(size: int = 24):
    """A unit quad in z = 0 facing a camera on +z (u along +x, v downwards along -y), a glossy
    uniform material and the studio environment of _glossy_scene."""
    from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at

    _, material, environment = _glossy_scene()
    verts = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=torch.float32)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=torch.float32)
    mesh = Mesh(verts, faces, uvs=uvs, uv_faces=faces.clone(), texture=torch.zeros(4, 4, 3))
    eyes = torch.tensor([[0.3, 0.2, 3.0], [-0.8, 0.4, 2.8]])
    cameras = Cameras(
        look_at(eyes), intrinsics_from_fov(40.0, (size, size)).expand(2, 3, 3), (size, size)
    )
    return mesh, cameras, material, environment


def _with_normal_map(material: torch.Tensor, tangent_normal: torch.Tensor) -> torch.Tensor:
    return torch.cat([material, tangent_normal.expand(*material.shape[:2], 3)], dim=-1)


def test_flat_normal_map_changes_nothing_and_a_tilt_equals_tilted_normals():
    from recon.render.environment import prefilter_environment

    mesh, cameras, material, environment = _lit_plane()
    renderer = Renderer(texture_filter="linear")
    prefiltered = prefilter_environment(environment, 4)
    buffers = renderer.surface_buffers(mesh, cameras)

    def shade(texture, shading_buffers=buffers):
        return renderer.shade_pbr(
            shading_buffers, cameras.centers(), texture, prefiltered, antialias_edges=False
        ).color

    plain = shade(material)
    flat = shade(_with_normal_map(material, torch.tensor([0.0, 0.0, 1.0])))
    torch.testing.assert_close(flat, plain, atol=1e-6, rtol=0)
    # Tilt toward +u (world +x) and +v_up (world +y): the same as normals turned that way.
    tilt = torch.nn.functional.normalize(torch.tensor([0.4, -0.3, 0.85]), dim=0)
    mapped = shade(_with_normal_map(material, tilt))
    turned = renderer.surface_buffers(mesh, cameras, vertex_normals_world=tilt.expand(4, 3))
    torch.testing.assert_close(mapped, shade(material, turned), atol=1e-5, rtol=0)
    assert float((mapped - plain).abs().max()) > 0.05


def test_normal_map_gradients_match_finite_differences():
    from recon.render.environment import prefilter_environment

    mesh, cameras, material, environment = _lit_plane(16)
    renderer = Renderer(texture_filter="linear")
    prefiltered = prefilter_environment(environment, 4)
    buffers = renderer.surface_buffers(mesh, cameras)
    weights = torch.rand(2, 16, 16, 3, generator=torch.Generator().manual_seed(2))

    def loss(slopes: torch.Tensor) -> torch.Tensor:
        normal = torch.cat([slopes, (1 - slopes.square().sum()).sqrt()[None]])
        color = renderer.shade_pbr(
            buffers,
            cameras.centers(),
            _with_normal_map(material, normal),
            prefiltered,
            antialias_edges=False,
        ).color
        return (color * weights).sum()

    slopes = torch.tensor([0.2, -0.1], requires_grad=True)
    loss(slopes).backward()
    step = 1e-2
    with torch.no_grad():
        for axis in range(2):
            offset = torch.zeros(2)
            offset[axis] = step
            numeric = (loss(slopes + offset) - loss(slopes - offset)) / (2 * step)
            torch.testing.assert_close(slopes.grad[axis], numeric, rtol=0.03, atol=1e-2)


def test_pbr_shading_with_a_normal_map_agrees_across_devices_and_gives_gradients(device):
    """The whole pbr path (rasterise, sample the [h, w, 8] material with its normal map, split-
    sum shade, antialias) on the device agrees with the CPU, and every material channel and the
    environment's texels receive gradient there (the CUDA run is skipped without a GPU)."""
    from recon.render.environment import prefilter_environment

    # The lit plane has real UVs, so the normal map's tangent frame is defined.
    mesh, cameras, material, environment = _lit_plane(16)

    def render(on, material, environment):
        renderer = Renderer(texture_filter="linear")
        buffers = renderer.surface_buffers(mesh.to(on), cameras.to(on))
        return renderer.shade_pbr(
            buffers, cameras.to(on).centers(), material, prefilter_environment(environment, 4)
        ).color

    tilt = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, 0.95]), dim=0)
    material = _with_normal_map(material, tilt).contiguous()
    expected = render("cpu", material, environment)
    material_on = material.to(device).requires_grad_(True)
    environment_on = environment.to(device).requires_grad_(True)
    found = render(device, material_on, environment_on)
    assert found.device.type == device.type
    torch.testing.assert_close(found.detach().cpu(), expected, atol=2e-4, rtol=1e-3)
    found.sum().backward()
    channel_gradient = material_on.grad.abs().sum((0, 1))
    # Base colour, roughness, metalness and the normal map's x, y all move the image.
    assert bool((channel_gradient[:7] > 0).all())
    assert float(environment_on.grad.abs().sum()) > 0
