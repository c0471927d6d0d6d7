"""The where figures are written."""

from __future__ import annotations

import pytest
from diagnose_where_scene import SIZE, make_scene, noisy, radial_vignetting

from recon.diagnose.domains import DOMAINS, where_analysis
from recon.diagnose.figures import where_figures, worst_views_figure


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def test_where_figures_are_written(scene, tmp_path):
    data = scene.data(noisy(scene.output.color * radial_vignetting(SIZE, SIZE)))
    paths = where_figures(data, where_analysis(data), tmp_path / "figures")
    assert set(paths) == set(DOMAINS) | {"worst_views"}
    for path in paths.values():
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 1000
    # Atomic writes leave no temporary files behind.
    assert sorted(tmp_path.joinpath("figures").iterdir()) == sorted(paths.values())
    single = worst_views_figure(data, tmp_path / "worst.png", count=1)
    assert single.stat().st_size > 1000


def test_the_line_target_figure_draws_the_measured_lens(tmp_path):
    """The figure of a line-target measurement (recon.diagnose.line_target) is a PNG drawn
    from the measurement's own record (what diagnosis.json stores)."""
    from PIL import Image

    from data_synth.line_target import line_target_capture
    from recon.config.run_config import (
        CameraRigConfig,
        CaptureConfig,
        EffectConfig,
        LineTargetConfig,
    )
    from recon.diagnose.figures import line_target_figure
    from recon.diagnose.line_target import measure_line_target

    capture_config = CaptureConfig(
        cameras=CameraRigConfig(rig="fibonacci", fov_deg=40.0, resolution=[48, 48]),
        line_target=LineTargetConfig(views=4),
    )
    capture, _, _ = line_target_capture(
        capture_config, [EffectConfig("lens_distortion", {"k1": -0.3})], 0
    )
    measurement = measure_line_target(capture.images.double(), capture.cameras.intrinsics)
    measurement["allowance"] = 0.3
    path = line_target_figure(measurement, tmp_path / "line_target.png")
    with Image.open(path) as image:
        assert image.size[0] > 400 and image.size[1] > 200
