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


def test_view_directions_are_kept_for_the_same_views_and_recomputed_for_changed_ones():
    from dataclasses import replace

    from recon.diagnose.pixel_table import _view_directions, view_directions

    data, _ = glossy_torus_views(views=3, size=32, specular=0.0, exposure_sigma=0.0)
    world, to_camera = view_directions(data)
    again = view_directions(replace(data))  # another record of the same tensors: kept
    assert again[0] is world and again[1] is to_camera
    fresh = _view_directions(data)
    assert torch.equal(fresh[0], world) and torch.equal(fresh[1], to_camera)
    moved = replace(data, depth=data.depth * 1.1)  # other tensors: computed for them
    assert not torch.equal(view_directions(moved)[0], world)
    data.depth.mul_(1.0)  # changed in place (a new version): computed again
    assert view_directions(data)[0] is not world
    assert torch.equal(view_directions(data)[0], world)


def test_the_tables_pieces_are_its_columns():
    from recon.diagnose.pixel_table import (
        pixel_radius,
        surface_labels,
        table_pixels,
        view_directions,
    )

    data, _ = glossy_torus_views(views=3, size=32, specular=0.3, exposure_sigma=0.1)
    table = pixel_table(data, surface_cells=4)
    keep = table_pixels(data)
    assert int(keep.sum()) == table.view.numel() > 100
    assert torch.equal(pixel_radius(data)[keep], table.values["radius"])
    assert torch.equal(surface_labels(view_directions(data)[0][keep], 4), table.labels["surface"])
