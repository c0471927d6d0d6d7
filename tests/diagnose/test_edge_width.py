"""The width of the data's silhouette edges by direction (recon.diagnose.edge_width).

Cases built to fool it: an elongated silhouette (its edges run mostly one way) blurred
isotropically must read as a defocus, not a motion blur; a line blur must read as a motion
blur, with its direction; a sharp silhouette the fit misplaced (shifted and larger) widens
nothing; a binary mask carries no width at all."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from recon.config.run_config import DecisionConfig, DiagnoseConfig, GeometricSpecificityConfig
from recon.diagnose.decision import decide
from recon.diagnose.edge_width import (
    DEFOCUS,
    MOTION,
    edge_blur_evidence,
    edge_evidence,
    edge_measurement,
    edge_producer,
    edge_profile,
    probe_blur_covariances,
)
from recon.diagnose.records import Candidate, Evidence
from recon.effects.optics import MotionBlur, gaussian_blur

SIZE = 48
OPTIONS = GeometricSpecificityConfig()


def ellipse(views: int, semi_x: float, semi_y: float, shift=(0.0, 0.0), samples: int = 8):
    """[views, SIZE, SIZE, 1] antialiased alpha of an ellipse (box filter, samples^2 per pixel),
    rotated by 25 degrees per view so the views' edges differ."""
    offsets = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples
    base = torch.arange(SIZE, dtype=torch.float64)
    ys = (base[:, None] + offsets[None, :]).reshape(-1)
    xs = ys.clone()
    mattes = []
    for view in range(views):
        angle = math.radians(25.0 * view)
        x = xs[None, :] - SIZE / 2 - shift[0]
        y = ys[:, None] - SIZE / 2 - shift[1]
        u = x * math.cos(angle) + y * math.sin(angle)
        v = -x * math.sin(angle) + y * math.cos(angle)
        inside = ((u / semi_x) ** 2 + (v / semi_y) ** 2 <= 1).double()
        matte = inside.reshape(SIZE, samples, SIZE, samples).mean(dim=(1, 3))
        mattes.append(matte)
    return torch.stack(mattes)[..., None]


def blurred(alpha: torch.Tensor, covariances: torch.Tensor) -> torch.Tensor:
    return gaussian_blur(alpha, covariances.double(), 30).clamp(0, 1)


def line_covariances(views: int, variance: float, angles_deg: list[float]) -> torch.Tensor:
    """Per-view covariances of a line blur (variance along the line) plus a little isotropic
    spread, as a rasterised path has."""
    rows = []
    for angle in angles_deg[:views]:
        direction = torch.tensor(
            [math.cos(math.radians(angle)), math.sin(math.radians(angle))], dtype=torch.float64
        )
        rows.append(variance * torch.outer(direction, direction) + 0.1 * torch.eye(2))
    return torch.stack(rows)


def data(observed: torch.Tensor, rendered: torch.Tensor) -> SimpleNamespace:
    return SimpleNamespace(
        observed_alpha=observed.float(),
        rendered_alpha=rendered.float(),
        view_count=observed.shape[0],
    )


def test_edge_width_grows_with_the_blur_and_points_along_a_line_blur():
    sharp = ellipse(1, 14, 14)
    widths = [
        float(edge_profile(blurred(sharp, torch.eye(2)[None] * variance), 0.05)[0, 0])
        for variance in (0.05, 0.4, 1.0)
    ]
    assert widths[0] < widths[1] < widths[2]
    # A line blur at 30 degrees widens the edges whose normal points along 30 degrees.
    streaked = blurred(sharp, line_covariances(1, 1.5, [30.0]))
    a, b, c = edge_profile(streaked, 0.05)[0].tolist()
    assert math.hypot(b, c) > 0.2 * a
    angle = math.degrees(math.atan2(c, b)) / 2 % 180
    assert abs(angle - 30.0) < 8.0


def test_an_isotropic_blur_of_an_elongated_silhouette_is_a_defocus_not_a_motion_blur():
    rendered = ellipse(6, 18, 6)  # edges mostly along the long axis
    observed = blurred(rendered, torch.eye(2)[None] * 0.5)
    evidence = {item.candidate: item for item in edge_evidence(data(observed, rendered), OPTIONS)}
    assert evidence[DEFOCUS].passed and not evidence[MOTION].passed
    assert evidence[DEFOCUS].details["favours"] == DEFOCUS
    assert evidence[DEFOCUS].details["widening_px"] > 0.1


