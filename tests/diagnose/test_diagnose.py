"""diagnose_run's parts: the radius the object's pixels reach."""

from __future__ import annotations

import torch

from recon.camera import orbit_cameras


def test_covered_radius_is_the_farthest_object_pixel():
    """covered_radius: the largest normalised radius among covered pixels; a full frame reaches
    the corners (radius about 1), a centred square of half the side about half of that."""
    from types import SimpleNamespace

    from recon.diagnose.diagnose import covered_radius

    size = 32
    cameras = orbit_cameras(1, (size, size))
    alpha = torch.zeros(1, size, size, 1)
    alpha[:, 8:24, 8:24] = 1.0
    data = SimpleNamespace(
        observed=torch.zeros(1, size, size, 3), observed_alpha=alpha, cameras=cameras
    )
    half = covered_radius(data)
    assert abs(half - (7.5 / 16)) < 0.02, half  # the square's corner pixel centre
    data.observed_alpha = torch.ones(1, size, size, 1)
    assert covered_radius(data) > 0.95
    data.observed_alpha = torch.zeros(1, size, size, 1)
    assert covered_radius(data) == 0.0


def test_a_corner_falloff_beyond_the_object_is_reported_as_an_extrapolation():
    """The real capture's object reaches radius 0.60 only: the polynomial's corner value (-5.1
    for a true 0.60 there) is no measurement. It moves aside; the falloff where the object is
    stays, with its value at the covered radius."""
    from recon.diagnose.diagnose import mark_radial_coverage

    a, b = -0.3, 0.2  # falloff 1 + r^2 (a + b (r^2 - 0.75))
    short = {"parameters": {"vignetting": {"corner_falloff": 0.9, "a": a, "b": b}}}
    mark_radial_coverage([], [short], 0.6, None, corner_radius=0.9)
    parameters = short["parameters"]["vignetting"]
    assert "corner_falloff" not in parameters
    assert parameters["extrapolated_corner_falloff"] == 0.9
    assert abs(parameters["covered_falloff"] - (1 + 0.36 * (a + b * (0.36 - 0.75)))) < 1e-6
    # An object reaching the corners keeps its corner falloff as measured.
    wide = {"parameters": {"vignetting": {"corner_falloff": 0.9, "a": a, "b": b}}}
    mark_radial_coverage([], [wide], 0.95, None, corner_radius=0.9)
    assert wide["parameters"]["vignetting"]["corner_falloff"] == 0.9
    assert "covered_falloff" not in wide["parameters"]["vignetting"]
