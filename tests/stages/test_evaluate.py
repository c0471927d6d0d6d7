"""The evaluate stage's own checks (a whole run is tests/pipeline's)."""

from __future__ import annotations

import pytest
import torch

from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.run_folder import prepare_run_folder
from recon.stages.evaluate import evaluate_stage


def test_evaluate_without_a_fit_names_the_missing_mesh(tmp_path):
    paths = prepare_run_folder(tmp_path / "run")
    with pytest.raises(ReconError, match=r"evaluate: no fitted mesh at .*model.obj"):
        evaluate_stage(RunConfig(), paths, torch.device("cpu"))


def test_a_pbr_fit_is_scored_against_the_true_material_over_the_surface(tmp_path):
    """Through the files (8-bit maps, OBJ round trip): a fit whose roughness is the truth plus
    0.1 everywhere scores about 0.1, with metalness about right."""
    import json

    from tests.material_scenes import material_run

    paths = material_run(tmp_path / "run", "pbr", roughness_offset=0.1)
    config = RunConfig()
    config.evaluate.material_samples = 3000
    evaluate_stage(config, paths, torch.device("cpu"))
    material = json.loads(paths.metrics.read_text())["material"]
    assert material["roughness_mae"] == pytest.approx(0.1, abs=0.01)
    assert material["roughness_bias"] == pytest.approx(0.1, abs=0.01)
    assert material["roughness_within_tolerance"] < 0.05
    assert material["metalness_mae"] < 0.01 and material["metalness_within_tolerance"] == 1.0
    # Two training views see part of the sphere; only that part is compared.
    assert material["seen_from"] == "train" and 0.3 < material["seen_fraction"] < 0.95
    assert material["compared_fraction"] == pytest.approx(material["seen_fraction"])


def test_a_lambert_fit_has_no_material_section(tmp_path):
    import json

    from tests.material_scenes import material_run

    paths = material_run(tmp_path / "run", "lambert")
    evaluate_stage(RunConfig(), paths, torch.device("cpu"))
    metrics = json.loads(paths.metrics.read_text())
    assert "image" in metrics and "geometry" in metrics and "material" not in metrics