def test_a_per_view_line_blur_is_a_motion_blur_with_its_directions():
    angles = [10.0, 60.0, 100.0, 150.0, 30.0, 120.0]
    rendered = ellipse(6, 16, 11)
    observed = blurred(rendered, line_covariances(6, 1.2, angles))
    measurement = edge_measurement(data(observed, rendered), OPTIONS)
    assert measurement is not None
    evidence = {item.candidate: item for item in edge_evidence(data(observed, rendered), OPTIONS)}
    assert evidence[MOTION].passed and not evidence[DEFOCUS].passed
    for found, true in zip(measurement["angles_deg"], angles, strict=True):
        difference = abs(found - true) % 180
        assert min(difference, 180 - difference) < 15.0


def test_a_misplaced_sharp_silhouette_widens_nothing():
    rendered = ellipse(4, 12, 9)
    observed = ellipse(4, 13, 10, shift=(0.7, -0.5))  # the fit's outline is off, not blurred
    measurement = edge_measurement(data(observed, rendered), OPTIONS)
    assert measurement is not None
    assert abs(measurement["widening_px"]) < 0.03
    blurred_evidence = edge_evidence(
        data(blurred(observed, torch.eye(2)[None] * 0.6), rendered), OPTIONS
    )
    widened = blurred_evidence[0].details["widening_px"]
    assert widened > 5 * abs(measurement["widening_px"])


def test_a_binary_mask_carries_no_width():
    rendered = ellipse(3, 12, 9)
    mask = (blurred(rendered, torch.eye(2)[None] * 0.6) > 0.5).double()
    assert edge_measurement(data(mask, rendered), OPTIONS) is None
    assert edge_evidence(data(mask, rendered), OPTIONS) == []


def test_switched_off_it_measures_nothing():
    rendered = ellipse(3, 12, 9)
    observed = blurred(rendered, torch.eye(2)[None] * 0.6)
    options = GeometricSpecificityConfig(edge_widths=False)
    assert edge_evidence(data(observed, rendered), options) == []


def probed(name: str, lower_bound: float, conditional_on: str | None = None) -> Candidate:
    """A candidate whose probe alone has the lower bound given (measured on top of another
    effect when conditional_on names one, the probe alone kept beside it)."""
    candidate = Candidate(name)
    alone = Evidence("probe", name, lower_bound, math.nan, False, "probe", {"reduction": 0.3})
    if conditional_on is None:
        candidate.add(alone)
    else:
        details = {"conditional_on": conditional_on, "alone": alone.to_json()}
        candidate.add(Evidence("probe", name, -0.01, math.nan, False, "probe on top", details))
    return candidate


def test_the_producer_measures_only_where_both_blur_probes_could_clear():
    rendered = ellipse(4, 12, 9)
    inputs = SimpleNamespace(data=data(blurred(rendered, torch.eye(2)[None] * 0.6), rendered))
    settings = DiagnoseConfig()
    # The motion probe measured on top of the defocus: its probe alone counts.
    both = [probed(DEFOCUS, 0.25), probed(MOTION, 0.23, conditional_on=DEFOCUS)]
    assert {item.candidate for item in edge_producer(inputs, both, settings)} == {DEFOCUS, MOTION}
    # A clean fit's blur probes below the floor of every allowance: nothing to tie, no cost.
    assert edge_producer(inputs, [probed(DEFOCUS, 0.25), probed(MOTION, 0.01)], settings) == []
    assert edge_producer(inputs, [probed(DEFOCUS, 0.25)], settings) == []


# The edge_blur null: a blur probe's blur must show in the data's own edges.


def blur_probed(name: str, parameters: dict, lower_bound: float = 0.3) -> Candidate:
    """A blur candidate whose probe clears its allowance with the parameters given."""
    candidate = Candidate(name)
    details = {"reduction": lower_bound + 0.05, "parameters": parameters}
    candidate.add(Evidence("probe", name, lower_bound, math.nan, False, "probe", details))
    return candidate


def motion_module(lengths: list[float], angles: list[float]) -> MotionBlur:
    """A MotionBlur whose per-view lines have these lengths (px) and angles (degrees)."""
    module = MotionBlur(len(lengths))
    with torch.no_grad():
        for view, (length, angle) in enumerate(zip(lengths, angles, strict=True)):
            size = length**2 / 24  # |w|: major variance ~ 2 |w| = L^2 / 12
            doubled = math.radians(2 * angle)
            module.line[view] = torch.tensor([size * math.cos(doubled), size * math.sin(doubled)])
    return module


def motion_parameters(lengths: list[float], angles: list[float]) -> dict:
    """A motion blur probe's reported parameters (MotionBlur.parameters_summary)."""
    return motion_module(lengths, angles).parameters_summary()


