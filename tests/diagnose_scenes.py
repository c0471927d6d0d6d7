"""Small scenes shared by the diagnosis tests."""

from __future__ import annotations

from collections.abc import Callable

import torch

from data_synth.shapes import torus
from recon.mesh.mesh import Mesh


def patterned_torus(
    waves: tuple[int, int],
    amplitude: float,
    colours: Callable[[torch.Tensor], list[torch.Tensor]],
    base: float = 0.5,
) -> Mesh:
    """A torus (24 segments) with a 32 x 32 texture: pattern = base + amplitude sin(2 pi a u)
    sin(2 pi b v) for waves (a, b), turned into three channels by colours(pattern)."""
    mesh = torus(resolution=24)
    steps = torch.linspace(0, 1, 32)
    u, v = torch.meshgrid(steps, steps, indexing="xy")
    pattern = base + amplitude * torch.sin(6.28 * waves[0] * u) * torch.sin(6.28 * waves[1] * v)
    mesh.texture = torch.stack(colours(pattern), -1)
    return mesh


def directions_to_camera(output, cameras) -> torch.Tensor:
    """[B, H, W, 3] unit directions from each pixel's surface point (its rendered depth, lifted
    through the cameras' intrinsics and pose) toward the camera centre."""
    batch, height, width, _ = output.color.shape
    depth = output.depth[..., 0]
    rows, columns = torch.meshgrid(
        torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij"
    )
    intrinsics = cameras.intrinsics
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    points = torch.stack(
        [(columns - cx) / fx * depth, (rows - cy) / fy * depth, depth, torch.ones_like(depth)],
        -1,
    ).view(batch, -1, 4)
    world = (points @ torch.linalg.inv(cameras.world_to_cam).transpose(1, 2))[..., :3]
    to_camera = cameras.centers()[:, None, None, :] - world.view(batch, height, width, 3)
    return to_camera / to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def glossy_torus_views(
    views: int = 12,
    size: int = 40,
    exposure_sigma: float = 0.0,
    white_balance_sigma: float = 0.0,
    specular: float = 0.5,
    shininess: float = 3.0,
    light_direction: tuple[float, float, float] = (0.0, 0.2, 1.0),
    seed: int = 0,
    transform: Callable[[torch.Tensor, object], torch.Tensor] | None = None,
    distance: float = 2.4,
    fov_x_deg: float = 45.0,
    specular_colour: tuple[float, float, float] = (1.0, 1.0, 1.0),
):
    """Held-out views of a glossy torus beside its diffuse fit: (DiagnosisData, true gains [V]).

    The world adds a Blinn-Phong highlight specular * max(0, n.h)^shininess (white, under a
    directional light toward light_direction plus a dim ambient) to a coloured diffuse torus,
    then a per-view exposure exp(exposure_sigma N(0, 1)) and per-view red/blue gains
    exp(white_balance_sigma N(0, 1)). The "fit" is the diffuse model whose light absorbed the
    mean highlight per channel (the best per-channel scale): what a diffuse fit of a glossy
    object leaves. The light's direction is near the cameras' ring, so views that face it show
    more highlight: per-view gains follow n.h. transform(observed, output) applies a further
    camera effect to the observed views (premultiplied linear colour). distance and fov_x_deg
    frame the orbit (how much of the image the torus covers). specular_colour: the highlight's
    colour (a metal's, e.g. gold's, is its own colour; a dielectric's is white).
    """
    from recon.camera import orbit_cameras
    from recon.diagnose.data import build_diagnosis_data
    from recon.render.renderer import Renderer
    from recon.render.shading import DirectionalLight, Lighting

    mesh = patterned_torus((3, 2), 0.3, lambda p: [p, 0.8 * p + 0.1, 0.6 * (1 - p) + 0.2])
    cameras = orbit_cameras(
        views, (size, size), distance=distance, fov_x_deg=fov_x_deg, elevation_deg=30
    )
    direction = torch.tensor(light_direction, dtype=torch.float32)
    direction = direction / direction.norm()
    irradiance = torch.full((3,), 2.0)
    world_light = Lighting.constant(0.3)
    world_light.directional.append(DirectionalLight(direction, irradiance))
    renderer = Renderer(texture_filter="linear")
    output = renderer.render(mesh, cameras, world_light)
    to_camera = directions_to_camera(output, cameras)
    halfway = to_camera + direction
    halfway = halfway / halfway.norm(dim=-1, keepdim=True)
    normals = output.normals
    lit = (normals * direction).sum(-1) > 0
    highlight = specular * (normals * halfway).sum(-1).clamp_min(0) ** shininess * lit
    generator = torch.Generator().manual_seed(seed)
    gains = torch.exp(exposure_sigma * torch.randn(views, generator=generator))
    red_blue = torch.exp(white_balance_sigma * torch.randn(views, 2, generator=generator))
    channel_gains = torch.stack([red_blue[:, 0], torch.ones(views), red_blue[:, 1]], -1)
    tint = torch.tensor(specular_colour, dtype=torch.float32)
    observed = output.color + highlight[..., None] * tint * output.alpha
    observed = observed * gains[:, None, None, None] * channel_gains[:, None, None, :]
    if transform is not None:
        observed = transform(observed, output)
    # The diffuse fit: the light's per-channel scale absorbs the mean highlight.
    scale = (observed * output.color).sum((0, 1, 2)) / (output.color**2).sum((0, 1, 2))
    fitted_light = Lighting(
        sh_coefficients=world_light.sh_coefficients * scale,
        directional=[DirectionalLight(direction, irradiance * scale)],
    )
    fitted = renderer.render(mesh, cameras, fitted_light)
    observed = observed + 0.002 * torch.randn(observed.shape, generator=generator)
    data = build_diagnosis_data(observed, output.alpha, fitted, cameras, fitted_light, mesh)
    return data, gains


