"""Camera rigs: where the synthetic captures are taken from (y is up in the world)."""

from __future__ import annotations

import math

import torch

from recon.camera import Cameras, intrinsics_from_fov, look_at
from recon.config.run_config import CameraRigConfig
from recon.errors import ReconError


def rig_directions(rig: str, count: int, generator: torch.Generator) -> torch.Tensor:
    """Unit directions [count, 3] from the object toward each camera."""
    if count <= 0:
        return torch.zeros(0, 3)
    if rig in ("fibonacci", "hemisphere"):
        # Fibonacci lattice: near-uniform points; the hemisphere rig keeps y >= 0 (above ground).
        index = torch.arange(count, dtype=torch.float64) + 0.5
        if rig == "fibonacci":
            height = 1 - 2 * index / count
        else:
            height = 1 - index / count
        radius = torch.sqrt((1 - height**2).clamp_min(0))
        angle = index * math.pi * (3 - math.sqrt(5))
        directions = torch.stack([radius * torch.cos(angle), height, radius * torch.sin(angle)], -1)
    elif rig == "orbit":
        # Rings at three elevations, cameras spread around each.
        elevations = torch.tensor([-15.0, 15.0, 45.0])
        ring = torch.arange(count) % 3
        position = torch.arange(count) // 3
        per_ring = math.ceil(count / 3)
        azimuth = (position.double() + 0.5 * ring.double()) * (2 * math.pi / per_ring)
        elevation = torch.deg2rad(elevations[ring].double())
        directions = torch.stack(
            [
                torch.cos(elevation) * torch.sin(azimuth),
                torch.sin(elevation),
                torch.cos(elevation) * torch.cos(azimuth),
            ],
            -1,
        )
    elif rig == "random":
        directions = torch.randn(count, 3, generator=generator, dtype=torch.float64)
        directions = torch.nn.functional.normalize(directions, dim=-1)
    else:
        raise ReconError(f"cameras.rig: unknown rig {rig!r}")
    return directions.float()


def _jitter(directions: torch.Tensor, degrees: float, generator: torch.Generator) -> torch.Tensor:
    if degrees <= 0:
        return directions
    noise = torch.randn(directions.shape, generator=generator) * math.radians(degrees)
    return torch.nn.functional.normalize(directions + noise, dim=-1)


def make_cameras(
    config: CameraRigConfig, count: int, generator: torch.Generator, offset: int = 0
) -> Cameras:
    """count cameras of the rig; offset rotates the lattice so splits get disjoint views."""
    directions = rig_directions(config.rig, count, generator)
    if offset and count:
        # Rotate about y by an irrational fraction of a turn: same distribution, other views.
        angle = offset * math.pi * (math.sqrt(5) - 1)
        rotation = torch.tensor(
            [
                [math.cos(angle), 0.0, math.sin(angle)],
                [0.0, 1.0, 0.0],
                [-math.sin(angle), 0.0, math.cos(angle)],
            ]
        )
        directions = directions @ rotation.T
    directions = _jitter(directions, config.jitter_deg, generator)
    height, width = config.resolution
    intrinsics = intrinsics_from_fov(config.fov_deg, (height, width))
    return Cameras(
        world_to_cam=look_at(directions * config.distance),
        intrinsics=intrinsics[None].repeat(count, 1, 1),
        image_size=(height, width),
        near=config.near,
        far=config.far,
    )
