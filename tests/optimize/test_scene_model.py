"""recon.optimize.scene_model.texture_total_variation on degenerate sizes (a uniform material
is a 1 x 1 texture, fit.pbr.material_texture_size: 1)."""

from __future__ import annotations

import torch

from recon.optimize.scene_model import texture_total_variation


def test_total_variation_of_thin_textures_is_finite():
    assert float(texture_total_variation(torch.rand(1, 1, 2))) == 0.0
    row = torch.tensor([[[0.0], [1.0], [3.0]]])  # [1, 3, 1]
    assert float(texture_total_variation(row)) == 1.5
    column = row.transpose(0, 1)  # [3, 1, 1]
    assert float(texture_total_variation(column)) == 1.5
    square = torch.tensor([[[0.0], [1.0]], [[2.0], [3.0]]])
    assert float(texture_total_variation(square)) == 3.0