def albedo_error_views(
    seed: int,
    views: int = 12,
    size: int = 32,
    error: float = 0.5,
    channel_gains: torch.Tensor | None = None,
    cells: int = 4,
    grey: bool = False,
):
    """Held-out views of a torus whose fitted texture is wrong by smooth random patches
    (texture * (1 + error * a random 4 x 4 field per channel, upsampled)): a ~20 dB fit with
    no camera or light-transport effect at all, only the base model's mismatch. channel_gains
    [views, 3] (a white balance per view) multiply the observed views when given; cells: the
    random field's cells per side (more: a more local misfit); grey: one field for the three
    channels (a shading-like misfit that leaves the colour alone)."""
    from recon.camera import orbit_cameras
    from recon.diagnose.data import build_diagnosis_data
    from recon.render.renderer import Renderer
    from recon.render.shading import Lighting

    def colours(pattern):
        return [pattern, 0.8 * pattern + 0.1, 0.6 * (1 - pattern) + 0.2]

    true = patterned_torus((3, 2), 0.3, colours)
    fitted = patterned_torus((3, 2), 0.3, colours)
    generator = torch.Generator().manual_seed(seed)
    field = torch.randn(1, 1 if grey else 3, cells, cells, generator=generator).expand(1, 3, -1, -1)
    field = torch.nn.functional.interpolate(
        field, size=(32, 32), mode="bilinear", align_corners=True
    )
    true.texture = (true.texture * (1 + error * field[0].permute(1, 2, 0))).clamp(0.02, 1)
    cameras = orbit_cameras(views, (size, size), distance=2.4, fov_x_deg=45, elevation_deg=30)
    lighting = Lighting.constant(0.8)
    renderer = Renderer(texture_filter="linear")
    observed = renderer.render(true, cameras, lighting)
    render = renderer.render(fitted, cameras, lighting)
    colour = observed.color
    if channel_gains is not None:
        colour = colour * channel_gains[:, None, None, :]
    noisy = colour + 0.002 * torch.randn(observed.color.shape, generator=generator)
    return build_diagnosis_data(noisy, observed.alpha, render, cameras, lighting, fitted)


