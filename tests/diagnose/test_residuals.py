"""The where-analysis' samples: the shared response curve and its intensity bins are built
once per set of samples and are what the plain functions give."""

from __future__ import annotations

import pytest
import torch
from diagnose_where_scene import make_scene, noisy

from recon.diagnose.residuals import (
    BinBaseline,
    BinStage,
    ResidualSamples,
    intensity_bins,
    shared_response,
)


def test_the_shared_response_is_built_once_and_equals_the_plain_one():
    scene = make_scene()
    observed = noisy(scene.output.color.detach() ** 1.3)
    samples = ResidualSamples.from_data(scene.data(observed))
    edges, levels = samples.intensity_bins()
    plain_edges, plain_levels = intensity_bins(samples.rendered)
    assert torch.equal(edges, plain_edges) and torch.equal(levels, plain_levels)
    assert samples.intensity_bins()[1] is levels
    response = samples.response()
    assert samples.response() is response
    assert torch.equal(response.rows, shared_response(samples.rendered).rows)
    # Both splits' baselines fit that one stage; fitting leaves it unchanged.
    views, pixels = samples.baseline("views"), samples.baseline("pixels")
    plain = BinBaseline(samples.residual, [shared_response(samples.rendered)], samples.view_half())
    assert torch.equal(views.left, plain.left)
    by_pixels = BinBaseline(
        samples.residual, [shared_response(samples.rendered)], samples.pixel_half()
    )
    for (_, left), (_, plain_left) in zip(pixels.left_by_half, by_pixels.left_by_half, strict=True):
        assert torch.equal(left, plain_left)
    assert samples.response() is response and float(views.left.abs().sum()) > 0


@pytest.mark.parametrize("parameters", [1, 2, 3])
def test_a_bin_model_predicts_the_plain_sum_of_its_products(parameters):
    generator = torch.Generator().manual_seed(parameters)
    features = torch.randn(500, 3, parameters, generator=generator, dtype=torch.float64)
    bins = torch.randint(7, (500,), generator=generator)
    stage = BinStage(features, bins, 7)
    coefficients = stage.fit(torch.randn(500, 3, generator=generator, dtype=torch.float64))
    plain = (stage.features * coefficients[stage.rows]).sum(-1)
    assert torch.equal(stage.predict(coefficients), plain)


def test_a_rebinned_stage_shares_its_features_and_fits_like_a_new_one():
    generator = torch.Generator().manual_seed(3)
    features = torch.randn(400, 3, 2, generator=generator, dtype=torch.float64)
    target = torch.randn(400, 3, generator=generator, dtype=torch.float64)
    first = BinStage(features, torch.randint(5, (400,), generator=generator), 5)
    bins = torch.randint(9, (400, 3), generator=generator)
    rebinned = first.rebinned(bins, 9)
    fresh = BinStage(features, bins, 9)
    assert rebinned._outer is first._outer and rebinned.count == 9 and first.count == 5
    train = torch.rand(400, generator=generator) < 0.5
    assert torch.equal(rebinned.fit(target, train), fresh.fit(target, train))
    assert torch.equal(first.fit(target), BinStage(features, first.rows // 3, 5).fit(target))
