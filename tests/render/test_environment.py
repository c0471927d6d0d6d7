"""Suns added to a lat-long environment (recon.render.environment.add_suns): the splat keeps
the sun's irradiance and direction, at the azimuth seam and near the poles too."""

from __future__ import annotations

import math

import pytest
import torch

from recon.render.environment import add_suns, latlong_directions
from recon.render.shading import DirectionalLight


@pytest.mark.parametrize(
    "direction",
    [
        (0.3, 0.8, -0.5),
        (1.0, 0.0, -1e-3),  # azimuth just below 2 pi: the splat wraps over the seam
        (0.02, 0.999, 0.01),  # beyond the first row's centre
        (0.0, -0.6, 0.8),
    ],
)
def test_the_added_sun_keeps_its_irradiance_and_direction(direction):
    height, width = 16, 32
    environment = torch.zeros(height, width, 3)
    to_light = torch.nn.functional.normalize(torch.tensor(direction), dim=0)
    sun = DirectionalLight(to_light, torch.tensor([2.0, 1.0, 0.5]))
    combined = add_suns(environment, [sun])
    directions, solid_angle = latlong_directions(height, width)
    energy = combined * solid_angle[..., None]
    torch.testing.assert_close(energy.sum(dim=(0, 1)), sun.irradiance, rtol=1e-5, atol=1e-5)
    # The energy-weighted mean direction lies within a texel of the sun.
    mean = torch.nn.functional.normalize((energy[..., :1] * directions).sum(dim=(0, 1)), dim=0)
    assert float(torch.acos((mean @ to_light).clamp(-1, 1))) < 2 * math.pi / width


def test_the_environment_itself_is_not_changed():
    environment = torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(0))
    before = environment.clone()
    sun = DirectionalLight(torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 1.0, 1.0]))
    combined = add_suns(environment, [sun, sun])
    torch.testing.assert_close(environment, before)
    _, solid_angle = latlong_directions(8, 16)
    added = ((combined - environment) * solid_angle[..., None]).sum(dim=(0, 1))
    torch.testing.assert_close(added, torch.full((3,), 2.0), rtol=1e-5, atol=1e-5)
