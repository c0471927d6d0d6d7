"""The Renderer: rasterize -> interpolate -> texture -> shade -> antialias, for a camera batch."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.camera.cameras import Cameras
from recon.errors import ReconError
from recon.mesh.mesh import Mesh, uv_tangents, validate_mesh_tensors, vertex_normals
from recon.render.antialias import EdgeTopology, antialias, build_topology
from recon.render.environment import PrefilteredEnvironment
from recon.render.interpolate import interpolate_packed
from recon.render.pbr import PbrMaterial, pbr_shade, perturb_normals
from recon.render.rasterize import Fragments, rasterize, scatter_to_image
from recon.render.shading import DirectionalLight, Lighting, lambertian
from recon.render.texture import texture as sample_texture


@dataclass
class RenderOutput:
    """Everything one render returns; all [B, H, W, ...] float32.

    color: [B, H, W, C] linear radiance composited over the background, antialiased.
    alpha: [B, H, W, 1] antialiased coverage (differentiable at silhouettes).
    normals: [B, H, W, 3] world-space shading normals (0 on background), not antialiased.
    depth: [B, H, W, 1] camera-space depth z (0 on background), differentiable, not antialiased.
    mask: [B, H, W, 1] hard coverage of pixel centres.
    albedo: [B, H, W, C] albedo (0 on background), not antialiased.
    fragments: the rasterizer output, for further passes.
    """

    color: torch.Tensor
    alpha: torch.Tensor
    normals: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor
    albedo: torch.Tensor
    fragments: Fragments


class Renderer:
    """Composes the four primitives with Lambertian SH shading.

    texture_filter: 'linear', 'linear-mipmap-linear' or 'nearest' for textured meshes.
    cull_backfaces: skip faces pointing away (only for closed meshes).
    """

    def __init__(
        self,
        texture_filter: str = "linear-mipmap-linear",
        texture_boundary: str = "wrap",
        cull_backfaces: bool = False,
    ) -> None:
        self.texture_filter = texture_filter
        self.texture_boundary = texture_boundary
        self.cull_backfaces = cull_backfaces

    def render(
        self,
        mesh: Mesh,
        cameras: Cameras,
        lighting: Lighting,
        background: torch.Tensor | float = 0.0,
        topology: EdgeTopology | None = None,
        vertex_normals_world: torch.Tensor | None = None,
        mip_pyramid: list[torch.Tensor] | None = None,
    ) -> RenderOutput:
        """Render mesh from every camera.

        mesh: albedo from mesh.texture (+ uvs) when present, else mesh.vertex_colors, else 0.5.
        background: scalar or [C] linear colour behind the object.
        topology: build_topology(mesh.faces), pass it to avoid rebuilding each call.
        vertex_normals_world: [V, 3] to override the area-weighted normals.
        """
        buffers = self.surface_buffers(mesh, cameras, topology, vertex_normals_world)
        return self.shade(buffers, lighting, background=background, mip_pyramid=mip_pyramid)

    def surface_buffers(
        self,
        mesh: Mesh,
        cameras: Cameras,
        topology: EdgeTopology | None = None,
        vertex_normals_world: torch.Tensor | None = None,
    ) -> SurfaceBuffers:
        """The light- and texture-independent part of a render (rasterise and interpolate).
        Shading it again with another texture or light (Renderer.shade) skips the rasterizer:
        what a fit with frozen geometry needs at every step."""
        validate_mesh_tensors(mesh.verts, mesh.faces)
        if mesh.verts.device != cameras.device:
            raise ReconError(f"mesh is on {mesh.verts.device} but cameras are on {cameras.device}")
        faces = mesh.faces
        height, width = cameras.image_size
        batch = len(cameras)
        clip_pos = cameras.project_to_clip(mesh.verts)
        textured = mesh.texture is not None and mesh.uvs is not None
        needs_derivatives = textured and self.texture_filter == "linear-mipmap-linear"
        fragments = rasterize(
            clip_pos,
            faces,
            (height, width),
            with_derivatives=needs_derivatives,
            cull_backfaces=self.cull_backfaces,
        )
        if topology is None:
            topology = build_topology(faces, mesh.verts.shape[0])
        normals_world = (
            vertex_normals(mesh.verts, faces)
            if vertex_normals_world is None
            else vertex_normals_world
        )
        normals = torch.nn.functional.normalize(
            interpolate_packed(normals_world, fragments, faces), dim=-1, eps=1e-12
        )
        uv = uv_derivatives = None
        if textured:
            if needs_derivatives:
                uv, uv_derivatives = interpolate_packed(
                    mesh.uvs, fragments, mesh.uv_faces, with_derivatives=True
                )
                uv_derivatives = uv_derivatives.detach()
            else:
                uv = interpolate_packed(mesh.uvs, fragments, mesh.uv_faces)
        # Camera-space depth as a differentiable attribute (interpolated w is camera z).
        depth = (
            interpolate_packed(clip_pos[..., 3:4], fragments, faces)
            if batch > 0
            else normals.new_zeros(0, 1)
        )
        return SurfaceBuffers(
            mesh,
            fragments,
            clip_pos,
            topology,
            normals,
            uv,
            uv_derivatives,
            depth,
            (height, width),
            cameras.world_to_cam,
        )

    def shade(
        self,
        buffers: SurfaceBuffers,
        lighting: Lighting,
        texture: torch.Tensor | None = None,
        background: torch.Tensor | float = 0.0,
        mip_pyramid: list[torch.Tensor] | None = None,
        antialias_edges: bool = True,
    ) -> RenderOutput:
        """Texture, shade, composite and antialias surface buffers.

        texture: [h, w, C] albedo to use instead of the buffers' mesh texture (same UVs).
        antialias_edges: False composites the hard coverage (alpha = mask): cheaper, for fits
            whose geometry is frozen and whose loss ignores the silhouette's subpixel position.
        """
        mesh, fragments = buffers.mesh, buffers.fragments
        faces = mesh.faces
        texture = mesh.texture if texture is None else texture
        if buffers.uv is not None and texture is not None:
            filter_mode = self.texture_filter
            if filter_mode == "linear-mipmap-linear" and buffers.uv_derivatives is None:
                filter_mode = "linear"
            albedo = _texture_packed(
                texture,
                buffers.uv,
                buffers.uv_derivatives,
                filter_mode,
                self.texture_boundary,
                mip_pyramid,
            )
        elif mesh.vertex_colors is not None:
            albedo = interpolate_packed(mesh.vertex_colors, fragments, faces)
        else:
            albedo = torch.full(
                (fragments.covered_index.shape[0], 3), 0.5, device=mesh.verts.device
            )
        positions = interpolate_packed(mesh.verts, fragments, faces) if lighting.points else None
        normals = buffers.normals
        if lighting.frame == "camera":
            normals, positions = _to_camera_axes(buffers, normals, positions)
        radiance = lambertian(albedo, normals, lighting, positions)
        return self._composite(buffers, radiance, albedo, background, antialias_edges)

    def shade_pbr(
        self,
        buffers: SurfaceBuffers,
        camera_centers: torch.Tensor,
        material_texture: torch.Tensor,
        environment: PrefilteredEnvironment | None,
        directional: list[DirectionalLight] | None = None,
        specular_level: float = 0.5,
        background: torch.Tensor | float = 0.0,
        mip_pyramid: list[torch.Tensor] | None = None,
        antialias_edges: bool = True,
        diffuse_weighting: str = "none",
        light_frame: str = "world",
        directional_visibility: list[torch.Tensor | None] | None = None,
    ) -> RenderOutput:
        """Texture, shade with the metallic-roughness model (recon.render.pbr), composite and
        antialias: the `pbr` material's counterpart of shade().

        camera_centers: [B, 3] world positions of the batch's cameras (the view directions).
        material_texture: [h, w, 5] base colour (3), roughness, metalness on the buffers' UVs,
            or [h, w, 8] with a tangent-space normal map (x, y, z; tangents from the UVs,
            recon.mesh.mesh.uv_tangents) that perturbs the shading normals.
        environment: the pre-filtered environment light (None: directional lights only).
        mip_pyramid: build_mip_pyramid(material_texture), to reuse across calls.
        diffuse_weighting: 'specular_albedo' or 'none' (PbrMaterial).
        light_frame: 'world', or 'camera' for an environment (and directional lights) fixed to
            the camera, as under studio lights on a turntable: normals and view directions are
            rotated into each view's OpenCV camera axes before the look-ups (the same axes as
            the Lambertian camera-frame light, Lighting.frame).
        directional_visibility: per directional light, packed visibility [N, 1] of the
            buffers' covered pixels (recon.optimize.sun_light.ShadowMap.visibility) or None.
        RenderOutput.albedo holds the base colour.
        """
        mesh, fragments = buffers.mesh, buffers.fragments
        if buffers.uv is None:
            raise ReconError("shade_pbr: the mesh has no UVs to look the material texture up")
        if material_texture.ndim != 3 or material_texture.shape[-1] not in (5, 8):
            raise ReconError(
                "shade_pbr: material_texture: expected [h, w, 5] (base colour, roughness, "
                "metalness) or [h, w, 8] (+ a tangent-space normal map), got "
                f"{tuple(material_texture.shape)}"
            )
        filter_mode = self.texture_filter
        if filter_mode == "linear-mipmap-linear" and buffers.uv_derivatives is None:
            filter_mode = "linear"
        channels = _texture_packed(
            material_texture,
            buffers.uv,
            buffers.uv_derivatives,
            filter_mode,
            self.texture_boundary,
            mip_pyramid,
        )
        material = PbrMaterial.from_channels(channels[:, :5], specular_level, diffuse_weighting)
        positions = interpolate_packed(mesh.verts, fragments, mesh.faces)
        centers = camera_centers.to(positions.dtype)[fragments.covered_batch]
        to_viewer = torch.nn.functional.normalize(centers - positions, dim=-1, eps=1e-12)
        normals = buffers.normals
        if channels.shape[-1] == 8:
            tangents, bitangents = uv_tangents(mesh.verts, mesh.faces, mesh.uvs, mesh.uv_faces)
            normals = perturb_normals(
                normals,
                interpolate_packed(tangents, fragments, mesh.uv_faces),
                interpolate_packed(bitangents, fragments, mesh.uv_faces),
                channels[:, 5:8],
            )
        if light_frame == "camera":
            # Shading is invariant under a common rotation: rotating n and v into the camera
            # axes looks the environment up at camera-frame reflection and normal directions.
            normals, to_viewer = _to_camera_axes(buffers, normals, to_viewer, translate=False)
        elif light_frame != "world":
            raise ReconError(
                f"shade_pbr: light_frame: expected 'world' or 'camera', got {light_frame!r}"
            )
        radiance = pbr_shade(
            material, normals, to_viewer, environment, directional, directional_visibility
        )
        return self._composite(buffers, radiance, material.base_color, background, antialias_edges)

    def _composite(
        self,
        buffers: SurfaceBuffers,
        radiance: torch.Tensor,
        albedo: torch.Tensor,
        background: torch.Tensor | float,
        antialias_edges: bool,
    ) -> RenderOutput:
        """Scatter packed radiance [N, C] to images, composite over the background and
        antialias (shared by the Lambertian and the PBR shading)."""
        fragments, faces = buffers.fragments, buffers.mesh.faces
        height, width = buffers.image_size
        batch = fragments.mask.shape[0]
        channels = radiance.shape[-1]
        covered = fragments.covered_index
        radiance_image = scatter_to_image(radiance, covered, batch, height, width)
        mask = fragments.mask
        background_color = torch.as_tensor(
            background, dtype=radiance.dtype, device=radiance.device
        ).expand(channels)
        composited = radiance_image + (1 - mask) * background_color
        if antialias_edges:
            antialiased = antialias(
                torch.cat([composited, mask], dim=-1),
                fragments,
                buffers.clip_pos,
                faces,
                buffers.topology,
            )
            color, alpha = antialiased[..., :channels], antialiased[..., channels:]
        else:
            color, alpha = composited, mask
        return RenderOutput(
            color=color,
            alpha=alpha,
            normals=scatter_to_image(buffers.normals, covered, batch, height, width),
            depth=scatter_to_image(buffers.depth, covered, batch, height, width),
            mask=mask,
            albedo=scatter_to_image(albedo, covered, batch, height, width),
            fragments=fragments,
        )


@dataclass
class SurfaceBuffers:
    """What the rasterizer saw, packed per covered pixel (N of them): Renderer.surface_buffers.

    normals: [N, 3] world shading normals; uv: [N, 2] (None untextured); uv_derivatives:
    [N, 4] (None without mipmapping); depth: [N, 1] camera z; clip_pos: [B, V, 4].
    """

    mesh: Mesh
    fragments: Fragments
    clip_pos: torch.Tensor
    topology: EdgeTopology
    normals: torch.Tensor
    uv: torch.Tensor | None
    uv_derivatives: torch.Tensor | None
    depth: torch.Tensor
    image_size: tuple[int, int]
    # [B, 4, 4] the cameras' world-to-camera matrices (for lights fixed to the camera).
    world_to_cam: torch.Tensor | None = None


def _to_camera_axes(
    buffers: SurfaceBuffers,
    normals: torch.Tensor,
    positions: torch.Tensor | None,
    translate: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Packed world normals [N, 3] (and positions, or with translate=False another set of
    directions [N, 3]) in their own view's OpenCV camera axes."""
    if buffers.world_to_cam is None:
        raise ReconError("a camera-frame light needs the buffers' world_to_cam (surface_buffers)")
    view = buffers.fragments.covered_batch
    matrices = buffers.world_to_cam[view]  # [N, 4, 4]
    rotation = matrices[:, :3, :3]
    camera_normals = (rotation @ normals[..., None])[..., 0]
    if positions is not None:
        positions = (rotation @ positions[..., None])[..., 0]
        if translate:
            positions = positions + matrices[:, :3, 3]
    return camera_normals, positions


def _texture_packed(
    texture_image: torch.Tensor,
    uv: torch.Tensor,
    uv_derivatives: torch.Tensor | None,
    filter_mode: str,
    boundary: str,
    mip_pyramid: list[torch.Tensor] | None,
) -> torch.Tensor:
    """Sample a texture at packed uv [N, 2] (texture() works on image-shaped inputs)."""
    count = uv.shape[0]
    uv_image = uv.view(1, 1, count, 2)
    derivative_image = None
    if uv_derivatives is not None:
        # interpolate gives (du/dx, dv/dx, du/dy, dv/dy): the layout texture() expects.
        derivative_image = uv_derivatives.view(1, 1, count, 4)
    kwargs = {}
    if mip_pyramid is not None:
        kwargs["mip_pyramid"] = mip_pyramid
    sampled = sample_texture(
        texture_image,
        uv_image,
        uv_derivatives=derivative_image,
        filter=filter_mode,
        boundary=boundary,
        **kwargs,
    )
    return sampled.view(count, -1)
