"""benchmarks.nerf_synthetic: its scene configs are valid run configs in the NeRF-synthetic
style (Mitsuba, 200 px, white background, hemisphere, held-out test views), and the published
figure it compares with is stated with its setting."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.nerf_synthetic import PUBLISHED
from recon.config.loader import load_config
from recon.config.run_config import RunConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("scene", ["spot", "bob"])
def test_scene_configs_are_nerf_synthetic_style(scene: str) -> None:
    config = load_config(
        REPO_ROOT / "configs" / "bench" / f"nerf_synthetic_{scene}.yaml", RunConfig
    )
    capture = config.capture
    assert capture.backend == "mitsuba"
    assert capture.cameras.resolution == [200, 200] and capture.cameras.rig == "hemisphere"
    assert capture.background == [1.0, 1.0, 1.0]
    assert capture.test_views >= 8 and capture.train_views >= 48
    assert {effect.name for effect in capture.effects} == {"specular", "shadows"}
    assert "evaluate" in config.stages


def test_published_figure_names_its_setting() -> None:
    assert PUBLISHED["psnr"] == pytest.approx(29.0)
    assert "800" in PUBLISHED["setting"] and "GPU" in PUBLISHED["setting"]
