"""Environment maps: solid angles, SH projection, procedural sky and studio."""

from __future__ import annotations

import math

import torch

from data_synth.environment import (
    equirect_directions,
    procedural_sky,
    procedural_studio,
    project_to_sh,
    sun_direction,
)
from recon.io.images import write_exr
from recon.render.shading import Lighting, sh_basis, sh_irradiance


def test_solid_angles_sum_to_the_sphere_and_directions_are_unit():
    directions, solid_angle = equirect_directions(32, 64)
    assert abs(float(solid_angle.sum()) - 4 * math.pi) < 1e-4
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(32, 64))
    assert float(directions[0, 0, 1]) > 0.99  # row 0 looks up


def test_projection_recovers_band_limited_radiance():
    coefficients = torch.randn(9, 3, generator=torch.Generator().manual_seed(1))
    directions, _ = equirect_directions(128, 256)
    environment = sh_basis(directions) @ coefficients
    torch.testing.assert_close(project_to_sh(environment), coefficients, atol=2e-3, rtol=1e-3)


def test_constant_environment_projects_to_constant_lighting():
    # Texel-centre quadrature leaves a small band-2 residual on a coarse grid.
    sh = project_to_sh(torch.full((64, 128, 3), 0.7))
    torch.testing.assert_close(sh, Lighting.constant(0.7).sh_coefficients, atol=1e-3, rtol=1e-3)


def test_sky_is_brighter_above_and_irradiance_follows():
    sky = procedural_sky(32, 64)
    assert float(sky[0].mean()) > float(sky[-1].mean())
    sh = project_to_sh(sky)
    up = sh_irradiance(torch.tensor([[0.0, 1.0, 0.0]]), sh)
    down = sh_irradiance(torch.tensor([[0.0, -1.0, 0.0]]), sh)
    assert bool((up > down).all())


def test_studio_key_light_side_is_brighter_and_seeded():
    studio = procedural_studio(32, 64, seed=3)
    assert torch.equal(studio, procedural_studio(32, 64, seed=3))
    assert not torch.equal(studio, procedural_studio(32, 64, seed=4))
    sh = project_to_sh(studio)
    key = sun_direction(35.0, 40.0)
    toward_key = sh_irradiance(key[None], sh)
    away = sh_irradiance(-key[None], sh)
    assert bool((toward_key > away).all())


def test_exr_environment_round_trip(tmp_path):
    from data_synth.environment import load_environment

    sky = procedural_sky(16, 32)
    write_exr(tmp_path / "sky.exr", sky)
    torch.testing.assert_close(load_environment(str(tmp_path / "sky.exr"), strength=2.0), sky * 2)