def turntable_torus_views(
    views: int = 6,
    size: int = 32,
    limb: float = 0.0,
    vignetting: float = 0.0,
    seed: int = 0,
    exposures: list[float] | None = None,
):
    """Held-out views of a torus under a light fixed to the camera (a turntable capture, as the
    shared real capture is fitted), beside its diffuse fit: DiagnosisData.

    limb: the object's reflectance departs from the diffuse model at grazing angles: observed
    *= 1 - limb + limb n.v (darker toward the silhouette, as a real object often is); the
    object sits at the image centre, so the rim lies at the same radii in every view.
    vignetting: a real falloff, observed *= 1 - vignetting r^2 (r over the half diagonal). The
    "fit" is the diffuse model whose light absorbed the mean of both per channel.
    exposures: one gain per view (a real exposure change), observed *= exposures[view]."""
    import math

    from recon.camera import orbit_cameras
    from recon.diagnose.data import build_diagnosis_data
    from recon.render.renderer import Renderer
    from recon.render.shading import DirectionalLight, Lighting

    mesh = patterned_torus((3, 2), 0.3, lambda p: [p, 0.8 * p + 0.1, 0.6 * (1 - p) + 0.2])
    cameras = orbit_cameras(views, (size, size), distance=2.4, fov_x_deg=45, elevation_deg=30)
    direction = torch.tensor([0.3, -0.3, -1.0])  # toward the light, in camera axes
    direction = direction / direction.norm()
    light = Lighting(
        sh_coefficients=Lighting.constant(0.2).sh_coefficients,
        directional=[DirectionalLight(direction, torch.full((3,), 2.0))],
        frame="camera",
    )
    renderer = Renderer(texture_filter="linear")
    output = renderer.render(mesh, cameras, light)
    batch, height, width, _ = output.color.shape
    rotation = cameras.world_to_cam[:, :3, :3]
    normals = (output.normals.view(batch, -1, 3) @ rotation.transpose(1, 2)).view(
        output.normals.shape
    )
    rows, columns = torch.meshgrid(
        torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij"
    )
    intrinsics = cameras.intrinsics
    x = (columns - intrinsics[:, 0, 2, None, None]) / intrinsics[:, 0, 0, None, None]
    y = (rows - intrinsics[:, 1, 2, None, None]) / intrinsics[:, 1, 1, None, None]
    rays = torch.stack([x, y, torch.ones_like(x)], -1)
    n_dot_v = -(normals * rays / rays.norm(dim=-1, keepdim=True)).sum(-1).clamp(-1, 1)
    observed = output.color * (1 - limb + limb * n_dot_v.clamp_min(0))[..., None]
    radius = torch.sqrt(
        (columns - intrinsics[:, 0, 2, None, None]) ** 2
        + (rows - intrinsics[:, 1, 2, None, None]) ** 2
    ) / (0.5 * math.hypot(height, width))
    observed = observed * (1 - vignetting * radius**2)[..., None]
    if exposures is not None:
        observed = observed * torch.tensor(exposures)[:, None, None, None]
    scale = (observed * output.color).sum((0, 1, 2)) / (output.color**2).sum((0, 1, 2))
    fitted_light = Lighting(
        sh_coefficients=light.sh_coefficients * scale,
        directional=[DirectionalLight(direction, torch.full((3,), 2.0) * scale)],
        frame="camera",
    )
    fitted = renderer.render(mesh, cameras, fitted_light)
    generator = torch.Generator().manual_seed(seed)
    observed = observed + 0.002 * torch.randn(observed.shape, generator=generator)
    return build_diagnosis_data(observed, output.alpha, fitted, cameras, fitted_light, mesh)


def camera_effect_torus_views(
    effect: str | None, parameters: dict, size: int = 36, views: int = 8, seed: int = 0
):
    """Held-out views of a textured torus with one data_synth image effect (name, parameters)
    applied to the captured views, beside the exact model's render (DiagnosisData): whatever
    the diagnosis finds beyond noise is that effect."""
    from data_synth.effects.base import Capture
    from data_synth.effects.registry import apply_effects
    from recon.camera import orbit_cameras
    from recon.diagnose.data import build_diagnosis_data
    from recon.render.renderer import Renderer
    from recon.render.shading import DirectionalLight, Lighting

    mesh = patterned_torus((3, 2), 0.3, lambda p: [p, 0.8 * p + 0.1, 0.6 * (1 - p) + 0.2])
    cameras = orbit_cameras(views, (size, size), distance=2.4, fov_x_deg=45, elevation_deg=30)
    light = Lighting.constant(0.4)
    light.directional.append(DirectionalLight(torch.tensor([0.3, 0.8, 0.5]), torch.full((3,), 1.5)))
    output = Renderer(texture_filter="linear").render(mesh, cameras, light)
    capture = Capture(output.color.clone(), output.alpha.clone(), cameras)
    generator = torch.Generator().manual_seed(seed)
    if effect:
        apply_effects(capture, [(effect, parameters)], generator)
    noisy = capture.images + 0.002 * torch.randn(capture.images.shape, generator=generator)
    return build_diagnosis_data(noisy, capture.alpha, output, cameras, light, mesh)
