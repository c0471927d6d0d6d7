"""Environment maps: HDR EXR files or procedural (sky with a sun, studio softboxes).

Equirectangular convention: image [h, w, 3] linear radiance; row i is the polar angle
theta = pi (i + 0.5) / h from +y (row 0 looks up), column j the azimuth phi = 2 pi (j + 0.5) / w,
direction = (sin theta cos phi, cos theta, sin theta sin phi).

recon's own renderer shades with order-2 SH, so maps are projected onto SH for it (exact for the
Lambertian irradiance up to the well-known ~1-3 % band-3+ residual). A procedural sun is kept out
of the projection and returned as a directional light, which the renderer handles exactly.
"""

from __future__ import annotations

import math

import torch

from recon.io.images import read_exr
from recon.render.shading import DirectionalLight, sh_basis


def equirect_directions(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions [h, w, 3] of texel centres and their solid angles [h, w] (sum = 4 pi)."""
    theta = (torch.arange(height, dtype=torch.float64) + 0.5) * math.pi / height
    phi = (torch.arange(width, dtype=torch.float64) + 0.5) * 2 * math.pi / width
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.cos(theta), torch.sin(theta) * torch.sin(phi)],
        dim=-1,
    )
    # Exact solid angle of each latitude band, split evenly over its texels.
    edges = torch.arange(height + 1, dtype=torch.float64) * math.pi / height
    band = (torch.cos(edges[:-1]) - torch.cos(edges[1:])) * (2 * math.pi / width)
    return directions.float(), band[:, None].expand(height, width).float()


def project_to_sh(environment: torch.Tensor) -> torch.Tensor:
    """SH coefficients [9, C] (order 2) of an equirectangular radiance map [h, w, C]."""
    height, width, channels = environment.shape
    directions, solid_angle = equirect_directions(height, width)
    basis = sh_basis(directions.reshape(-1, 3).double())  # [N, 9]
    weighted = environment.reshape(-1, channels).double() * solid_angle.reshape(-1, 1).double()
    return (basis.T @ weighted).float()


def sun_direction(elevation_deg: float, azimuth_deg: float) -> torch.Tensor:
    """Unit direction toward the sun [3] (y up; azimuth from +x toward +z)."""
    elevation = math.radians(elevation_deg)
    azimuth = math.radians(azimuth_deg)
    return torch.tensor(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.sin(elevation),
            math.cos(elevation) * math.sin(azimuth),
        ]
    )


def procedural_sky(
    height: int = 64,
    width: int = 128,
    zenith: tuple[float, float, float] = (0.25, 0.45, 0.9),
    horizon: tuple[float, float, float] = (0.8, 0.85, 0.95),
    ground: tuple[float, float, float] = (0.25, 0.22, 0.2),
    strength: float = 1.0,
) -> torch.Tensor:
    """A clear-sky gradient without the sun [h, w, 3] (the sun is a separate directional light)."""
    directions, _ = equirect_directions(height, width)
    up = directions[..., 1:2]
    sky_blend = up.clamp_min(0).sqrt()
    sky = torch.tensor(horizon) * (1 - sky_blend) + torch.tensor(zenith) * sky_blend
    # Ground: darker, with a soft transition below the horizon.
    ground_blend = (-up * 8).clamp(0, 1)
    image = sky * (1 - ground_blend) + torch.tensor(ground) * ground_blend
    return image * strength


def sun_light(
    elevation_deg: float, azimuth_deg: float, irradiance: float | list[float]
) -> DirectionalLight:
    return DirectionalLight(
        sun_direction(elevation_deg, azimuth_deg),
        torch.as_tensor(irradiance, dtype=torch.float32).expand(3).clone(),
    )


def procedural_studio(
    height: int = 64, width: int = 128, strength: float = 1.0, seed: int = 0
) -> torch.Tensor:
    """A dim room with three softboxes (key, fill, rim) as bright rectangles [h, w, 3]."""
    generator = torch.Generator().manual_seed(seed)
    image = torch.full((height, width, 3), 0.05)
    # (centre azimuth, centre elevation, half width, half height in degrees, radiance)
    boxes = [
        (40.0, 35.0, 18.0, 14.0, 6.0),  # key
        (150.0, 15.0, 25.0, 12.0, 2.0),  # fill
        (260.0, 50.0, 10.0, 20.0, 4.0),  # rim
    ]
    theta = (torch.arange(height) + 0.5) * 180.0 / height
    elevation = 90.0 - theta
    azimuth = (torch.arange(width) + 0.5) * 360.0 / width
    elevation, azimuth = torch.meshgrid(elevation, azimuth, indexing="ij")
    for centre_azimuth, centre_elevation, half_width, half_height, radiance in boxes:
        jitter = (torch.rand(2, generator=generator) - 0.5) * 10
        azimuth_distance = (azimuth - centre_azimuth - jitter[0] + 180) % 360 - 180
        inside = (azimuth_distance.abs() <= half_width) & (
            (elevation - centre_elevation - jitter[1]).abs() <= half_height
        )
        image[inside] = radiance
    return image * strength


def load_environment(path: str, strength: float = 1.0) -> torch.Tensor:
    """An HDR equirectangular map [h, w, 3] from an EXR file (our convention above)."""
    image = read_exr(path)
    return image[..., :3] * strength
