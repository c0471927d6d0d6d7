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
