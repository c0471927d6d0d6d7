"""The fit's effect modules leave the fit in RUN/effects.json (FitEffects.to_json) and come back
for the evaluate stage (recon.metrics.evaluate.load_fitted_effects) with the same values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from recon.errors import ReconError
from recon.io.run_folder import RunPaths
from recon.metrics.evaluate import load_fitted_effects
from recon.optimize.scene_model import FitEffects


def test_fitted_effects_round_trip_through_the_run_folder(tmp_path: Path) -> None:
    effects = FitEffects(["specular", "exposure"], view_count=3, device=torch.device("cpu"))
    with torch.no_grad():
        effects.modules[0].strength.fill_(0.7)
        effects.modules[0].log_exponent.fill_(-0.4)
        for parameter in effects.modules[1].parameters():
            parameter.copy_(torch.linspace(-0.2, 0.3, parameter.numel()).view_as(parameter))
    paths = RunPaths(tmp_path)
    paths.fitted_effects.write_text(json.dumps(effects.to_json()))
    loaded = load_fitted_effects(paths, torch.device("cpu"))
    assert [module.name for module in loaded] == ["specular", "exposure"]
    for before, after in zip(effects.modules, loaded, strict=True):
        for key, value in before.state_dict().items():
            assert torch.allclose(after.state_dict()[key], value)
    assert json.loads(paths.fitted_effects.read_text())["effects"][0]["summary"]["strength"] == (
        pytest.approx(0.7)
    )


def test_no_effects_file_means_no_effects_and_a_broken_one_is_named(tmp_path: Path) -> None:
    paths = RunPaths(tmp_path)
    assert load_fitted_effects(paths, torch.device("cpu")) == []
    paths.fitted_effects.write_text("{not json")
    with pytest.raises(ReconError, match="effects.json"):
        load_fitted_effects(paths, torch.device("cpu"))
