"""The visibility fingerprint: self-shadowing of the fitted light baked into the fitted albedo is
named (shadows when it is whole, interreflection when bounced light filled part of it back); an
albedo with no baked shadowing, or one darker in concavities under any light (a texture or an
occlusion, not this light's shadows), names nothing; its share stays within 0..1 whatever the
slope. The "fitted" albedo here is built by hand from a random pattern and the mesh's own
predicted visible share."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from data_synth.shapes import torus
from recon.camera import orbit_cameras
from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.decision import decide
from recon.diagnose.fingerprint import visibility_fingerprint
from recon.diagnose.records import Candidate
from recon.effects.light_transport import vertex_light_visibility, vertex_occlusion
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SIZE = 64
DECISION = DecisionConfig()
SETTINGS = DiagnoseConfig()


def sky_and_sun() -> Lighting:
    lighting = Lighting.constant(0.3)
    lighting.directional = [
        DirectionalLight(torch.tensor([0.3, 0.9, 0.2]), torch.tensor([2.0, 2.0, 2.0]))
    ]
    return lighting


@pytest.fixture(scope="module")
def scene():
    """A torus lying in the x-z plane (its inner ring shadows itself) under sky + sun."""
    torch.set_num_threads(1)
    mesh = torus(resolution=32)
    lighting = sky_and_sun()
    share = vertex_light_visibility(mesh.verts, mesh.faces, lighting).float()
    generator = torch.Generator().manual_seed(0)
    # A blotchy albedo that knows nothing of the lighting: two levels on a random vertex field.
    pattern = torch.rand(mesh.verts.shape[0], 1, generator=generator)
    base = torch.where(pattern > 0.5, 0.7, 0.35) * torch.tensor([[1.0, 0.9, 0.8]])
    cameras = orbit_cameras(8, (SIZE, SIZE), distance=2.8, fov_x_deg=40, elevation_deg=35)
    return mesh, lighting, share, base, cameras


def fingerprint_with(scene, darkening: torch.Tensor, lighting: Lighting | None = None):
    """The fingerprint of the base albedo times a per-vertex darkening [V]."""
    mesh, fitted_light, _, base, cameras = scene
    lighting = lighting or fitted_light
    fitted = replace(mesh, vertex_colors=base * darkening[:, None], texture=None)
    output = Renderer().render(fitted, cameras, lighting)
    data = build_diagnosis_data(output.color, output.alpha, output, cameras, lighting, fitted)
    return visibility_fingerprint(data, output, SETTINGS)


def fingerprint_of(scene, baked_exponent: float):
    """The fingerprint of an albedo with share^exponent of the self-shadowing baked in."""
    return fingerprint_with(scene, scene[2] ** baked_exponent)


def test_the_torus_shadows_itself(scene):
    _, _, share, _, _ = scene
    assert float(share.min()) < 0.7 and float(share.max()) > 0.99


def test_clean_albedo_has_no_fingerprint(scene):
    fingerprint = fingerprint_of(scene, 0.0)
    assert fingerprint.coverage >= DECISION.fingerprint_minimum_coverage
    assert abs(fingerprint.slope) < 0.1 and fingerprint.share < 0.1, fingerprint
    assert fingerprint.p_value > 0.1
    assert fingerprint.names(DECISION) is None
    assert fingerprint.identifiability("shadows", DECISION) is None


def test_baked_shadows_are_named_shadows_not_interreflection(scene):
    fingerprint = fingerprint_of(scene, 1.0)
    assert fingerprint.share == pytest.approx(1.0, abs=0.15), fingerprint
    assert fingerprint.placebo_lights > 100
    assert fingerprint.excess > DECISION.fingerprint_minimum
    assert fingerprint.p_value < DECISION.fingerprint_alpha
    assert fingerprint.names(DECISION) == "shadows"
    assert not fingerprint.evidence("interreflection").passed_under(DECISION)
    assert fingerprint.identifiability("shadows", DECISION) is None


def test_partly_filled_shadows_are_named_interreflection(scene):
    fingerprint = fingerprint_of(scene, 0.4)
    assert fingerprint.share == pytest.approx(0.4, abs=0.12), fingerprint
    assert fingerprint.slope < DECISION.shadow_share
    assert fingerprint.names(DECISION) == "interreflection"


def test_a_share_cannot_exceed_its_meaning(scene):
    """An albedo three times as dark (in log) as the predicted self-shadowing: the slope says
    so, the share stays 1 and the reason says why."""
    fingerprint = fingerprint_of(scene, 3.0)
    assert fingerprint.slope > 2.0
    assert fingerprint.share == 1.0
    record = fingerprint.evidence("shadows").record()
    assert -1.0 <= record.statistic <= 1.0
    assert "darker than the predicted self-shadowing" in record.reason
    assert fingerprint.names(DECISION) == "shadows"  # a deep shadow is still a shadow


def test_an_albedo_darker_in_concavities_under_any_light_is_not_named(scene):
    """The case built to fool the old share: the albedo darkened by the mesh's occlusion (what
    any light would leave, a texture that is darker in concavities), not by the fitted light's
    shadows. Its slope is as large as a baked shadow's, but placebo lights explain it as well."""
    mesh = scene[0]
    occlusion = vertex_occlusion(mesh.verts, mesh.faces).float()
    fingerprint = fingerprint_with(scene, (1 - occlusion).clamp(min=0.05) ** 2)
    assert fingerprint.slope > DECISION.shadow_share  # the old rule named shadows here
    assert fingerprint.excess < 0 and fingerprint.p_value > 0.1, fingerprint
    assert fingerprint.names(DECISION) is None
    # Not a silent miss: one light cannot tell it from baked shadows, and the verdict says so.
    shadows = Candidate("shadows")
    shadows.add(fingerprint.evidence("shadows").record())
    shadows.add(fingerprint.identifiability("shadows", DECISION))
    decide(shadows, DECISION)
    assert shadows.status == "not_identifiable" and not shadows.significant
    assert "cannot tell apart" in shadows.why and "second, known light" in shadows.why


