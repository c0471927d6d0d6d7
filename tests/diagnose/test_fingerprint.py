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
from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.fingerprint import visibility_fingerprint
from recon.effects.light_transport import vertex_light_visibility
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SIZE = 64
DECISION = DecisionConfig()
SETTINGS = DiagnoseConfig()


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
    return visibility_fingerprint(data, output, SETTINGS)


def test_the_torus_shadows_itself(scene):
    _, _, share, _, _ = scene
    assert float(share.min()) < 0.7 and float(share.max()) > 0.99


def test_clean_albedo_has_no_fingerprint(scene):
    fingerprint = fingerprint_of(scene, 0.0)
    assert fingerprint.coverage >= DECISION.fingerprint_minimum_coverage
    assert abs(fingerprint.share) < 0.1, fingerprint
    assert fingerprint.names(DECISION) is None


def test_baked_shadows_are_named_shadows(scene):
    fingerprint = fingerprint_of(scene, 1.0)
    assert fingerprint.share == pytest.approx(1.0, abs=0.15), fingerprint
    assert fingerprint.interval[0] > DECISION.visibility_share_minimum
    assert fingerprint.names(DECISION) == "shadows"


def test_partly_filled_shadows_are_named_interreflection(scene):
    fingerprint = fingerprint_of(scene, 0.4)
    assert fingerprint.share == pytest.approx(0.4, abs=0.12), fingerprint
    assert fingerprint.share < DECISION.shadow_share
    assert fingerprint.names(DECISION) == "interreflection"


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
    fingerprint = visibility_fingerprint(data, output, SETTINGS)
    assert fingerprint.coverage < DECISION.fingerprint_minimum_coverage
    assert fingerprint.names(DECISION) is None
