"""Identifiability as an output: built to fool a diagnosis that only looks at residuals.

A tone curve under one fixed light, a falloff where the object stays in the middle of the
image, a distortion of a small centred object (a per-view zoom reproduces it), a blur in views
whose edges all run one way: each must come back as "not identifiable from this data,
because ..." with the capture that would settle it; the same effects with the right capture
must come back identifiable.
"""

from __future__ import annotations

import json
from dataclasses import replace

import torch
from diagnose_scenes import glossy_torus_views

from recon.diagnose.identifiability import (
    CaptureConditions,
    IdentifiabilityOptions,
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
    # Known exposures barely apart do not help; a bracket, a relight split or a light that
    # turns with the camera does.
    small = CaptureConditions(exposure_gains=torch.tensor([1.0, 1.1, 0.95]))
    assert not by_candidate(identifiability_evidence(data, small))["response_curve"].passed
    bracket = CaptureConditions(exposure_gains=torch.tensor([1.0, 2.0, 0.5]))
    assert by_candidate(identifiability_evidence(data, bracket))["response_curve"].passed
    relight = CaptureConditions(relight=True)
    assert by_candidate(identifiability_evidence(data, relight))["response_curve"].passed
    turning = replace(data, lighting=replace(data.lighting, frame="camera"))
    assert by_candidate(identifiability_evidence(turning))["response_curve"].passed


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
    options = IdentifiabilityOptions()
    assert motion_blur_evidence(data, options).passed
    rows = torch.arange(32, dtype=torch.float32)
    stripes = (0.5 + 0.4 * torch.sin(rows / 2))[None, :, None, None].expand(4, 32, 32, 3)
    striped = replace(data, rendered=stripes.contiguous())
    blur = motion_blur_evidence(striped, options)
    assert not blur.passed and "defocus_blur" in blur.reason
    for item in identifiability_evidence(data):
        json.dumps(item.to_json())
