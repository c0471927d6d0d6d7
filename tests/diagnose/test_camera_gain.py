"""The exposure's per-view gains read apart from a highlight: the camera's gain on a glossy
object, where a plain per-view gain also takes how much highlight each view shows."""

from __future__ import annotations

import torch
from diagnose_scenes import glossy_torus_views

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.camera_gain import gain_evidence, highlight_free_log_gains

SETTINGS = DiagnoseConfig()


def ratio_errors(log_gains: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """Median and largest relative error of per-view gains, both normalised by their geometric
    mean (as the blind benchmark scores them)."""
    truth = truth.double().log()
    relative = ((log_gains - log_gains.mean()) - (truth - truth.mean())).exp() - 1
    return float(relative.abs().median()), float(relative.abs().max())


def least_squares_log_gains(data) -> torch.Tensor:
    observed, rendered = data.observed.double(), data.rendered.double()
    weight = data.region.double()
    return torch.log(
        (observed * rendered * weight).sum((1, 2, 3)) / (rendered**2 * weight).sum((1, 2, 3))
    )


def test_an_exposure_on_a_glossy_object_is_recovered_apart_from_its_highlight():
    # A white and a gold highlight on a diffuse fit, per-view exposures of 0.3 log RMS.
    for colour in ((1.0, 1.0, 1.0), (1.0, 0.7, 0.25)):
        data, gains = glossy_torus_views(
            views=8,
            size=32,
            specular=1.0,
            shininess=20.0,
            specular_colour=colour,
            exposure_sigma=0.3,
        )
        log_gains, _ = highlight_free_log_gains(
            data, SETTINGS.exposure_highlight_powers, SETTINGS.exposure_gain_iterations
        )
        median, largest = ratio_errors(log_gains, gains)
        assert median < 0.02 and largest < 0.05, (median, largest)
        # A plain least-squares gain per view takes the views' highlight with it.
        plain_median, _ = ratio_errors(least_squares_log_gains(data), gains)
        assert plain_median > 3 * median, (plain_median, median)


def test_without_a_highlight_the_gains_are_the_least_squares_gains():
    data, gains = glossy_torus_views(views=8, size=32, specular=0.0, exposure_sigma=0.3)
    log_gains, lobes = highlight_free_log_gains(
        data, SETTINGS.exposure_highlight_powers, SETTINGS.exposure_gain_iterations
    )
    plain = least_squares_log_gains(data)
    assert torch.allclose(log_gains - log_gains.mean(), plain - plain.mean(), atol=2e-3)
    assert ratio_errors(log_gains, gains)[1] < 0.01


def test_the_evidence_reports_the_gains_as_the_exposure_parameters():
    data, gains = glossy_torus_views(
        views=8, size=32, specular=1.0, shininess=20.0, exposure_sigma=0.3
    )
    evidence = gain_evidence(data, SETTINGS)
    assert evidence.kind == "gain" and evidence.candidate == "exposure"
    ratios = torch.tensor(evidence.details["parameters"]["ratios"], dtype=torch.float64)
    assert ratios.numel() == 8
    assert abs(float(ratios.log().mean())) < 1e-9  # normalised by their geometric mean
    assert ratio_errors(ratios.log(), gains)[0] < 0.02
    assert "highlight" in evidence.reason


def _whole_image_log_gains(data, powers, iterations):
    """highlight_free_log_gains the straightforward way: masked sums over whole images."""
    from recon.diagnose.agreement import surface_angles

    observed, rendered = data.observed.double(), data.rendered.double()
    weight = data.region.double()[..., 0] > 0
    n_dot_h, _ = surface_angles(data)
    coverage = data.rendered_alpha.double()[..., 0]
    lobes = torch.stack([n_dot_h.clamp_min(0.0).pow(power) * coverage for power in powers], -1)
    gains = torch.ones(observed.shape[0], dtype=torch.float64)
    coefficients = torch.zeros(len(powers), 3, dtype=torch.float64)
    mask = weight[..., None].double()
    for _ in range(iterations):
        predicted = rendered + torch.einsum("bhwk,kc->bhwc", lobes, coefficients)
        energy = (predicted * predicted * mask).sum(dim=(1, 2, 3))
        gains = (observed * predicted * mask).sum(dim=(1, 2, 3)) / energy
        design = (gains[:, None, None, None] * lobes)[weight]
        target = (observed - gains[:, None, None, None] * rendered)[weight]
        coefficients = torch.linalg.lstsq(design, target).solution
    return gains.log(), coefficients


def test_the_packed_fit_equals_the_whole_image_fit():
    """The fit on the region's packed pixels is the masked whole-image fit (to rounding)."""
    data, _ = glossy_torus_views(views=5, size=32, specular=1.0, shininess=20.0, exposure_sigma=0.3)
    powers, iterations = SETTINGS.exposure_highlight_powers, SETTINGS.exposure_gain_iterations
    log_gains, coefficients = highlight_free_log_gains(data, powers, iterations)
    plain_gains, plain_coefficients = _whole_image_log_gains(data, powers, iterations)
    assert float(coefficients.abs().max()) > 1e-3  # a highlight to fit
    assert torch.allclose(log_gains, plain_gains, rtol=0, atol=1e-12)
    assert torch.allclose(coefficients, plain_coefficients, rtol=0, atol=1e-12)


def _with_misfit_region(data, view: int, factor: float):
    """data with one view's observed pixels brighter by factor in the upper-left quadrant of its
    object (a region the fit got wrong in that view alone: a highlight no other view shows)."""
    from dataclasses import replace

    inside = data.rendered_alpha[view, ..., 0] > 0.5
    rows, columns = inside.nonzero(as_tuple=True)
    quadrant = torch.zeros_like(inside)
    upper = rows < rows.float().median()
    left = columns < columns.float().median()
    quadrant[rows[upper & left], columns[upper & left]] = True
    observed = data.observed.clone()
    observed[view][quadrant] *= factor
    return replace(data, observed=observed)


def test_one_views_misfit_region_does_not_move_its_robust_gain():
    """Built to fool the estimator: one view's quadrant of the object 60 % brighter than the
    model (and than any other view shows there). Least squares moves that view's gain by
    about the quadrant's share; the regions' robust fit rejects the quadrant's cells."""
    from dataclasses import replace as replace_settings

    data, gains = glossy_torus_views(views=8, size=32, specular=0.0, exposure_sigma=0.3)
    fooled = _with_misfit_region(data, view=3, factor=1.6)
    plain, _ = highlight_free_log_gains(
        fooled, SETTINGS.exposure_highlight_powers, SETTINGS.exposure_gain_iterations
    )
    plain_error = plain - plain.mean() - (gains.double().log() - gains.double().log().mean())
    assert abs(float(plain_error[3].exp()) - 1) > 0.08, plain_error
    robust = replace_settings(SETTINGS, exposure_gain_estimator="robust_regions")
    evidence = gain_evidence(fooled, robust)
    ratios = torch.tensor(evidence.details["parameters"]["ratios"], dtype=torch.float64)
    median, largest = ratio_errors(ratios.log(), gains)
    assert largest < 0.02, (median, largest)
    assert evidence.details["parameters"]["estimator"] == "robust_regions"
    assert 0 < evidence.details["rejected_cells"] < 0.2
    assert "regions" in evidence.reason


def test_robust_regions_recover_an_exposure_under_a_shared_highlight():
    """A highlight every view shows is read against the shared lobe, and what the lobe leaves
    of it is a region's mismatch that every view shares, not a view's gain."""
    from dataclasses import replace as replace_settings

    data, gains = glossy_torus_views(
        views=8, size=32, specular=1.0, shininess=20.0, exposure_sigma=0.3
    )
    robust = replace_settings(SETTINGS, exposure_gain_estimator="robust_regions")
    ratios = torch.tensor(
        gain_evidence(data, robust).details["parameters"]["ratios"], dtype=torch.float64
    )
    median, largest = ratio_errors(ratios.log(), gains)
    assert median < 0.01 and largest < 0.02, (median, largest)