def test_an_even_light_has_no_placebo_and_names_nothing(scene):
    fingerprint = fingerprint_with(scene, scene[2], Lighting.constant(0.5))
    assert fingerprint.placebo_lights == 0
    record = fingerprint.evidence("shadows").record()
    assert record.statistic != record.statistic  # NaN: not measured
    assert "no dominant direction" in record.reason
    assert fingerprint.names(DECISION) is None


def test_a_convex_mesh_is_not_testable():
    from data_synth.shapes import sphere

    mesh = sphere(resolution=16)
    lighting = sky_and_sun()
    share = vertex_light_visibility(mesh.verts, mesh.faces, lighting)
    assert float(share.min()) > 0.9
    mesh.vertex_colors = torch.full((mesh.verts.shape[0], 3), 0.5)
    cameras = orbit_cameras(4, (32, 32), distance=2.8, fov_x_deg=40, elevation_deg=20)
    output = Renderer().render(mesh, cameras, lighting)
    data = build_diagnosis_data(output.color, output.alpha, output, cameras, lighting, mesh)
    fingerprint = visibility_fingerprint(data, output, SETTINGS)
    assert fingerprint.coverage < DECISION.fingerprint_minimum_coverage
    assert fingerprint.names(DECISION) is None
    assert "not a share of anything" in fingerprint.evidence("shadows").record().reason


def test_partial_correlations_equal_a_column_by_column_least_squares() -> None:
    from recon.diagnose.fingerprint import _partial_correlations

    generator = torch.Generator().manual_seed(3)
    lamberts = torch.rand(4000, 6, generator=generator, dtype=torch.float64)
    features = 0.2 * torch.randn(4000, 6, generator=generator, dtype=torch.float64) + lamberts**2
    target = torch.randn(4000, generator=generator, dtype=torch.float64) + features[:, 1]
    features[:, 5] = 0.7  # a constant share: nothing left once the intercept is out
    expected = []
    for column in range(5):
        lambert = lamberts[:, column]
        nuisance = torch.stack([torch.ones_like(lambert), lambert, lambert**2], 1)
        both = torch.stack([target, features[:, column]], 1)
        rest = both - nuisance @ torch.linalg.lstsq(nuisance, both).solution
        expected.append(float(rest[:, 0] @ rest[:, 1] / rest.norm(dim=0).prod()))
    values = _partial_correlations(target, features, lamberts)
    assert torch.allclose(values[:5], torch.tensor(expected, dtype=torch.float64), atol=1e-9)
    assert float(values[1]) > 3 * float(values[[0, 2, 3, 4]].abs().max())  # it stands out
    assert float(values[5]) == 0.0
    # Gathered a block of rows at a time: the same correlations to rounding.
    blocked = _partial_correlations(target, features, lamberts, rows=700)
    assert torch.allclose(blocked, values, rtol=0, atol=1e-12)


def test_lit_blocks_give_the_correlations_of_the_whole_arrays_bit_for_bit() -> None:
    from recon.diagnose.fingerprint import (
        _correlations_of_blocks,
        _lit_blocks,
        _partial_correlations,
    )

    generator = torch.Generator().manual_seed(5)
    count, lights_count, rows = 3001, 9, 512  # a last block shorter than the others
    normals = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=generator, dtype=torch.float64), dim=1
    )
    lights = torch.nn.functional.normalize(
        torch.randn(lights_count, 3, generator=generator, dtype=torch.float64), dim=1
    )
    log_share = -torch.rand(count, lights_count, generator=generator)  # float32, as rendered
    target = torch.randn(count, generator=generator, dtype=torch.float64)
    lamberts = (normals @ lights.T).clamp(min=0.0)
    plain = _partial_correlations(target, log_share.double(), lamberts, rows=rows)
    first = torch.empty(count, dtype=torch.float64)
    blocks = _lit_blocks(log_share, normals, lights, rows, first_column=first)
    fused = _correlations_of_blocks(target, blocks, lights_count, rows)
    assert torch.equal(fused, plain)
    assert torch.equal(first, lamberts[:, 0])
    assert float(fused.abs().max()) > 0
