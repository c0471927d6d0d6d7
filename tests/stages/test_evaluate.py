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
