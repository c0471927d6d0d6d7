"""Nulls from the run: placebo effects of the candidate's size, split-half agreement.

Built to fool them: a strongly glossy fit (a large structured residual) where a fixed allowance
would call a one-gain-per-view effect significant, beside a clean fit with a small but real
exposure; and per-view parameters that are pure noise beside real ones.
"""

from __future__ import annotations

import json

import torch
from diagnose_scenes import albedo_error_views, glossy_torus_views

from recon.config.run_config import DiagnoseConfig, NullConfig
from recon.diagnose.nulls import (
    null_evidence,
    parameter_layout,
    placebo_null,
    split_half_evidence,
)
from recon.diagnose.which import rank_candidates

OPTIONS = DiagnoseConfig(nulls=NullConfig(placebo_draws=12, permutations=300))


class Probed:
    """A candidate's probe result: significant, reduction, interval."""

    def __init__(self, data, name):
        candidate = next(item for item in rank_candidates(data, [name]) if item.name == name)
        evidence = candidate.evidence_of("probe")
        self.effect = name
        self.significant = candidate.significant
        self.heldout_reduction = evidence.details["reduction"]
        self.interval = evidence.interval


def probe(data, name):
    return Probed(data, name)


def test_placebos_have_the_candidate_s_parameters():
    assert parameter_layout("exposure", 12) == (1, 0)
    assert parameter_layout("white_balance", 12) == (2, 0)
    assert parameter_layout("pose_error", 12) == (3, 0)  # rotations only, like the probe
    assert parameter_layout("vignetting", 12) == (0, 2)


def test_the_null_grows_with_the_fit_s_mismatch():
    clean, _ = glossy_torus_views(specular=0.0, size=32)
    glossy, _ = glossy_torus_views(specular=1.5, shininess=2.0, size=32)
    clean_null, _ = placebo_null(clean, "white_balance", OPTIONS)
    glossy_null, draws = placebo_null(glossy, "white_balance", OPTIONS)
    assert len(draws) == OPTIONS.nulls.placebo_draws
    assert clean_null < 0.005
    assert glossy_null > 0.03 and glossy_null > 10 * max(clean_null, 1e-4)


def test_a_20_db_albedo_mismatch_does_not_turn_into_effects():
    # No effect at all, only a wrong texture: the fixed allowances call four effects
    # significant; against placebos of their own size on this fit, three are not.
    data = albedo_error_views(seed=1)
    names = ["exposure", "response_curve", "vignetting"]
    for candidate in (probe(data, name) for name in names):
        assert candidate.significant, candidate.effect
        evidence = null_evidence(
            data, candidate.effect, candidate.heldout_reduction, candidate.interval, OPTIONS
        )
        assert evidence.kind == "null" and not evidence.passed, evidence.reason
        assert "not significant" in evidence.reason and "dB fit" in evidence.reason
    white = probe(albedo_error_views(seed=2), "white_balance")
    assert white.significant
    evidence = null_evidence(
        albedo_error_views(seed=2),
        "white_balance",
        white.heldout_reduction,
        white.interval,
        OPTIONS,
    )
    assert not evidence.passed, evidence.reason


def test_a_small_real_exposure_on_a_clean_fit_is_significant():
    real, _ = glossy_torus_views(specular=0.0, exposure_sigma=0.05, size=32)
    exposure = probe(real, "exposure")
    evidence = null_evidence(
        real, "exposure", exposure.heldout_reduction, exposure.interval, OPTIONS
    )
    assert evidence.passed, evidence.reason
    json.dumps(evidence.to_json())


def test_split_half_agreement_tells_real_per_view_gains_from_noise():
    real, _ = glossy_torus_views(specular=0.0, exposure_sigma=0.1, size=32)
    agreement = split_half_evidence(real, "exposure", OPTIONS)
    assert agreement.passed and agreement.statistic > 0.95, agreement.reason
    # A clean diffuse fit: its white balance "parameters" are noise.
    clean, _ = glossy_torus_views(specular=0.0, size=32)
    noise = split_half_evidence(clean, "white_balance", OPTIONS)
    assert not noise.passed, noise.reason
    assert split_half_evidence(clean, "lens_distortion", OPTIONS) is None


def test_geometric_placebos_move_the_render():
    data, _ = glossy_torus_views(specular=0.0, size=32, views=6)
    threshold, draws = placebo_null(
        data, "pose_error", DiagnoseConfig(nulls=NullConfig(placebo_draws=4))
    )
    assert all(torch.isfinite(torch.tensor(draws)))
    assert threshold < 0.05


def test_smooth_fields_upsample_only_the_kept_ones_from_the_same_draws():
    from recon.diagnose.nulls import smooth_fields

    keep = torch.tensor([True, False, True, False])
    full = smooth_fields(4, 12, 10, 3, torch.Generator().manual_seed(5))
    some = smooth_fields(4, 12, 10, 3, torch.Generator().manual_seed(5), keep)
    assert torch.equal(some[keep], full[keep])
    assert not bool(some[~keep].any())


