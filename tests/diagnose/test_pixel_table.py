"""The pixel table's gain models: built once per table and factors, the same numbers as new."""

from __future__ import annotations

import torch
from diagnose_scenes import glossy_torus_views

from recon.diagnose.pixel_table import GainModels, pixel_table


def test_gain_models_of_one_table_are_built_once_with_the_same_fits():
    data, _ = glossy_torus_views(views=4, size=32, specular=0.5, exposure_sigma=0.2)
    table = pixel_table(data)
    terms = [("view",), ("n_dot_h", "channel")]
    first = GainModels(table, ["n_dot_h", "view"])
    again = GainModels(table, ["n_dot_h", "view"])
    assert again.log_gain is first.log_gain  # kept, not rebuilt
    assert GainModels(table, ["n_dot_h", "view"], all_pixels=True).log_gain is not first.log_gain
    fresh = GainModels(pixel_table(data), ["n_dot_h", "view"])  # another table: built anew
    assert fresh.log_gain is not first.log_gain
    assert torch.equal(fresh.log_gain, first.log_gain)
    assert first.residual_sum(terms) == again.residual_sum(terms) == fresh.residual_sum(terms)
    assert torch.equal(again.heldout_errors(terms), fresh.heldout_errors(terms))
    residual, rank = fresh.residual_sum(terms)
    assert residual > 0 and rank > 1
