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