def _reference_placebo_reduction(data, per_view, shared, geometric, settings, seed):
    """One placebo draw the plain way: whole-image fields, one least-squares fit per view."""
    from recon.diagnose.nulls import _Pixels, smooth_fields

    pixels = _Pixels.of(data, settings.block_pixels)
    generator = torch.Generator().manual_seed(seed)
    batch, height, width = data.view_count, *data.image_size
    components = 2 if geometric else 1

    def bases(count, views, share):
        keep = (torch.arange(count * views * 2) % 2) < components
        fields = smooth_fields(
            count * views * 2, height, width, settings.nulls.field_cells, generator, keep
        )
        fields = fields.view(count, views, 2, height, width)
        view = torch.zeros_like(pixels.view) if share else pixels.view
        values = fields[:, view, :, pixels.row, pixels.column].permute(1, 0, 2)  # [P, N, 2]
        weight = (pixels.rendered**2).sum(-1)
        for component in range(components):
            mean = torch.stack(
                [
                    (values[:, pixels.view == v, component] * weight[pixels.view == v]).sum(1)
                    / weight[pixels.view == v].sum()
                    for v in range(batch)
                ],
                1,
            )
            values[..., component] -= mean[:, pixels.view]
        if not geometric:
            return (values[..., :1] * pixels.rendered[None]).double()
        return (
            values[..., :1] * pixels.gradient_x[None] + values[..., 1:2] * pixels.gradient_y[None]
        ).double()

    def solve(basis, target, fit):
        chosen = basis[:, fit].flatten(1)
        return torch.linalg.lstsq(chosen.T, target[fit].flatten()[:, None]).solution[:, 0]

    residual, explained = pixels.residual, torch.zeros_like(pixels.residual)
    if per_view:
        basis = bases(per_view, batch, False)
        for v in range(batch):
            here = pixels.view == v
            theta = solve(basis[:, here], residual[here], pixels.first[here])
            explained[here] += torch.einsum("p,pnc->nc", theta, basis[:, here])
    if shared:
        basis = bases(shared, 1, True)
        theta = solve(basis, residual - explained, pixels.first)
        explained += torch.einsum("p,pnc->nc", theta, basis)
    test = ~pixels.first
    return float(1 - ((residual - explained)[test] ** 2).sum() / (residual[test] ** 2).sum())


def test_a_placebo_draw_is_the_plain_per_view_fit_of_whole_image_fields():
    """The vectorised draw (fields read at the region's pixels, every view's fit solved at
    once) against the plain computation, per-view and shared, gain and geometric."""
    from recon.diagnose.nulls import _Pixels, _placebo_reduction

    data, _ = glossy_torus_views(specular=0.3, size=32, views=4)
    settings = DiagnoseConfig()
    pixels = _Pixels.of(data, settings.block_pixels)
    for per_view, shared, geometric in ((1, 0, False), (3, 0, True), (0, 2, False), (2, 1, True)):
        fast = _placebo_reduction(pixels, data, per_view, shared, geometric, settings, 7)
        plain = _reference_placebo_reduction(data, per_view, shared, geometric, settings, 7)
        assert abs(fast - plain) < 1e-6 * max(1.0, abs(plain)), (per_view, shared, geometric)
        assert fast > 0


def test_placebo_draws_are_drawn_once_per_layout_for_the_same_views(monkeypatch):
    """Candidates of one parameter layout (shadows and vignetting: 2 shared gains) share the
    draws; other views, another layout or other settings draw afresh, the same numbers as
    drawn without the cache."""
    import recon.diagnose.nulls as nulls

    data, _ = glossy_torus_views(specular=0.3, size=32, views=4)
    other, _ = glossy_torus_views(specular=0.3, size=32, views=4)
    settings = DiagnoseConfig(nulls=NullConfig(placebo_draws=3))
    drawn = []
    original = nulls._placebo_reduction

    def counted(*arguments):
        drawn.append(arguments[2:5])
        return original(*arguments)

    monkeypatch.setattr(nulls, "_placebo_reduction", counted)
    shadows = nulls.placebo_null(data, "shadows", settings)
    vignetting = nulls.placebo_null(data, "vignetting", settings)
    assert shadows == vignetting and len(drawn) == 3
    nulls.placebo_null(data, "exposure", settings)  # (1, 0): its own draws
    assert len(drawn) == 6
    assert nulls.placebo_null(other, "vignetting", settings)[1] == shadows[1]  # equal views
    assert len(drawn) == 9
    more = DiagnoseConfig(nulls=NullConfig(placebo_draws=4))
    assert nulls.placebo_null(other, "vignetting", more)[1][:3] == shadows[1]
    assert len(drawn) == 13
    pixels = nulls._Pixels.of(data, settings.block_pixels)
    fresh = [
        original(pixels, data, 0, 2, False, settings, settings.nulls.seed + d) for d in range(3)
    ]
    assert shadows[1] == fresh


def test_gain_normal_equations_from_the_fields_equal_those_of_the_bases():
    """A gain placebo's least squares from its factored normal equations (fields and two
    per-pixel sums) is the least squares of its materialised bases, field times render."""
    from recon.diagnose.nulls import _gain_least_squares, _least_squares_at

    generator = torch.Generator().manual_seed(3)
    fields = torch.randn(5, 400, generator=generator)
    rendered = torch.rand(400, 3, generator=generator)
    target = torch.randn(400, 3, generator=generator, dtype=torch.float64)
    bases = fields.double()[:, :, None] * rendered.double()[None]  # [P, M, 3]
    plain = _least_squares_at(bases, target)
    factored = _gain_least_squares(fields, rendered, target)
    assert torch.allclose(factored, plain, rtol=1e-10, atol=1e-12)
    assert float(plain.abs().max()) > 1e-3
