"""scripts/blur_reduction.py: the blur of the render that a capture's own blur asks for."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest
from diagnose_scenes import glossy_torus_views

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "blur_reduction.py"


@pytest.fixture(scope="module")
def script():
    return runpy.run_path(str(SCRIPT))


def test_a_blurred_capture_asks_for_its_blur_and_a_sharp_one_for_none(script):
    blurred = lambda observed, output: script["gaussian_blurred"](observed, 1.1)  # noqa: E731
    data, _ = glossy_torus_views(views=4, size=32, specular=0.0, transform=blurred)
    sigma, reduction = script["blur_reduction"](data)
    assert 0.9 <= sigma <= 1.3 and reduction > 0.6, (sigma, reduction)
    sharp, _ = glossy_torus_views(views=4, size=32, specular=0.0)
    sigma, reduction = script["blur_reduction"](sharp)
    assert sigma == 0.0 and reduction == pytest.approx(0.0, abs=1e-9)
