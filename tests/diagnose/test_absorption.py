"""Absorption evidence: a frozen-geometry refit with vignetting takes back from the texture the
darkening that a fit without it baked in, and finds nothing to take back on clean data."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from diagnose_scenes import patterned_torus

from recon.camera import orbit_cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose.absorption import (
    FrozenTrainingViews,
    bootstrap_reduction,
    frozen_refit,
    heldout_errors,
    heldout_modules,
)
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.decision import absorption_threshold, decide
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.which import probe_evidence
from recon.effects import make_effect
from recon.io.datasets import CaptureSet
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

SIZE, TRAIN, TEST = 40, 12, 6
SETTINGS = DiagnoseConfig()
DECISION = SETTINGS.decision


def scene_and_views(corner_darkening: float):
    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.7 * p + 0.2, 0.5 * (1 - p) + 0.2])
    lighting = Lighting.constant(0.9)
    renderer = Renderer(texture_filter="linear-mipmap-linear", texture_boundary="clamp")
    cameras = orbit_cameras(
        TRAIN + TEST, (SIZE, SIZE), distance=2.0, fov_x_deg=60, elevation_deg=35
    )
    output = renderer.render(mesh, cameras, lighting)
    vignetting = make_effect("vignetting")
    vignetting.set_polynomial(-corner_darkening)
    with torch.no_grad():
        observed, _ = vignetting(output.color, output.alpha, cameras, None)
    # What a fit without the effect keeps: the texture darkened by the average falloff.
    mesh.texture = mesh.texture * (1 - 0.3 * corner_darkening)
    train = CaptureSet(
        cameras[:TRAIN],
        observed[:TRAIN],
        output.alpha[:TRAIN],
        [str(i) for i in range(TRAIN)],
        "train",
    )
    with torch.no_grad():
        fitted = renderer.render(mesh, cameras[TRAIN:], lighting)
    test = build_diagnosis_data(
        observed[TRAIN:], output.alpha[TRAIN:], fitted, cameras[TRAIN:], lighting, mesh
    )
    return FrozenTrainingViews.build(train, mesh, lighting, Renderer(texture_filter="linear")), test


def absorption_reduction(corner_darkening: float) -> tuple[float, tuple[float, float]]:
    torch.manual_seed(0)
    frozen, test = scene_and_views(corner_darkening)
    renderer = Renderer(texture_filter="linear")
    errors = []
    for names in ([], ["vignetting"]):
        settings = replace_settings(SETTINGS, absorption_steps=60)
        mesh, lighting, fitted = frozen_refit(frozen, names, renderer, settings)
        modules = heldout_modules(names, fitted, test.view_count, "cpu")
        errors.append(heldout_errors(replace_scene(test, mesh, lighting), modules, SETTINGS)[0])
    return bootstrap_reduction(errors[0], errors[1], SETTINGS.bootstrap_samples)


def replace_settings(settings, **changes):
    from dataclasses import replace

    return replace(settings, **changes)


def replace_scene(data, mesh, lighting):
    from dataclasses import replace

    return replace(data, mesh=mesh, lighting=lighting)


def test_vignetting_pulled_back_out_of_the_texture():
    reduction, (low, _) = absorption_reduction(0.4)
    assert low > 0.08, reduction


def test_clean_views_leave_nothing_to_absorb():
    reduction, (_, high) = absorption_reduction(0.0)
    assert abs(reduction) < 0.04 and high < 0.06, reduction


def test_frozen_buffers_cover_every_training_view_once():
    frozen, _ = scene_and_views(0.0)
    views = torch.cat([group[1] for group in frozen.groups])
    assert torch.equal(views, torch.arange(TRAIN))
    assert all(group[2].shape[0] == group[1].shape[0] for group in frozen.groups)


def make(name: str, probe: tuple[float, float], absorption=None, reduction=None) -> Candidate:
    """A decided candidate with probe evidence (interval; reduction default its midpoint) and,
    optionally, absorption evidence (interval)."""
    candidate = Candidate(name)
    middle = sum(probe) / 2 if reduction is None else reduction
    candidate.add(probe_evidence(name, middle, probe, {}))
    if absorption is not None:
        candidate.add(
            Evidence(
                "absorption",
                name,
                absorption[0],
                float("nan"),
                False,
                "absorption",
                {"interval": list(absorption), "reduction": sum(absorption) / 2},
            )
        )
    return decide(candidate, DECISION)


class RefitCalled(Exception):
    """Raised by the stand-ins for the refits' first step: a test that expects it knows the
    refits ran."""


@pytest.fixture
def frozen_refits_raise(monkeypatch):
    """(RefitCalled, data, inputs): the absorption module with FrozenTrainingViews.build (every
    frozen-geometry refit's start) and refit_with (the lens refits) raising RefitCalled, and
    stand-ins for the diagnosis data and the absorption inputs it is called with."""
    import recon.diagnose.absorption as absorption

    def frozen_build(*arguments, **options):
        raise RefitCalled

    monkeypatch.setattr(absorption.FrozenTrainingViews, "build", frozen_build)
    monkeypatch.setattr(absorption, "refit_with", frozen_build)
    movable = SimpleNamespace(to=lambda device: None)
    data = SimpleNamespace(mesh=movable, lighting=movable)
    return RefitCalled, data, inputs_with()


def inputs_with(**settings):
    from recon.config.run_config import RunConfig

    config = RunConfig()
    return SimpleNamespace(
        config=SimpleNamespace(diagnose=config.diagnose, fit=config.fit, seed=0),
        model=SimpleNamespace(pbr=None, effects=[], effect_names=[]),
        training=None,
        device=torch.device("cpu"),
        scratch=None,
    )


@pytest.mark.parametrize("effect", ["lens_distortion", "specular"])
def test_refits_run_only_where_the_probe_sees_a_residual(frozen_refits_raise, effect):
    """The refits (the dearest step: the lens refits move the geometry, the specular ones
    rasterise the training views first) are skipped when the frozen-scene probe's held-out
    reduction is under diagnose.decision.minimum_share, and run when it is above."""
    import recon.diagnose.absorption as absorption

    RefitCalled, data, inputs = frozen_refits_raise
    minimum = DECISION.minimum_share
    quiet = make(effect, (0.0, 0.02), reduction=0.5 * minimum)
    absorption.absorption_probes([quiet], data, inputs)
    assert quiet.evidence_of("absorption") is None
    loud = make(effect, (0.0, 0.08), reduction=2 * minimum)
    with pytest.raises(RefitCalled):
        absorption.absorption_probes([loud], data, inputs)


def test_a_pbr_model_is_not_refitted(frozen_refits_raise):
    import recon.diagnose.absorption as absorption

    RefitCalled, data, inputs = frozen_refits_raise
    inputs.model.pbr = "a pbr material"
    loud = make("specular", (0.0, 0.08), reduction=0.05)
    absorption.absorption_probes([loud], data, inputs)
    assert loud.evidence_of("absorption") is None


def test_refits_on_top_of_a_given_effect_only_follow_earlier_evidence(frozen_refits_raise):
    """On top of a per-view effect, a candidate whose unconditional absorption lower bound was
    not positive keeps that evidence (no refit); one whose bound was positive is refitted."""
    import recon.diagnose.absorption as absorption

    RefitCalled, data, inputs = frozen_refits_raise
    quiet = make("specular", (0.0, 0.01), absorption=(-0.01, 0.02), reduction=0.001)
    absorption.absorption_probes([quiet], None, inputs, given="exposure")
    assert quiet.evidence_of("absorption").interval == (-0.01, 0.02)
    assert quiet.evidence_of("absorption").details.get("conditional_on") is None
    loud = make("specular", (0.0, 0.01), absorption=(0.01, 0.05), reduction=0.001)
    with pytest.raises(RefitCalled):
        absorption.absorption_probes([loud], data, inputs, given="exposure")


def test_refits_on_top_of_a_given_effect_need_room_to_clear_the_allowance(frozen_refits_raise):
    """A positive but small unconditional lower bound is not enough: the refits run again only
    when the first pass's upper bound, as a share of the error the given effect leaves (its
    probe interval's upper end), reaches the allowance."""
    import recon.diagnose.absorption as absorption

    RefitCalled, data, inputs = frozen_refits_raise
    threshold = absorption_threshold("specular", DECISION)
    # The lens datasets' specular evidence: a lower bound just above zero, far below the
    # allowance even on the error a lens distortion (probe interval up to 0.26) leaves.
    given = make("lens_distortion", (0.15, 0.26))
    faint = make("specular", (-0.001, 0.001), absorption=(0.001, 0.5 * threshold))
    absorption.absorption_probes([given, faint], data, inputs, given="lens_distortion")
    assert faint.evidence_of("absorption").interval == (0.001, 0.5 * threshold)
    # The same evidence under a given effect that removes 60 % of the error could clear it.
    strong = make("exposure", (0.4, 0.6))
    with pytest.raises(RefitCalled):
        absorption.absorption_probes([strong, faint], data, inputs, given="exposure")


def test_both_absorption_passes_rasterise_the_training_views_once(monkeypatch):
    """The pass on top of a given effect reuses the first pass's rasterised training views."""
    import recon.diagnose.absorption as absorption

    builds = []

    def frozen_build(*arguments, **options):
        builds.append(1)
        return SimpleNamespace(view_count=2)

    def frozen_refit(frozen, names, renderer, settings):
        modules = [SimpleNamespace(name=name, parameters_summary=dict) for name in names]
        return movable, movable, modules

    def heldout_errors(refitted, modules, settings):
        errors = torch.tensor([1.0, 1.0]) * (0.5 if "specular" in [m.name for m in modules] else 1)
        return errors, None

    movable = SimpleNamespace(to=lambda device: movable)
    monkeypatch.setattr(absorption.FrozenTrainingViews, "build", frozen_build)
    monkeypatch.setattr(absorption, "frozen_refit", frozen_refit)
    monkeypatch.setattr(absorption, "heldout_errors", heldout_errors)
    monkeypatch.setattr(absorption, "heldout_modules", lambda names, fitted, *a: fitted)
    monkeypatch.setattr(absorption, "replace", lambda data, **changes: data)
    data = SimpleNamespace(mesh=movable, lighting=movable, view_count=2, observed=torch.zeros(1))
    inputs = inputs_with()
    specular = make("specular", (-0.01, 0.05), reduction=0.03)
    exposure = make("exposure", (0.4, 0.6))
    cache = absorption.AbsorptionCache()
    absorption.absorption_probes([exposure, specular], data, inputs, cache=cache)
    assert specular.evidence_of("absorption").details["reduction"] == 0.5
    assert specular.significant and specular.decided_by == "absorption"
    absorption.absorption_probes([exposure, specular], data, inputs, given="exposure", cache=cache)
    assert specular.evidence_of("absorption").details["conditional_on"] == "exposure"
    assert len(builds) == 1


def test_a_given_effect_voids_the_geometry_refits_evidence_without_refitting(monkeypatch):
    """On top of a given effect the lens refits do not run again: the evidence measured alone
    is kept in the record but no longer decides, so the conditional probe does; a lens
    candidate that was significant by absorption alone stops being significant."""
    import recon.diagnose.absorption as absorption
    from recon.diagnose.decision import excess

    class RefitCalled(Exception):
        pass

    def refit_with(*arguments, **options):
        raise RefitCalled

    monkeypatch.setattr(absorption, "refit_with", refit_with)
    threshold = absorption_threshold("lens_distortion", DECISION)
    lens = make("lens_distortion", (-0.01, 0.01), absorption=(threshold + 0.1, 0.4))
    assert lens.significant and lens.decided_by == "absorption"
    inputs = inputs_with()
    absorption.absorption_probes([lens], None, inputs, given="defocus_blur")
    voided = lens.evidence_of("absorption")
    assert voided is not None and voided.details["discounted_by"] == "defocus_blur"
    assert "void beside defocus_blur" in voided.void
    assert not lens.significant and excess(lens) < 0
    again = decide(Candidate.from_json(lens.to_json()), DECISION)
    assert not again.significant and again.evidence_of("absorption").void
    # Without a given effect the refits still run.
    fresh = make("lens_distortion", (-0.01, 0.01), reduction=0.1)
    with pytest.raises(RefitCalled):
        absorption.absorption_probes([fresh], None, inputs)
