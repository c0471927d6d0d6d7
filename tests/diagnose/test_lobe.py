"""The lobe evidence (recon.diagnose.lobe): a highlight moving over the surface from view to
view is named under the fitted light and nowhere else.

Built to fool it: a glossy torus under one light with a per-view exposure on top (the residual
changes from view to view twice over; only the highlight follows the light's half-vector), a
Lambertian torus whose views are misaligned (a view-to-view residual from no highlight) and
Lambertian fits with an albedo error and noise only (placebo data: the p-value must be no
smaller than chance).
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from diagnose_scenes import glossy_torus_views

from recon.config.run_config import DiagnoseConfig, LobeConfig
from recon.diagnose.decision import decide
from recon.diagnose.lobe import (
    RELIGHT_KIND,
    lobe_evidence,
    lobe_statistic,
    project_out,
    spread_weights,
)
from recon.diagnose.records import Candidate

SETTINGS = DiagnoseConfig(lobe=LobeConfig(placebo_lights=120))


def test_projection_removes_cell_offsets_and_view_gains_and_keeps_what_is_orthogonal():
    generator = torch.Generator().manual_seed(0)
    count, cells, views = 600, 20, 6
    cell = torch.randint(0, cells, (count,), generator=generator)
    view = torch.randint(0, views, (count,), generator=generator)
    rendered = 0.2 + torch.rand(count, generator=generator, dtype=torch.float64)
    nuisance = (
        torch.randn(cells, dtype=torch.float64)[cell]
        + torch.randn(views, dtype=torch.float64)[view] * rendered
    )
    projected = project_out(nuisance[:, None], cell, view, rendered)
    assert float(projected.norm() / nuisance.norm()) < 1e-6
    # Idempotent: a projected vector stays as it is.
    signal = torch.randn(count, 1, generator=generator, dtype=torch.float64)
    once = project_out(signal, cell, view, rendered)
    twice = project_out(once, cell, view, rendered)
    assert torch.allclose(once, twice, atol=1e-6)


def test_a_glossy_object_under_a_constant_camera_gives_a_specular_lobe():
    data, _ = glossy_torus_views(views=12, size=40, specular=0.3, shininess=30.0)
    measured = lobe_statistic([data], SETTINGS)
    assert measured["p_value"] < 0.01 and measured["correlation"] > 0.3, measured
    assert measured["exponent"] in (16.0, 32.0, 64.0), measured
    candidate = Candidate("specular")
    candidate.add(lobe_evidence([data], "specular", SETTINGS))
    decide(candidate, SETTINGS.decision)
    assert candidate.significant and candidate.decided_by == "lobe", candidate.why
    assert "placebo lights" in candidate.why


def test_a_glossy_object_with_a_per_view_exposure_still_gives_the_lobe():
    data, _ = glossy_torus_views(
        views=12, size=40, specular=0.3, shininess=30.0, exposure_sigma=0.1
    )
    measured = lobe_statistic([data], SETTINGS)
    assert measured["p_value"] < 0.01 and measured["correlation"] > 0.3, measured


def test_a_lambertian_fit_gives_no_lobe():
    data, _ = glossy_torus_views(views=12, size=40, specular=0.0, exposure_sigma=0.1)
    evidence = lobe_evidence([data], "specular", SETTINGS)
    assert not evidence.passed, evidence.reason
    assert evidence.statistic < SETTINGS.decision.lobe_allowance["specular"], evidence.statistic


def test_misaligned_lambertian_views_give_no_lobe():
    # A pose error: every view's render comes from a camera turned by a fraction of a degree, so
    # shading edges and the silhouette move from view to view without any highlight.
    data, _ = glossy_torus_views(views=12, size=40, specular=0.0)
    generator = torch.Generator().manual_seed(3)
    shifted = torch.roll(data.observed, shifts=1, dims=2)
    jitter = torch.randint(0, 2, (data.view_count, 1, 1, 1), generator=generator).float()
    data = replace(data, observed=jitter * shifted + (1 - jitter) * data.observed)
    evidence = lobe_evidence([data], "specular", SETTINGS)
    assert not evidence.passed, evidence.reason


def test_placebo_data_rarely_reaches_the_level():
    # Lambertian fits with noise only: the p-value against placebo lights is about uniform, so
    # it falls below the level in few of them (8 seeds: at 1 %, none expected).
    settings = DiagnoseConfig(lobe=LobeConfig(placebo_lights=60, exponents=[16.0, 64.0]))
    p_values = []
    for seed in range(8):
        data, _ = glossy_torus_views(views=8, size=32, specular=0.0, seed=seed, exposure_sigma=0.05)
        p_values.append(lobe_statistic([data], settings)["p_value"])
    assert sum(value < 0.05 for value in p_values) <= 2, p_values
    assert max(p_values) > 0.2, p_values


def test_the_producer_is_registered_and_measures_training_and_heldout_views_together():
    from recon.diagnose.data import FittedModel
    from recon.diagnose.lobe import lobe_producer
    from recon.diagnose.producers import PRODUCERS, EvidenceInputs
    from recon.io.datasets import CaptureSet

    assert lobe_producer in PRODUCERS
    heldout, _ = glossy_torus_views(views=6, size=40, specular=0.3, shininess=30.0, seed=1)
    training, _ = glossy_torus_views(views=9, size=40, specular=0.3, shininess=30.0, seed=2)
    captures = CaptureSet(
        training.cameras, training.observed, training.observed_alpha, training.names, "train"
    )
    model = FittedModel(training.mesh, training.lighting)
    inputs = EvidenceInputs(heldout, None, None, captures, model)
    candidates = [Candidate("specular"), Candidate("exposure")]
    evidence = lobe_producer(inputs, candidates, SETTINGS)
    assert [item.candidate for item in evidence] == ["specular"]
    assert evidence[0].details["views"] == 15 and evidence[0].passed, evidence[0].reason
    disabled = replace(SETTINGS, lobe=replace(SETTINGS.lobe, enabled=False))
    assert lobe_producer(inputs, candidates, disabled) == []


def _blurred(observed: torch.Tensor, output) -> torch.Tensor:
    """A small defocus-like blur of the observed views: a 3x3 binomial kernel (variance 0.5 px^2
    per axis)."""
    image = observed.permute(0, 3, 1, 2)
    kernel = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]]) / 16
    kernel = kernel[None, None].repeat(image.shape[1], 1, 1, 1)
    padded = torch.nn.functional.pad(image, (1, 1, 1, 1), mode="replicate")
    return torch.nn.functional.conv2d(padded, kernel, groups=image.shape[1]).permute(0, 2, 3, 1)


def test_the_blur_nuisance_is_the_render_laplacian_of_each_view_on_its_own_pixels():
    from recon.diagnose.lobe import blur_columns, image_laplacian

    rows, columns = torch.meshgrid(
        torch.arange(6, dtype=torch.float64), torch.arange(7, dtype=torch.float64), indexing="ij"
    )
    # x^2 + 2 y^2: Laplacian 2 + 4 = 6 inside (the replicated border bends it).
    laplacian = image_laplacian((columns**2 + 2 * rows**2)[None].expand(2, 6, 7))
    assert torch.allclose(laplacian[:, 1:-1, 1:-1], torch.full((2, 4, 5), 6.0, dtype=torch.float64))
    # A gaussian blur of variance s^2 adds s^2 / 2 x the Laplacian to a smooth image.
    view = torch.tensor([0, 0, 1, 1, 1, 0, 1])
    values = torch.arange(1.0, 8.0, dtype=torch.float64)
    per_view = blur_columns(view, values)
    assert per_view.shape == (7, 2)
    assert torch.equal(per_view.sum(1), values)
    assert float(per_view[view == 1, 0].abs().max()) == 0.0


def test_a_blurred_lambertian_object_gives_no_lobe_a_glossy_one_still_does():
    # Built to fool it: a blur changes the shading where it curves, under the fitted light only
    # (placebo lights do not reproduce it), so without its first-order change projected out the
    # light-specific view-to-view residual reads as a lobe.
    settings = DiagnoseConfig(lobe=LobeConfig(placebo_lights=120))
    blurred, _ = glossy_torus_views(views=12, size=64, specular=0.0, transform=_blurred)
    evidence = lobe_evidence([blurred], "specular", settings)
    assert not evidence.passed, evidence.reason
    unguarded = replace(settings, lobe=replace(settings.lobe, blur_nuisance=False))
    assert lobe_evidence([blurred], "specular", unguarded).passed
    glossy, _ = glossy_torus_views(
        views=12, size=64, specular=0.3, shininess=30.0, transform=_blurred
    )
    measured = lobe_statistic([glossy], settings)
    assert measured["p_value"] < 0.01 and measured["correlation"] > 0.5, measured


RELIGHT_SETTINGS = replace(SETTINGS, lobe=replace(SETTINGS.lobe, relight=True))


def _relight_inputs(relight_specular: float, exposure_sigma: float = 0.0):
    """EvidenceInputs whose training and held-out views are a Lambertian torus (nothing for
    the lobe under the fitted light) and whose relight split, under another known light, is
    the torus with a highlight of relight_specular (and a per-view exposure)."""
    from recon.diagnose.data import FittedModel
    from recon.diagnose.producers import EvidenceInputs
    from recon.io.datasets import CaptureSet

    heldout, _ = glossy_torus_views(views=6, size=40, specular=0.0, seed=1)
    training, _ = glossy_torus_views(views=9, size=40, specular=0.0, seed=2)
    relight, _ = glossy_torus_views(
        views=8,
        size=40,
        specular=relight_specular,
        shininess=30.0,
        light_direction=(0.8, 0.5, -0.3),
        exposure_sigma=exposure_sigma,
        seed=3,
    )
    captures = CaptureSet(
        training.cameras, training.observed, training.observed_alpha, training.names, "train"
    )
    model = FittedModel(training.mesh, training.lighting)
    return EvidenceInputs(heldout, None, None, captures, model, relight=relight)


def test_a_highlight_under_the_relight_splits_known_light_is_named_from_it():
    from recon.diagnose.lobe import lobe_producer

    inputs = _relight_inputs(relight_specular=0.3)
    evidence = lobe_producer(inputs, [Candidate("specular")], RELIGHT_SETTINGS)
    evidence = {item.kind: item for item in evidence}
    assert not evidence["lobe"].passed, evidence["lobe"].reason
    assert evidence["relight_lobe"].passed, evidence["relight_lobe"].reason
    assert "relight split's known light" in evidence["relight_lobe"].reason
    candidate = Candidate("specular")
    for item in evidence.values():
        candidate.add(item)
    decide(candidate, SETTINGS.decision)
    assert candidate.significant and candidate.decided_by == "relight_lobe", candidate.why
    # On by default (docs/decisions/0216-relight-specular.md); off, the lobe alone.
    assert [item.kind for item in lobe_producer(inputs, [Candidate("specular")], SETTINGS)] == [
        "lobe",
        "relight_lobe",
    ]
    unlit = replace(SETTINGS, lobe=replace(SETTINGS.lobe, relight=False))
    assert [item.kind for item in lobe_producer(inputs, [Candidate("specular")], unlit)] == ["lobe"]


def test_a_relight_split_with_a_per_view_exposure_and_no_highlight_gives_no_lobe():
    from recon.diagnose.lobe import lobe_producer

    inputs = _relight_inputs(relight_specular=0.0, exposure_sigma=0.1)
    candidate = Candidate("specular")
    for item in lobe_producer(inputs, [candidate], RELIGHT_SETTINGS):
        candidate.add(item)
    decide(candidate, SETTINGS.decision)
    assert candidate.evidence_of("relight_lobe") is not None
    assert not candidate.significant, candidate.why


def test_weighted_projection_removes_the_nuisances_of_the_scaled_rows():
    generator = torch.Generator().manual_seed(1)
    count, cells, views = 600, 20, 6
    cell = torch.randint(0, cells, (count,), generator=generator)
    view = torch.randint(0, views, (count,), generator=generator)
    rendered = 0.2 + torch.rand(count, generator=generator, dtype=torch.float64)
    weights = 0.2 + 3 * torch.rand(count, generator=generator, dtype=torch.float64)
    nuisance = (
        torch.randn(cells, dtype=torch.float64)[cell]
        + torch.randn(views, dtype=torch.float64)[view] * rendered
    )
    projected = project_out(nuisance[:, None], cell, view, rendered, weights=weights)
    assert float(projected.norm() / nuisance.norm()) < 1e-6
    # Equal weights are the unweighted projection, scaled.
    signal = torch.randn(count, 1, generator=generator, dtype=torch.float64)
    plain = project_out(signal, cell, view, rendered)
    scaled = project_out(signal, cell, view, rendered, weights=torch.full((count,), 2.0))
    assert torch.allclose(scaled, 2 * plain, atol=1e-9)


def test_spread_weights_follow_the_residuals_spread_along_the_sun_and_ignore_a_sparse_highlight():
    generator = torch.Generator().manual_seed(2)
    cosine = torch.linspace(-1, 1, 4000, dtype=torch.float64)
    spread = torch.where(cosine > 0, 4.0, 1.0).double()
    residual = spread * torch.randn(4000, generator=generator, dtype=torch.float64)
    highlight = residual.clone()
    highlight[cosine > 0.9] += 50.0  # a highlight on a fifth of the brightest bin's pixels
    for values in (residual, highlight):
        weights = spread_weights(values, cosine, 4)
        assert abs(float(weights[cosine < -0.1].mean()) - 1.0) < 0.1
        assert abs(float(weights[(cosine > 0.1) & (cosine < 0.5)].mean()) - 0.25) < 0.025
    # The highlight's bin keeps most of its weight (the median ignores a sparse highlight).
    top = cosine > 0.5
    assert float(spread_weights(highlight, cosine, 4)[top].mean()) > 0.18
    assert torch.equal(spread_weights(residual, cosine, 1), torch.ones(4000, dtype=torch.float64))


L_RELIGHT = (0.8, 0.5, -0.3)


def _relight_views(transform, seed: int = 0, specular: float = 0.0, exposure_sigma: float = 0.0):
    """A Lambertian torus's 8 relight views under the sun toward L_RELIGHT (+ a highlight of
    specular, a per-view exposure exp(exposure_sigma N(0, 1))), the observed views changed by
    transform(observed, output)."""
    data, _ = glossy_torus_views(
        views=8,
        size=40,
        specular=specular,
        shininess=30.0,
        light_direction=L_RELIGHT,
        seed=seed,
        exposure_sigma=exposure_sigma,
        transform=transform,
    )
    return data


def _sunlit_noise(seed: int, sigma: float = 0.1):
    """A residual that grows with the sun's light and follows no highlight: blotchy noise
    (3 x 3 box-smoothed) times max(0, n.l) of the relight sun, as a fit's texture, normal and
    pose errors leave where the sun shades them (the Mitsuba spot's relight split)."""
    direction = torch.tensor(L_RELIGHT) / torch.tensor(L_RELIGHT).norm()

    def transform(observed, output):
        generator = torch.Generator().manual_seed(100 + seed)
        noise = torch.randn(observed.shape[:3] + (1,), generator=generator).permute(0, 3, 1, 2)
        noise = torch.nn.functional.conv2d(noise, torch.ones(1, 1, 3, 3) / 3, padding=1)
        lit = (output.normals * direction).sum(-1, keepdim=True).clamp_min(0)
        return observed + sigma * noise.permute(0, 2, 3, 1) * lit * output.alpha

    return transform


def test_a_relight_residual_that_grows_with_the_sun_is_not_named_a_highlight():
    # Built to fool the relight lobe: unweighted, the sun's lobe lies where the residual is
    # large and clears the floor against placebo lights whose lobes lie in the dim part; the
    # weighted statistic does not (docs/decisions/0216-relight-specular.md).
    unweighted = replace(SETTINGS, lobe=replace(SETTINGS.lobe, relight_spread_bins=1))
    for seed in (5, 6):
        data = _relight_views(_sunlit_noise(seed), seed=seed)
        fooled = lobe_evidence([data], "specular", unweighted, RELIGHT_KIND)
        assert fooled.passed, fooled.reason
        evidence = lobe_evidence([data], "specular", SETTINGS, RELIGHT_KIND)
        assert not evidence.passed, evidence.reason
        assert evidence.details["spread_bins"] == SETTINGS.lobe.relight_spread_bins
        assert "weighted by the residual's spread" in evidence.reason


def test_a_relight_split_under_a_misplaced_sun_gives_no_lobe():
    # A fit with a wrong terminator: the views are lit by a sun 25 degrees from the known one,
    # the residual follows the two suns' cosines, not a half-vector.
    import math

    known = torch.tensor(L_RELIGHT) / torch.tensor(L_RELIGHT).norm()
    axis = torch.tensor([0.0, 1.0, 0.0]) - known[1] * known
    axis = axis / axis.norm()
    actual = math.cos(math.radians(25)) * known + math.sin(math.radians(25)) * axis

    def transform(observed, output):
        ambient, sun = 0.3 * math.pi, 2.0  # the scene's irradiances (glossy_torus_views)
        known_cosine = (output.normals * known).sum(-1, keepdim=True).clamp_min(0)
        actual_cosine = (output.normals * actual).sum(-1, keepdim=True).clamp_min(0)
        return observed * (ambient + sun * actual_cosine) / (ambient + sun * known_cosine)

    evidence = lobe_evidence([_relight_views(transform)], "specular", SETTINGS, RELIGHT_KIND)
    assert not evidence.passed, evidence.reason


def test_a_highlight_on_top_of_a_sunlit_residual_is_still_named():
    data = _relight_views(_sunlit_noise(5), seed=5, specular=0.3)
    evidence = lobe_evidence([data], "specular", SETTINGS, RELIGHT_KIND)
    assert evidence.passed, evidence.reason


def test_dividing_each_views_gain_leaves_a_surface_misfit_the_same_in_every_view():
    # An exposure g_v over an albedo that averaged differently exposed views (off by e(point)):
    # the residual g_v e render - render is a product of view and point, which no additive
    # per-view gain or per-cell offset takes out. Divided by each view's gain first, the same
    # point has the same residual in every view, up to the one common factor.
    from recon.diagnose.lobe import divide_view_gains

    generator = torch.Generator().manual_seed(4)
    points, views = 50, 5
    render = 0.2 + torch.rand(points, generator=generator, dtype=torch.float64)
    misfit = 1 + 0.3 * torch.randn(points, generator=generator, dtype=torch.float64)
    gains = torch.tensor([0.5, 0.8, 1.0, 1.6, 2.2], dtype=torch.float64)
    view = torch.arange(views).repeat_interleave(points)
    rendered = render.repeat(views)
    residual = gains[view] * misfit.repeat(views) * rendered - rendered
    before = residual.view(views, points)
    assert float((before - before.mean(0)).abs().max()) > 0.3
    divided = divide_view_gains(residual, rendered, view).view(views, points)
    assert torch.allclose(divided, divided[0].expand_as(divided), atol=1e-12)
    # Without an exposure every view's gain is the same and only that common factor moves.
    flat = divide_view_gains(misfit.repeat(views) * rendered - rendered, rendered, view)
    assert torch.allclose(flat.view(views, points), flat.view(views, points)[0].expand(views, -1))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_relight_split_with_an_exposure_over_a_misfit_albedo_names_only_a_highlight(seed):
    # The relight views under a strong exposure (gains 0.5-2) over an albedo misfit that
    # varies over the surface: a highlight under the known sun is still named, and without
    # one nothing is.
    def misfit(observed, output):
        normals = output.normals
        error = 1 + 0.3 * torch.sin(3 * normals[..., 0:1] + 1) * torch.cos(2 * normals[..., 2:3])
        return observed * error

    for specular, named in ((0.0, False), (0.3, True)):
        data = _relight_views(misfit, seed=seed, specular=specular, exposure_sigma=0.5)
        evidence = lobe_evidence([data], "specular", SETTINGS, RELIGHT_KIND)
        assert evidence.passed is named, evidence.reason
