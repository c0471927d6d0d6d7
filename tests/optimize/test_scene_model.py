"""The fit's effect modules (FitEffects) leave the fit as a JSON record (to_json, RUN/effects.json)
and come back as modules (modules_from_json) with the same values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from recon.io.run_folder import RunPaths
from recon.optimize.scene_model import FitEffects
from recon.stages.fitted_scene import load_fitted_effects


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
