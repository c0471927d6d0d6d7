"""Vignetting absorption by regression: with the falloff baked into the texture, the cell gains
plus a falloff predict held-out views better than the cell gains alone, and the falloff comes
back; on clean views, or on views brighter towards the rim, there is no evidence."""

from __future__ import annotations

import pytest
import torch
from diagnose_scenes import patterned_torus

from recon.camera import orbit_cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.radial_absorption import InteriorPixels, fit_gains, radial_absorption
from recon.diagnose.which import bootstrap_reduction
from recon.effects import make_effect
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

SETTINGS = DiagnoseConfig()

SIZE, TRAIN, TEST = 64, 12, 6


def training_and_heldout(corner_change: float, noise: float = 0.0):
    """DiagnosisData of TRAIN and TEST orbit views: observed = the true scene times the falloff
    1 + corner_change r^2 (plus Gaussian noise); fitted = the texture times 1 + 0.3
    corner_change (the average falloff a fit without the effect bakes in)."""
    generator = torch.Generator().manual_seed(0)
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.7 * p + 0.2, 0.5 * (1 - p) + 0.2])
    lighting = Lighting.constant(0.9)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    cameras = orbit_cameras(
        TRAIN + TEST, (SIZE, SIZE), distance=2.2, fov_x_deg=60, elevation_deg=35
    )
    with torch.no_grad():
        truth = renderer.render(mesh, cameras, lighting)
        vignetting = make_effect("vignetting")
        vignetting.set_polynomial(corner_change)
        observed, _ = vignetting(truth.color, truth.alpha, cameras, None)
        observed = observed + noise * torch.randn(observed.shape, generator=generator)
        mesh.texture = mesh.texture * (1 + 0.3 * corner_change)

    def split(views: slice):
        with torch.no_grad():
            fitted = renderer.render(mesh, cameras[views], lighting)
        return build_diagnosis_data(
            observed[views], truth.alpha[views], fitted, cameras[views], lighting, mesh
        )

    return split(slice(0, TRAIN)), split(slice(TRAIN, TRAIN + TEST))


def test_baked_in_vignetting_is_taken_back_and_its_falloff_recovered() -> None:
    training, heldout = training_and_heldout(-0.5, noise=0.002)
    control, with_falloff, module = radial_absorption(training, heldout, SETTINGS)
    reduction, (low, _) = bootstrap_reduction(control, with_falloff, SETTINGS.bootstrap_samples)
    assert low > 0.3 and reduction > 0.5
    summary = module.parameters_summary()
    # The truth is 1 - 0.5 r^2: 0.875 half-way out.
    assert summary["half_radius_falloff"] == pytest.approx(0.875, abs=0.01)


def test_clean_views_give_no_evidence() -> None:
    training, heldout = training_and_heldout(0.0, noise=0.002)
    control, with_falloff, module = radial_absorption(training, heldout, SETTINGS)
    reduction, (low, high) = bootstrap_reduction(control, with_falloff, SETTINGS.bootstrap_samples)
    assert abs(reduction) < 0.01 and low < 0.005
    assert module.parameters_summary()["half_radius_falloff"] == pytest.approx(1.0, abs=0.01)


def test_a_brightening_falloff_is_not_vignetting() -> None:
    training, heldout = training_and_heldout(0.4)
    control, with_falloff, module = radial_absorption(training, heldout, SETTINGS)
    assert module.parameters_summary()["half_radius_falloff"] > 1.05
    assert torch.equal(control, with_falloff)


def test_view_gains_hold_a_per_view_exposure() -> None:
    """An exposure change per training view is not a falloff: the fitted one stays flat."""
    training, _ = training_and_heldout(0.0)
    gains = torch.linspace(0.7, 1.3, TRAIN)[:, None, None, None]
    training.observed = training.observed * gains
    fit = fit_gains(InteriorPixels.from_data(training, SETTINGS), with_falloff=True)
    assert fit.coefficients.abs().max() < 0.01


def test_interior_pixels_equal_the_mask_indexed_columns() -> None:
    """from_data gathers the kept rows through one list of flat indices: every column equals
    the plain boolean-mask indexing of the [B, H, W, 3] images, bit for bit."""
    from recon.diagnose.data import box_dilate
    from recon.diagnose.radial_absorption import FULL_COVERAGE
    from recon.diagnose.which import block_halves
    from recon.effects.photometric import normalised_radius

    training, _ = training_and_heldout(-0.5, noise=0.002)
    pixels = InteriorPixels.from_data(training, SETTINGS)
    # The plain computation: the mask applied to each column.
    data, cells = training, SETTINGS.regression_cells_per_side
    batch, height, width, channels = data.observed.shape
    covered = (data.rendered_alpha >= FULL_COVERAGE) & (data.observed_alpha >= FULL_COVERAGE)
    covered = covered & (data.texel_uv[..., :1] >= 0)
    outside = (~covered).float().permute(0, 3, 1, 2)
    interior = box_dilate(outside, SETTINGS.regression_interior_margin) == 0
    interior = interior.permute(0, 2, 3, 1).expand(batch, height, width, channels)
    keep = interior & (data.rendered > SETTINGS.regression_minimum_rendered) & (data.observed > 0)

    def per_channel(values: torch.Tensor) -> torch.Tensor:
        return values[..., None].expand(batch, height, width, channels)[keep]

    uv = (data.texel_uv * cells).long().clamp(0, cells - 1)
    channel = torch.arange(channels).expand(batch, height, width, -1)[keep]
    view = torch.arange(batch)[:, None, None].expand(batch, height, width)
    first, _ = block_halves(batch, height, width, "cpu", SETTINGS.block_pixels)
    radius = normalised_radius(data.cameras, height, width, data.rendered)
    assert int(keep.sum()) > 1000
    assert torch.equal(pixels.rendered, data.rendered[keep].double())
    assert torch.equal(pixels.observed, data.observed[keep].double())
    assert torch.equal(pixels.radius, per_channel(radius).double())
    assert torch.equal(pixels.cell, per_channel(uv[..., 1] * cells + uv[..., 0]) * 3 + channel)
    assert torch.equal(pixels.view, per_channel(view) * channels + channel)
    assert torch.equal(pixels.first_half, per_channel(first[..., 0] > 0))
