"""The highlights seed of the pbr environment: back-projection of the specular excess along
mirror-reflection directions (recon/render/environment_seed.py)."""

from __future__ import annotations

import math

import pytest
import torch

from recon.errors import ReconError
from recon.render.environment import latlong_directions, sample_latlong
from recon.render.environment_seed import backproject_highlights, specular_weight

SIZE = (16, 32)
ROUGHNESS = 0.1


def _sphere_views(view_directions: list[list[float]], count: int = 4000):
    """Pixels of a unit sphere seen from far away along each direction: [N, 3] normals and
    directions to the viewer (only the visible hemisphere)."""
    generator = torch.Generator().manual_seed(0)
    normals, to_viewer = [], []
    for direction in view_directions:
        view = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float32), dim=0)
        points = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1)
        visible = points @ view > 0
        normals.append(points[visible])
        to_viewer.append(view.expand(int(visible.sum()), 3))
    return torch.cat(normals), torch.cat(to_viewer)


def _mirror_radiance(environment, normals, to_viewer):
    """The split-sum specular of a dielectric at ROUGHNESS looking the map up at R (no blur)."""
    n_dot_v = (normals * to_viewer).sum(-1, keepdim=True)
    reflected = 2 * n_dot_v * normals - to_viewer
    return specular_weight(n_dot_v, ROUGHNESS) * sample_latlong(environment, reflected)


def test_a_single_highlight_seeds_a_bright_texel_in_its_direction():
    directions, _ = latlong_directions(*SIZE)
    truth = torch.full((*SIZE, 3), 0.1)
    row, column = 5, 9  # a small bright light above the horizon
    truth[row, column] = 20.0
    normals, to_viewer = _sphere_views([[0, 0, 1], [1, 0.3, 0], [0, 0.5, -1], [-1, 0.2, 0.3]])
    diffuse = torch.full((normals.shape[0], 3), 0.3)
    observed = diffuse + _mirror_radiance(truth, normals, to_viewer)
    prior = torch.full((*SIZE, 3), 0.5)

    seeded = backproject_highlights(observed, diffuse, normals, to_viewer, prior, ROUGHNESS)

    brightest = int(seeded[..., 0].argmax())
    found = directions.reshape(-1, 3)[brightest]
    angle = math.degrees(math.acos(min(float((found * directions[row, column]).sum()), 1.0)))
    assert angle < 360 / SIZE[1] + 1e-3, angle  # within one texel
    # The bilinear splat spreads the light over its neighbours; their sum keeps most of it.
    neighbourhood = seeded[row - 1 : row + 2, column - 1 : column + 2, 0].sum()
    assert 0.6 * 20 < float(neighbourhood) < 1.4 * 20, float(neighbourhood)
    # Far from the light the seed holds the dim room, not the prior's 0.5.
    assert float(seeded[12, 25, 0]) < 0.3


def test_texels_no_reflection_reaches_keep_the_prior():
    # One view along +z: reflections within 2 acos(0.2) of +z; the texel around -z gets none.
    normals, to_viewer = _sphere_views([[0, 0, 1]])
    observed = torch.full((normals.shape[0], 3), 0.4)
    prior = torch.rand(*SIZE, 3, generator=torch.Generator().manual_seed(1)) + 0.5
    seeded = backproject_highlights(
        observed, torch.zeros_like(observed), normals, to_viewer, prior, ROUGHNESS
    )
    directions, _ = latlong_directions(*SIZE)
    away = int((directions.reshape(-1, 3) @ torch.tensor([0.0, 0.0, -1.0])).argmax())
    torch.testing.assert_close(seeded.reshape(-1, 3)[away], prior.reshape(-1, 3)[away])


def test_the_prior_weight_pulls_toward_the_prior():
    normals, to_viewer = _sphere_views([[0, 0, 1]], count=200)
    observed = torch.full((normals.shape[0], 3), 0.4)
    prior = torch.full((*SIZE, 3), 3.0)
    arguments = (observed, torch.zeros_like(observed), normals, to_viewer, prior, ROUGHNESS)
    free = backproject_highlights(*arguments, prior_weight=1e-6)
    pulled = backproject_highlights(*arguments, prior_weight=1e3)
    assert float((pulled - prior).abs().max()) < 0.01
    assert float((free - prior).abs().max()) > 1.0


@pytest.mark.parametrize(
    "observed, normals, prior, match",
    [
        (torch.zeros(5, 3), torch.zeros(4, 3), torch.zeros(*SIZE, 3), "normals"),
        (torch.zeros(5, 3), torch.zeros(5, 3), torch.zeros(*SIZE, 1), "prior"),
        (torch.zeros(5), torch.zeros(5, 3), torch.zeros(*SIZE, 3), "observed"),
    ],
)
def test_shapes_are_checked_by_name(observed, normals, prior, match):
    with pytest.raises(ReconError, match=match):
        backproject_highlights(observed, observed, normals, normals, prior, ROUGHNESS)
