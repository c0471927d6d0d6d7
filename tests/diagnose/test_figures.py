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
