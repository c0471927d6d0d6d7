"""The diagnosis' flat-field measurement and how it decides vignetting."""

from __future__ import annotations

import math

import pytest
import torch

from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.decision import decide, redecide
from recon.diagnose.diagnose import flat_field_evidence, mark_radial_coverage
from recon.diagnose.flat_field import local_value, measure_flat_field
from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.diagnose.which import conditioning_effect, probe_evidence
from recon.errors import ReconError

ALLOWANCE = DecisionConfig().flat_field_allowance

SIZE = 64


def _falloff(height: int, width: int) -> torch.Tensor:
    """An off-centre falloff [H, W] that steepens toward the corners (float64)."""
    rows = torch.arange(height, dtype=torch.float64) + 0.5
    columns = torch.arange(width, dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(rows, columns, indexing="ij")
    radius = torch.hypot(u - 0.5 * width - 2.0, v - 0.5 * height + 1.0) / (
        0.5 * math.hypot(height, width)
    )
    return (1 + 0.3 * radius**2) ** -2 * (1 - 0.25 * radius**6)


def _exact(falloff: torch.Tensor) -> tuple[float, float]:
    """The falloff's own corner and half-way values over the centre, by the definitions the
    measurement follows, evaluated on a 16x finer grid (bilinear at the exact points)."""
    height, width = falloff.shape

    def at(u: float, v: float) -> float:
        radius = math.hypot(u - 0.5 * width - 2.0, v - 0.5 * height + 1.0) / (
            0.5 * math.hypot(height, width)
        )
        return (1 + 0.3 * radius**2) ** -2 * (1 - 0.25 * radius**6)

    centre = at(0.5 * width, 0.5 * height)
    corners = [(0.5, 0.5), (width - 0.5, 0.5), (0.5, height - 0.5), (width - 0.5, height - 0.5)]
    corner = sum(at(u, v) for u, v in corners) / 4 / centre
    half = 0.25 * math.hypot(height, width)
    circle = [
        at(0.5 * width + half * math.cos(a), 0.5 * height + half * math.sin(a))
        for a in (2 * math.pi * k / 64 for k in range(64))
    ]
    return corner, sum(circle) / 64 / centre


def test_local_value_is_exact_on_a_quadratic_even_at_the_corner():
    rows = torch.arange(20, dtype=torch.float64) + 0.5
    columns = torch.arange(30, dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(rows, columns, indexing="ij")
    image = 2 + 0.1 * u - 0.05 * v + 0.01 * u * u - 0.002 * u * v + 0.003 * v * v
    for column, row in ((0.5, 0.5), (29.5, 19.5), (15.0, 10.0), (3.2, 17.7)):
        expected = (
            2 + 0.1 * column - 0.05 * row + 0.01 * column**2 - 0.002 * column * row + 0.003 * row**2
        )
        assert local_value(image, column, row, 4) == pytest.approx(expected, rel=1e-9)


def test_corner_and_half_way_falloff_are_read_off_the_frames_whatever_the_exposure():
    falloff = _falloff(SIZE, SIZE)
    true_corner, true_half = _exact(falloff)
    # Two frames at different exposures and white balance, with a little noise.
    generator = torch.Generator().manual_seed(0)
    gains = torch.tensor([[0.9, 1.0, 1.1], [0.6, 0.7, 0.5]], dtype=torch.float64)
    frames = 0.5 * falloff[None, :, :, None] * gains[:, None, None, :]
    frames = frames + 0.002 * torch.randn(frames.shape, generator=generator, dtype=torch.float64)
    measured = measure_flat_field(frames)
    assert true_corner < 0.6
    assert measured["corner_falloff"] == pytest.approx(true_corner, rel=0.01)
    assert measured["half_radius_falloff"] == pytest.approx(true_half, rel=0.005)
    assert measured["frames"] == 2 and len(measured["corner_falloff_per_frame"]) == 2
    assert measured["deviation"] == pytest.approx(1 - measured["corner_falloff"])
    # The profile falls from about 1 at the centre toward the corner value.
    assert measured["profile"][0] == pytest.approx(1.0, abs=0.01)
    assert measured["profile"][-1] < 0.7
    # A response curve bends the ratios: given its exponent, it is undone.
    curved = measure_flat_field(frames.clamp_min(0) ** 0.6, response_exponent=0.6)
    assert measure_flat_field(frames.clamp_min(0) ** 0.6)["corner_falloff"] > true_corner + 0.1
    assert curved["corner_falloff"] == pytest.approx(true_corner, rel=0.02)


def test_a_uniform_card_measures_flat():
    frames = torch.full((1, 32, 48, 3), 0.3, dtype=torch.float64)
    measured = measure_flat_field(frames)
    assert measured["corner_falloff"] == pytest.approx(1.0, abs=1e-9)
    assert measured["deviation"] < 1e-9


def test_frames_of_the_wrong_shape_are_refused_by_name():
    with pytest.raises(ReconError, match=r"flat_field.frames.*got \(2, 8, 8\)"):
        measure_flat_field(torch.ones(2, 8, 8))


def _vignetting(probe_lower: float, deviation: float | None = None) -> Candidate:
    candidate = Candidate("vignetting")
    candidate.add(probe_evidence("vignetting", probe_lower + 0.01, (probe_lower, 0.5), {"a": -0.2}))
    if deviation is not None:
        candidate.add(
            Evidence("flat_field", "vignetting", deviation, math.nan, False, "flat-field frames")
        )
    return decide(candidate, DecisionConfig())


def test_the_flat_field_overrules_the_residual_evidence_either_way():
    assert _vignetting(0.3).decided_by == "probe"
    loud = _vignetting(0.3, ALLOWANCE / 2)
    assert not loud.significant and loud.decided_by == ""
    assert not _vignetting(-0.1).significant
    quiet = _vignetting(-0.1, 0.3)
    assert quiet.significant and quiet.decided_by == "flat_field"
    # It survives the JSON round trip and a re-decision of a stored diagnosis.
    again = Candidate.from_json(quiet.to_json())
    assert again.evidence_of("flat_field") == quiet.evidence_of("flat_field")
    stored = Diagnosis(candidates=[loud, quiet]).to_json()
    decided = redecide(stored, DiagnoseConfig())
    assert [item.significant for item in decided.candidates] == [True, False]
    assert decided.candidates[0].decided_by == "flat_field"


def test_a_flat_field_decided_top_effect_conditions_only_when_its_probe_cleared():
    assert conditioning_effect([_vignetting(0.3, 0.3)]) == "vignetting"
    assert conditioning_effect([_vignetting(-0.1, 0.3)]) is None


def test_measured_falloffs_replace_the_polynomial_s_and_keep_it_beside():
    candidate = _vignetting(0.3)
    probe = candidate.evidence_of("probe")
    probe.details["parameters"] = {"corner_falloff": 0.86, "half_radius_falloff": 0.95, "a": -0.2}
    refits = [{"parameters": {"vignetting": {"corner_falloff": 0.84, "half_radius_falloff": 0.94}}}]
    measured = {"corner_falloff": 0.67, "half_radius_falloff": 0.948}
    mark_radial_coverage([candidate], refits, 0.6, measured)
    for parameters in (probe.details["parameters"], refits[0]["parameters"]["vignetting"]):
        assert parameters["corner_falloff"] == 0.67 and parameters["half_radius_falloff"] == 0.948
        assert parameters["falloff_source"] == "flat_field" and parameters["covered_radius"] == 1.0
        assert parameters["object_radius"] == 0.6
    assert probe.details["parameters"]["model_corner_falloff"] == 0.86
    assert refits[0]["parameters"]["vignetting"]["model_corner_falloff"] == 0.84
    # Without frames the polynomial's values stand, with the object's radius.
    plain = {"parameters": {"vignetting": {"corner_falloff": 0.8}}}
    mark_radial_coverage([], [plain], 0.6, None)
    assert plain["parameters"]["vignetting"] == {"corner_falloff": 0.8, "covered_radius": 0.6}


def test_a_flat_card_spares_the_vignetting_regression(monkeypatch):
    """With frames that measured no falloff the regression cannot change the verdict, so it
    does not run; with a falloff it does (its evidence still ranks the effect)."""
    from types import SimpleNamespace

    from recon.diagnose import absorption

    calls = []

    def rendered(captures, model, device, band_pixels):
        calls.append("train")
        return "training views"

    def regression(training, data, settings):
        return torch.ones(2), torch.full((2,), 0.5), None

    monkeypatch.setattr(absorption, "render_diagnosis_data", rendered)
    monkeypatch.setattr(absorption, "radial_absorption", regression)
    monkeypatch.setattr(absorption, "_record", lambda candidate, *rest: calls.append("recorded"))
    inputs = SimpleNamespace(
        config=SimpleNamespace(diagnose=DiagnoseConfig()),
        model=SimpleNamespace(pbr=None),
        training=None,
        device=torch.device("cpu"),
    )
    absorption.absorption_probes([_vignetting(0.3, 0.0)], None, inputs)
    assert calls == []
    absorption.absorption_probes([_vignetting(-0.1, 0.3)], None, inputs)
    assert calls == ["train", "recorded"]


def test_flat_field_evidence_decides_the_candidates_its_facts_apply_to():
    vignetting, exposure = _vignetting(0.3), Candidate("exposure")
    frames = _falloff(SIZE, SIZE)[None, :, :, None].expand(2, SIZE, SIZE, 3)
    measurement = flat_field_evidence([vignetting, exposure], frames, DiagnoseConfig())
    assert measurement["allowance"] == ALLOWANCE and measurement["deviation"] > ALLOWANCE
    assert vignetting.decided_by == "flat_field"
    assert exposure.evidence_of("flat_field") is None


def test_the_flat_field_figure_is_drawn(tmp_path):
    from recon.diagnose.figures import flat_field_figure

    falloff = _falloff(SIZE, SIZE)
    measured = measure_flat_field(falloff[None, :, :, None].expand(1, SIZE, SIZE, 3))
    model = {"a": -0.2, "b": 0.05, "object_radius": 0.6}
    path = flat_field_figure(measured, model, tmp_path / "flat_field.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Without a model (vignetting not a candidate) the measured profile alone.
    assert flat_field_figure(measured, None, tmp_path / "alone.png").stat().st_size > 1000


def test_unusable_frames_are_refused_by_name():
    dark = torch.zeros(2, 16, 16, 3, dtype=torch.float64)
    dark[0] = 0.5
    with pytest.raises(ReconError, match=r"flat_field.frames\[1\]: no light"):
        measure_flat_field(dark)
    clipped = torch.full((1, 16, 16, 3), 0.5, dtype=torch.float64)
    clipped[0, :8] = 1.0
    with pytest.raises(ReconError, match=r"flat_field.frames\[0\]: 50.0 % of the pixels clipped"):
        measure_flat_field(clipped)
    broken = torch.full((1, 16, 16, 3), float("nan"), dtype=torch.float64)
    with pytest.raises(ReconError, match="non-finite"):
        measure_flat_field(broken)
