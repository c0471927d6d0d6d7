"""The warm-started refit's settings: a response curve's exponent held at the relight probe's
estimate, the steps and step size handed to the texture stage, and the fit's own effects
switched on at their fitted parameters."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import recon.diagnose.refit as refit
from recon.config.run_config import RunConfig
from recon.diagnose.refit import RefitSettings
from recon.effects.registry import make_effect


class Captured(Exception):
    """Raised by the stand-in texture stage with what the refit handed it."""


def capture_refit(monkeypatch, names, settings, model_effects=()):
    mesh = SimpleNamespace(verts=torch.zeros(3, 3), faces=torch.zeros(1, 3, dtype=torch.long))
    mesh.to = lambda device: mesh
    lighting = SimpleNamespace(to=lambda device: None)
    model = SimpleNamespace(
        mesh=mesh,
        lighting=lighting,
        effects=list(model_effects),
        effect_names=[module.name for module in model_effects],
        pbr=None,
    )
    monkeypatch.setattr(refit.LightModel, "from_lighting", staticmethod(lambda lighting: None))

    def texture_stage(captures, geometry, fit_config, *arguments, effects, **keywords):
        raise Captured(fit_config, effects)

    monkeypatch.setattr(refit, "run_texture_stage", texture_stage)
    training = SimpleNamespace(cameras=[0] * 4)
    with pytest.raises(Captured) as caught:
        refit.refit_with(
            names, training, model, RunConfig(), torch.device("cpu"), Path("scratch"), settings
        )
    return caught.value.args


def test_a_response_refit_holds_the_given_exponent(monkeypatch):
    settings = RefitSettings(steps=5, response_exponent=0.8)
    fit_config, effects = capture_refit(monkeypatch, ["response_curve"], settings)
    (curve,) = effects.modules
    assert float(curve.log_gamma.exp()) == pytest.approx(0.8)
    assert not curve.log_gamma.requires_grad and curve.lut.requires_grad
    assert fit_config.texture.steps == 5
    default_rate = RunConfig().diagnose.refit_position_learning_rate
    assert fit_config.texture.learning_rate == default_rate
    _, effects = capture_refit(monkeypatch, ["response_curve"], RefitSettings(steps=5))
    assert (
        float(effects.modules[0].log_gamma.detach()) == 0.0
        and effects.modules[0].log_gamma.requires_grad
    )


def test_the_given_step_size_reaches_the_texture_stage(monkeypatch):
    settings = RefitSettings(steps=5, position_learning_rate=0.01)
    fit_config, _ = capture_refit(monkeypatch, ["lens_distortion"], settings)
    assert fit_config.texture.learning_rate == 0.01


def test_the_fits_own_effects_are_switched_on_at_their_fitted_parameters(monkeypatch):
    fitted = make_effect("vignetting")
    with torch.no_grad():
        fitted.coefficients.fill_(-0.3)
    _, effects = capture_refit(
        monkeypatch, ["exposure"], RefitSettings(steps=5), model_effects=[fitted]
    )
    assert [module.name for module in effects.modules] == ["vignetting", "exposure"]
    assert torch.equal(effects.modules[0].coefficients, fitted.coefficients)
    assert effects.modules[1].is_identity()


def _pbr_model():
    """A glossy sphere (roughness 0.3) under a softbox: its pbr result, a perfect fit of the
    clean scene."""
    import trimesh

    from recon.mesh.mesh import Mesh
    from recon.mesh.uv import bake_vertex_attribute, dilate, unwrap
    from recon.optimize.material_stage import PbrTextureResult, light_from_environment
    from recon.render.environment import latlong_directions

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    uvs, uv_faces = unwrap(verts, faces, resolution=64)
    colour = torch.where(
        verts[:, 1:2] > 0.2, torch.tensor([0.7, 0.25, 0.2]), torch.tensor([0.2, 0.4, 0.7])
    )
    base, coverage = bake_vertex_attribute((faces, uvs, uv_faces), colour, (64, 64))
    texture = dilate(base.float(), coverage)
    mesh = Mesh(verts, faces, uvs=uvs.float(), uv_faces=uv_faces, texture=texture)
    directions, _ = latlong_directions(8, 16)
    key = torch.tensor([0.5, 0.7, 0.5])
    glow = 6 * torch.exp((directions @ (key / key.norm()) - 1) / 0.05)
    environment = (0.3 + glow)[..., None].expand(8, 16, 3).contiguous()
    material = torch.tensor([0.3, 0.0]).expand(64, 64, 2).contiguous()
    shading = RunConfig().fit.pbr  # the run's settings, which the refit shades with too
    light = light_from_environment(environment)
    return PbrTextureResult(
        mesh, material, environment, light, shading.specular_level, shading.prefilter_levels
    )


def _pbr_captures(pbr, gains: torch.Tensor, split: str):
    """Views of the pbr scene from len(gains) fibonacci points, each times its exposure gain."""
    from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at
    from recon.io.datasets import CaptureSet
    from recon.render.renderer import Renderer

    count = len(gains)
    index = torch.arange(count, dtype=torch.float32) + 0.5
    height = 1 - 2 * index / count
    radius = (1 - height**2).sqrt()
    angle = index * 2.4
    eyes = 3.0 * torch.stack([radius * angle.cos(), height, radius * angle.sin()], -1)
    intrinsics = intrinsics_from_fov(30.0, (24, 24)).expand(count, 3, 3)
    cameras = Cameras(look_at(eyes), intrinsics, (24, 24))
    with torch.no_grad():
        output = pbr.render(Renderer(texture_boundary="clamp"), cameras)
    images = output.color * gains[:, None, None, None]
    names = [f"{split}_{i}" for i in range(count)]
    return CaptureSet(cameras, images, output.alpha, names, split)


def _pbr_config(steps: int) -> RunConfig:
    config = RunConfig()
    config.fit.material = "pbr"
    config.fit.texture.texture_size = 64
    config.fit.texture.views_per_step = 4
    config.fit.checkpoint_every = 1000
    config.diagnose.refit_steps = steps
    return config


def test_a_pbr_refit_warm_starts_the_pbr_stage_and_takes_out_an_exposure(tmp_path):
    """A fit.material pbr model is refitted with its own material model: a refit of no steps
    renders exactly the fitted pbr scene (the Lambertian texture stage would lose the
    highlight), and a short refit with exposure switched on, on training views with per-view
    gains, closes most of the held-out gap of held-out views with gains of their own."""
    from recon.diagnose.data import FittedModel, render_diagnosis_data
    from recon.diagnose.how_far import RefitBaseline, RefitInputs, measure_refit
    from recon.render.renderer import Renderer

    pbr = _pbr_model()
    gains = torch.tensor([1.0, 0.7, 1.3, 0.85, 1.15, 0.75])
    training = _pbr_captures(pbr, gains, "train")
    model = FittedModel(pbr.mesh, pbr.light.lighting(), [], pbr)
    device = torch.device("cpu")
    still, _ = refit.refit_with(
        [], training, model, _pbr_config(0), device, tmp_path, RefitSettings(steps=0)
    )
    assert still.pbr is not None and still.material == "pbr"
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    with torch.no_grad():
        fitted = model.render(renderer, training.cameras).color
        assert torch.allclose(still.render(renderer, training.cameras).color, fitted, atol=1e-5)

    heldout = _pbr_captures(pbr, torch.tensor([1.25, 0.8, 1.1, 0.7]), "test")
    config = _pbr_config(30)
    data = render_diagnosis_data(heldout, model, device, config.diagnose.band_pixels)
    baseline = RefitBaseline.measure(data, 0.0, None, config.diagnose)
    inputs = RefitInputs(training, model, config, device, tmp_path)
    settings = RefitSettings(steps=30, position_learning_rate=0.0)
    record, _ = measure_refit(["exposure"], baseline, inputs, settings)
    assert record["closed_fraction"] > 0.8, record
    ratios = torch.tensor(record["parameters"]["exposure"]["ratios"])
    assert torch.allclose(ratios / ratios[0], gains / gains[0], rtol=0.1), ratios


def test_a_pbr_refit_of_a_fit_with_a_sun_starts_from_the_fitted_sun(tmp_path):
    """fit.pbr.sun_lights: the fitted environment no longer holds the sun, so a refit must not
    split another one off it: a refit of no steps keeps the fitted sun and renders the fit."""
    from dataclasses import replace

    from recon.diagnose.data import FittedModel
    from recon.render.renderer import Renderer
    from recon.render.shading import DirectionalLight

    sun = DirectionalLight(
        torch.nn.functional.normalize(torch.tensor([0.4, 0.8, 0.3]), dim=0),
        torch.tensor([2.5, 2.4, 2.2]),
    )
    pbr = replace(_pbr_model(), suns=[sun])
    training = _pbr_captures(pbr, torch.ones(4), "train")
    model = FittedModel(pbr.mesh, pbr.light.lighting(), [], pbr)
    config = _pbr_config(0)
    config.fit.pbr.sun_lights = 1
    still, _ = refit.refit_with(
        [], training, model, config, torch.device("cpu"), tmp_path, RefitSettings(steps=0)
    )
    (kept,) = still.pbr.suns
    assert torch.allclose(kept.direction_to_light, sun.direction_to_light, atol=1e-6)
    assert torch.allclose(kept.irradiance, sun.irradiance, atol=1e-5)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    with torch.no_grad():
        fitted = model.render(renderer, training.cameras).color
        assert torch.allclose(still.render(renderer, training.cameras).color, fitted, atol=1e-5)
