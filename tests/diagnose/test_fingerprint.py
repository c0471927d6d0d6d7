"""The visibility fingerprint: self-shadowing baked into a fitted albedo is measured, named
shadows when it is whole and interreflection when bounced light filled part of it back, and an
albedo with no baked shadowing gives nothing. The "fitted" albedo here is built by hand from a
random pattern and the mesh's own predicted visible share."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from data_synth.shapes import torus
from recon.camera import orbit_cameras
from recon.diagnose.calibration import (
    MINIMUM_SHARE,
    PROBE_ALLOWANCE,
    SHADOW_SHARE,
    VISIBILITY_SHARE_MINIMUM,
    probe_threshold,
)
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.fingerprint import visibility_fingerprint
from recon.diagnose.which import CandidateResult
from recon.effects.light_transport import vertex_light_visibility
from recon.effects.registry import MODEL_EFFECTS
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SIZE = 64


@pytest.fixture(scope="module")
def scene():
    """A torus lying in the x-z plane (its inner ring shadows itself) under sky + sun."""
    torch.set_num_threads(1)
    mesh = torus(resolution=32)
    lighting = Lighting.constant(0.3)
    lighting.directional = [
        DirectionalLight(torch.tensor([0.3, 0.9, 0.2]), torch.tensor([2.0, 2.0, 2.0]))
    ]
    share = vertex_light_visibility(mesh.verts, mesh.faces, lighting).float()
    generator = torch.Generator().manual_seed(0)
    # A blotchy albedo that knows nothing of the lighting: two levels on a random vertex field.
    pattern = torch.rand(mesh.verts.shape[0], 1, generator=generator)
    base = torch.where(pattern > 0.5, 0.7, 0.35) * torch.tensor([[1.0, 0.9, 0.8]])
    cameras = orbit_cameras(8, (SIZE, SIZE), distance=2.8, fov_x_deg=40, elevation_deg=35)
    return mesh, lighting, share, base, cameras


def fingerprint_of(scene, baked_exponent: float):
    """The fingerprint of an albedo with share^exponent of the self-shadowing baked in."""
    mesh, lighting, share, base, cameras = scene
    fitted = replace(mesh, vertex_colors=base * share[:, None] ** baked_exponent, texture=None)
    output = Renderer().render(fitted, cameras, lighting)
    data = build_diagnosis_data(output.color, output.alpha, output, cameras, lighting, fitted)
    return visibility_fingerprint(data, output)


def test_the_torus_shadows_itself(scene):
    _, _, share, _, _ = scene
    assert float(share.min()) < 0.7 and float(share.max()) > 0.99


def test_clean_albedo_has_no_fingerprint(scene):
    fingerprint = fingerprint_of(scene, 0.0)
    assert fingerprint.testable
    assert abs(fingerprint.share) < 0.1, fingerprint
    assert not fingerprint.significant and fingerprint.effect is None


def test_baked_shadows_are_named_shadows(scene):
    fingerprint = fingerprint_of(scene, 1.0)
    assert fingerprint.share == pytest.approx(1.0, abs=0.15), fingerprint
    assert fingerprint.interval[0] > VISIBILITY_SHARE_MINIMUM
    assert fingerprint.effect == "shadows"


def test_partly_filled_shadows_are_named_interreflection(scene):
    fingerprint = fingerprint_of(scene, 0.4)
    assert fingerprint.share == pytest.approx(0.4, abs=0.12), fingerprint
    assert fingerprint.share < SHADOW_SHARE
    assert fingerprint.effect == "interreflection"


def test_a_convex_mesh_is_not_testable():
    from data_synth.shapes import sphere

    mesh = sphere(resolution=16)
    lighting = Lighting.constant(1.0)
    share = vertex_light_visibility(mesh.verts, mesh.faces, lighting)
    assert torch.allclose(share, torch.ones_like(share), atol=0.02)
    mesh.vertex_colors = torch.full((mesh.verts.shape[0], 3), 0.5)
    cameras = orbit_cameras(4, (32, 32), distance=2.8, fov_x_deg=40, elevation_deg=20)
    output = Renderer().render(mesh, cameras, lighting)
    data = build_diagnosis_data(output.color, output.alpha, output, cameras, lighting, mesh)
    fingerprint = visibility_fingerprint(data, output)
    assert not fingerprint.testable and fingerprint.effect is None


def test_every_effect_has_an_allowance_at_least_the_minimum():
    assert set(PROBE_ALLOWANCE) == set(MODEL_EFFECTS)
    for effect in MODEL_EFFECTS:
        assert probe_threshold(effect) >= MINIMUM_SHARE


def test_ranking_puts_residual_evidence_before_the_fingerprint():
    def candidate(name, reduction, significant, evidence, share=0.0):
        return CandidateResult(
            effect=name,
            score=0.0,
            heldout_reduction=reduction,
            interval=(0.0, 0.0),
            significant=significant,
            evidence=evidence,
            fingerprint={"share": share} if evidence == "fingerprint" else None,
        )

    ranking = [
        candidate("shadows", 0.0, True, "fingerprint", share=0.8),
        candidate("pose_error", 0.3, False, ""),
        candidate("specular", 0.2, True, "probe"),
    ]
    ranking.sort(key=CandidateResult.rank_key, reverse=True)
    assert [item.effect for item in ranking] == ["specular", "shadows", "pose_error"]