def test_a_motion_probe_blur_is_rebuilt_from_its_reported_parameters():
    lengths, angles = [3.0, 4.5, 2.0], [20.0, 95.0, 150.0]
    parameters = motion_parameters(lengths, angles)
    with torch.no_grad():
        expected = motion_module(lengths, angles).covariances().double()
    rebuilt = probe_blur_covariances(blur_probed(MOTION, parameters), 3)
    assert rebuilt is not None
    # The summary reports the minor variance clamped at 0; the module's is down to -0.05 px^2
    # (its smoothing of |w| at 0), a sharpening across the line too slight to widen anything.
    assert torch.allclose(rebuilt, expected, atol=0.06)
    assert torch.allclose(
        torch.linalg.eigvalsh(rebuilt)[:, 1], torch.linalg.eigvalsh(expected)[:, 1], atol=1e-3
    )
    defocus = probe_blur_covariances(blur_probed(DEFOCUS, {"variance_px2": 0.7}), 2)
    assert torch.allclose(defocus, 0.7 * torch.eye(2, dtype=torch.float64).expand(2, 2, 2))


def test_a_blur_in_the_data_shows_in_its_edges_as_its_probe_blur_does():
    angles = [10.0, 60.0, 100.0, 150.0, 30.0, 120.0]
    rendered = ellipse(6, 16, 11)
    defocused = blurred(rendered, torch.eye(2)[None] * 0.6)
    defocus = blur_probed(DEFOCUS, {"variance_px2": 0.6})
    (found,) = edge_blur_evidence(data(defocused, rendered), [defocus], OPTIONS)
    assert 0.8 < found.statistic < 1.2, found.reason
    parameters = motion_parameters([3.5] * 6, angles)
    streaked = blurred(rendered, probe_blur_covariances(blur_probed(MOTION, parameters), 6))
    motion = blur_probed(MOTION, parameters)
    (found,) = edge_blur_evidence(data(streaked, rendered), [motion], OPTIONS)
    assert 0.8 < found.statistic < 1.2, found.reason
    # Decided, the null passes and the probe decides.
    motion.add(found)
    assert decide(motion, DecisionConfig()).significant


def test_a_misplaced_silhouette_is_no_blur_whatever_the_blur_probe_found():
    """Built to fool the blur probes: the fit's outline is off (shifted, larger), which any blur
    of the render reduces; the data's edges are as sharp as the render's."""
    rendered = ellipse(4, 12, 9)
    observed = ellipse(4, 13, 10, shift=(0.7, -0.5))
    defocus = blur_probed(DEFOCUS, {"variance_px2": 0.8})
    (found,) = edge_blur_evidence(data(observed, rendered), [defocus], OPTIONS)
    assert found.statistic < 0.2, found.reason
    defocus.add(found)
    decide(defocus, DecisionConfig())
    assert not defocus.significant and "silhouette edges" in defocus.why
    # Blurred by a third of the probe's variance, the edges show less than half its widening.
    faint = blurred(observed, torch.eye(2)[None] * 0.25)
    (found,) = edge_blur_evidence(data(faint, rendered), [defocus], OPTIONS)
    assert 0.2 < found.statistic < DecisionConfig().edge_blur_minimum_ratio


def test_no_edge_blur_null_without_soft_edges_or_a_probe_blur():
    rendered = ellipse(3, 12, 9)
    mask = (blurred(rendered, torch.eye(2)[None] * 0.6) > 0.5).double()
    defocus = blur_probed(DEFOCUS, {"variance_px2": 0.6})
    assert edge_blur_evidence(data(mask, rendered), [defocus], OPTIONS) == []
    observed = blurred(rendered, torch.eye(2)[None] * 0.6)
    sharpening = blur_probed(DEFOCUS, {"variance_px2": -0.2})
    assert edge_blur_evidence(data(observed, rendered), [sharpening], OPTIONS) == []
    assert edge_blur_evidence(data(observed, rendered), [Candidate(DEFOCUS)], OPTIONS) == []


def test_a_matte_harder_than_the_render_is_no_blur():
    """A renderer whose coverage is fractional on few edge pixels (most are 0 or 1) gives a
    matte harder than the fitted render's: too few soft pixels for the edges' shape (the
    inform row), enough to show that the data's edges are not wider."""
    rendered = ellipse(4, 12, 9)
    observed = torch.where((rendered > 0.35) & (rendered < 0.65), rendered, rendered.round())
    band = ((observed > 0.02) & (observed < 0.98)).sum()
    edge = ((rendered > 0.02) & (rendered < 0.98)).sum()
    assert OPTIONS.edge_blur_soft_minimum <= band / edge < OPTIONS.edge_soft_minimum
    assert edge_measurement(data(observed, rendered), OPTIONS) is None
    defocus = blur_probed(DEFOCUS, {"variance_px2": 0.5})
    (found,) = edge_blur_evidence(data(observed, rendered), [defocus], OPTIONS)
    assert found.statistic < 0, found.reason
