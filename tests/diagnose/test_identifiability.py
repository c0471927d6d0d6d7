"""Identifiability as an output: built to fool a diagnosis that only looks at residuals.

A tone curve under one fixed light, a falloff where the object stays in the middle of the
image, a distortion of a small centred object (a per-view zoom reproduces it), a blur in views
whose edges all run one way: each must come back as "not identifiable from this data,
because ..." with the capture that would settle it; the same effects with the right capture
must come back identifiable.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest
import torch
from diagnose_scenes import glossy_torus_views

from recon.config.run_config import IdentifiabilityConfig
from recon.diagnose.identifiability import (
    CaptureConditions,
    covered_radius,
    identifiability_evidence,
    motion_blur_evidence,
)


def by_candidate(evidence):
    return {item.candidate: item for item in evidence}


def test_a_tone_curve_under_one_light_is_not_identifiable():
    data, _ = glossy_torus_views(specular=0.0, size=32, views=6)
    curve = by_candidate(identifiability_evidence(data))["response_curve"]
    assert curve.kind == "identifiability" and not curve.passed
    assert curve.reason.startswith("response_curve is not identifiable from this data, because")
    assert "bracketed exposures or a second light" in curve.reason
    # Known exposures barely apart do not help; a bracket or a relight split does.
    small = CaptureConditions(exposure_gains=torch.tensor([1.0, 1.1, 0.95]))
    assert not by_candidate(identifiability_evidence(data, small))["response_curve"].passed
    bracket = CaptureConditions(exposure_gains=torch.tensor([1.0, 2.0, 0.5]))
    assert by_candidate(identifiability_evidence(data, bracket))["response_curve"].passed
    relight = CaptureConditions(relight=True)
    assert by_candidate(identifiability_evidence(data, relight))["response_curve"].passed
    # A light that turns with the camera is fitted with the scene: (albedo x shading)^g is
    # albedo^g x shading^g, which the fit absorbs whole (the real capture's turntable).
    turning = replace(data, lighting=replace(data.lighting, frame="camera"))
    curve = by_candidate(identifiability_evidence(turning))["response_curve"]
    assert not curve.passed and "turns with the camera" in curve.reason
    assert curve.details["camera_frame_light"] is True


def test_vignetting_needs_the_corners_or_a_flat_field():
    centred, _ = glossy_torus_views(specular=0.0, size=32, views=6, distance=4.0)
    assert covered_radius(centred) < 0.5
    vignetting = by_candidate(identifiability_evidence(centred))["vignetting"]
    assert not vignetting.passed and "corner falloff is an extrapolation" in vignetting.reason
    assert "flat-field frames" in vignetting.reason
    filling, _ = glossy_torus_views(specular=0.0, size=32, views=6, distance=1.1, fov_x_deg=80)
    assert covered_radius(filling) > 0.9
    assert by_candidate(identifiability_evidence(filling))["vignetting"].passed
    flat = CaptureConditions(flat_field=True)
    assert by_candidate(identifiability_evidence(centred, flat))["vignetting"].passed


def test_a_small_centred_object_cannot_tell_distortion_from_pose():
    small, _ = glossy_torus_views(specular=0.0, size=32, views=6, distance=6.0)
    distortion = by_candidate(identifiability_evidence(small))["lens_distortion"]
    assert not distortion.passed, distortion.reason
    assert "pose_error" in distortion.reason and "per-view zoom" in distortion.reason
    assert distortion.details["distinguishable_pixels"] < 0.1
    # Filling the frame, the same distortion is more than a zoom; a stronger one shows at the
    # small object's scale too.
    large, _ = glossy_torus_views(specular=0.0, size=48, views=6, distance=1.1, fov_x_deg=80)
    shift = 8.0
    assert by_candidate(identifiability_evidence(large, corner_shift_pixels=shift))[
        "lens_distortion"
    ].passed
    assert not by_candidate(identifiability_evidence(small, corner_shift_pixels=shift))[
        "lens_distortion"
    ].passed
    strong = identifiability_evidence(small, corner_shift_pixels=400.0)
    assert by_candidate(strong)["lens_distortion"].passed


def test_edges_that_all_run_one_way_cannot_tell_motion_blur_from_defocus():
    data, _ = glossy_torus_views(specular=0.0, size=32, views=4)
    options = IdentifiabilityConfig()
    assert motion_blur_evidence(data, options).passed
    rows = torch.arange(32, dtype=torch.float32)
    stripes = (0.5 + 0.4 * torch.sin(rows / 2))[None, :, None, None].expand(4, 32, 32, 3)
    striped = replace(data, rendered=stripes.contiguous())
    blur = motion_blur_evidence(striped, options)
    assert not blur.passed and "defocus_blur" in blur.reason
    for item in identifiability_evidence(data):
        json.dumps(item.to_json())


def test_a_recovered_distortion_is_judged_by_its_flow_over_the_object():
    from recon.diagnose.identifiability import (
        lens_distortion_evidence,
        radial_flow_remainder,
        similarity_share,
    )

    data, _ = glossy_torus_views(specular=0.0, size=48, views=6, distance=1.6, fov_x_deg=60)
    options = IdentifiabilityConfig()
    focal = float(data.cameras.intrinsics[0, 0, 0])
    corner = 0.5 * math.hypot(48, 48) / focal  # normalised corner radius
    # A pure k1 distortion: the pixel flow is the reference shape scaled by its corner shift.
    k1 = 0.3
    shift = focal * corner**3 * k1
    _, distinguishable, _ = similarity_share(data)
    _, pixels, _ = radial_flow_remainder(data, k1, 0.0)
    assert pixels == pytest.approx(distinguishable * shift, rel=1e-6)
    # k1 and k2 of opposite signs that cancel at the corners (what a probe fitted on the
    # object's radii often recovers): judged by its corner shift it is nothing, by its flow
    # over the object it is what it is.
    k2 = -k1 / corner**2
    cancelled = focal * corner**3 * (k1 + k2 * corner**2)
    assert abs(cancelled) < 1e-9
    by_corner = lens_distortion_evidence(data, options, corner_shift_pixels=cancelled)
    by_flow = lens_distortion_evidence(data, options, cancelled, radial=(k1, k2))
    assert by_corner.details["distinguishable_pixels"] < 1e-6
    assert by_flow.details["distinguishable_pixels"] > 0.05
    assert by_flow.details["judged"] == {"k1": k1, "k2": k2}
    assert "recovered radial distortion" in by_flow.reason


def test_white_balance_identifiability_is_the_colour_noise_not_the_change_found():
    # The same data either way: only the smallest change the agreement's test can name decides,
    # against the reference change; a cast common to every view is always named unknowable.
    from recon.diagnose.identifiability import white_balance_evidence

    options = IdentifiabilityConfig()
    reference = options.white_balance_reference_spread
    clear = white_balance_evidence(0.5 * reference, 0.01, 8, options)
    hidden = white_balance_evidence(2.0 * reference, 0.08, 8, options)
    assert clear.passed and not hidden.passed
    assert hidden.reason.startswith("white_balance is not identifiable from this data, because")
    assert "colour noise (8.0 %" in hidden.reason
    # A change the agreement found above what the noise hides was identified by this data: no
    # "hides a change below" beside a found white balance; one found below it is still hidden.
    found = white_balance_evidence(2.0 * reference, 0.08, 8, options, found=2.5 * reference)
    assert found.passed and "the one found (12.5 %" in found.reason
    assert "would hide in it" in found.reason
    weak = white_balance_evidence(2.0 * reference, 0.08, 8, options, found=1.5 * reference)
    assert not weak.passed and weak.reason == hidden.reason
    for item in (clear, hidden, found):
        assert "common to every view is absorbed by the albedo" in item.reason
        assert item.threshold == reference


def test_a_small_defocus_hidden_by_the_fits_misfit_is_not_identifiable():
    """The case built to fool it: the same 1 px defocus, once over a close fit (identifiable)
    and once over a fit whose misfit (a mottled albedo error the model cannot represent) is far
    larger than anything the blur changes: there the probe's allowance cannot be cleared by a
    blur that size, and the check must say so instead of a silent miss, with the capture that
    would settle it; judged again with a lower allowance (another calibration) it passes."""
    from diagnose_scenes import camera_effect_torus_views

    from recon.config.run_config import DecisionConfig
    from recon.diagnose.decision import rethreshold
    from recon.diagnose.identifiability import blur_share, defocus_blur_evidence

    options = IdentifiabilityConfig()
    close = camera_effect_torus_views("defocus_blur", {"radius_px": 1.0}, size=32, views=4)
    allowance = 0.157
    sharp = defocus_blur_evidence(close, options, allowance)
    assert sharp.passed, sharp.reason
    assert sharp.details["outline_share"] <= sharp.details["estimated_share"] <= 1
    generator = torch.Generator().manual_seed(1)
    mottle = 1 + 0.5 * torch.randn(close.observed.shape, generator=generator)
    hidden = replace(close, observed=close.observed * mottle.clamp_min(0))
    blurred = defocus_blur_evidence(hidden, options, allowance)
    assert not blurred.passed and blurred.statistic < allowance, blurred.reason
    assert "the fit's own misfit hides a blur this size" in blurred.reason
    assert "views in focus" in blurred.details["capture"]
    # The misfit another candidate explains (its probe's reduction) is not the fit's own: with
    # nearly all of it explained, the same blur would show.
    assert defocus_blur_evidence(hidden, options, allowance, explained=0.999).passed
    json.dumps(blurred.to_json())
    # A radius inside the centre pixel is the identity: nothing to identify.
    assert blur_share(close, 0.4)[0] == 0.0
    # Judged again with another calibration's allowance (the decision's rule).
    lenient = DecisionConfig(probe_allowance={"defocus_blur": 0.02}, minimum_share=0.0)
    expected = blurred.details["expected_share"]
    assert rethreshold(blurred, lenient).passed == (expected > 0.02)
    strict = DecisionConfig(probe_allowance={"defocus_blur": 1.0})
    assert not rethreshold(sharp, strict).passed


def test_radius_spread_is_the_spread_of_the_pixel_tables_radii():
    """radius_spread reads pixel_table's surface labels and radii without building the table:
    the same median spread as from the table."""
    from recon.diagnose.identifiability import radius_spread
    from recon.diagnose.pixel_table import pixel_table

    data, _ = glossy_torus_views(views=4, size=32, specular=0.0, exposure_sigma=0.0)
    options = IdentifiabilityConfig()
    table = pixel_table(data, surface_cells=options.surface_cells)
    cells, radius = table.labels["surface"], table.values["radius"].double()
    spreads = []
    for cell in torch.unique(cells):
        chosen = cells == cell
        if int(chosen.sum()) < 4:
            continue
        means = [
            float(radius[chosen & (table.view == view)].mean())
            for view in torch.unique(table.view[chosen])
        ]
        if len(means) > 1:
            spreads.append(max(means) - min(means))
    expected = float(torch.tensor(spreads).median())
    assert expected > 0
    assert radius_spread(data, options) == expected
