"""recon.optimize.scene_model: texture_total_variation on degenerate sizes (a uniform material
is a 1 x 1 texture, fit.pbr.material_texture_size: 1), and the fit's effect modules (FitEffects)
leaving the fit as a JSON record (to_json, RUN/effects.json) and coming back as modules
(modules_from_json) with the same values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from recon.io.run_folder import RunPaths
from recon.optimize.scene_model import FitEffects, texture_total_variation
from recon.stages.fitted_scene import load_fitted_effects


def test_total_variation_of_thin_textures_is_finite():
    assert float(texture_total_variation(torch.rand(1, 1, 2))) == 0.0
    row = torch.tensor([[[0.0], [1.0], [3.0]]])  # [1, 3, 1]
    assert float(texture_total_variation(row)) == 1.5
    column = row.transpose(0, 1)  # [3, 1, 1]
    assert float(texture_total_variation(column)) == 1.5
    square = torch.tensor([[[0.0], [1.0]], [[2.0], [3.0]]])
    assert float(texture_total_variation(square)) == 3.0


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
