"""The bounce evidence (recon.diagnose.bounce): relight views that carry the relight sun's
diffuse bounce light, which recon's renderer leaves out, are named interreflection; nothing
else is.

The world here is built apart from the evidence's own ray casting: its bounce is a brute-force
vertex-to-face form factor sum (no visibility, cosine-culled), its training light's bounce is
baked into the fitted albedo as a fit would bake it. Built to fool the evidence: views brighter
in the mesh's concavities whatever the sun (a misfit or an albedo that follows the occlusion),
views darker there (an albedo darker in the concavity, no bounce light) and noise alone.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
import trimesh

from recon.camera import orbit_cameras
from recon.config.run_config import BounceConfig, DiagnoseConfig
from recon.diagnose.bounce import (
    Light,
    Receivers,
    bounce_evidence,
    face_albedo,
    face_normals,
    first_hits,
    penumbra_suns,
)
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.decision import decide
from recon.diagnose.lobe import interior_pixels
from recon.diagnose.pixel_table import view_directions
from recon.diagnose.records import Candidate
from recon.effects.light_transport import fibonacci_directions, vertex_occlusion
from recon.mesh.mesh import Mesh, vertex_normals
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import scatter_to_image
from recon.render.renderer import Renderer
from recon.render.shading import DirectionalLight, Lighting

SETTINGS = DiagnoseConfig(bounce=BounceConfig(directions=32, cells=12, placebo_lights=40))
TRAINING_SUN = (0.6, 0.6, 0.6)
# Lights the inner face of wall A (normal +x), not wall B's (normal +z): A bounces onto B.
RELIGHT_SUN = (1.0, 0.5, -0.1)


def a_corner() -> tuple[Mesh, object]:
    """Two walls meeting at a right angle (inner faces x = -0.5 and z = -0.5), colourful,
    seen from 6 views at 32 x 32: (mesh, cameras)."""
    first = trimesh.creation.box(extents=[0.1, 1.2, 1.2])
    first.apply_translation([-0.55, 0.0, 0.0])
    second = trimesh.creation.box(extents=[1.1, 1.2, 0.1])
    second.apply_translation([0.05, 0.0, -0.55])
    merged = trimesh.util.concatenate(
        [first.subdivide().subdivide(), second.subdivide().subdivide()]
    )
    verts = torch.tensor(merged.vertices, dtype=torch.float32)
    colours = 0.6 + 0.15 * torch.stack(
        [
            torch.sin(4 * verts[:, 1]),
            torch.cos(3 * verts[:, 0] + verts[:, 2]),
            torch.sin(2 * verts[:, 2]),
        ],
        -1,
    )
    mesh = Mesh(verts, torch.tensor(merged.faces), vertex_colors=colours)
    return mesh, orbit_cameras(6, (32, 32), distance=3.2, elevation_deg=30)


def _sun_light(direction: tuple[float, float, float], ambient: float) -> Lighting:
    lighting = Lighting.constant(ambient)
    toward = torch.nn.functional.normalize(torch.tensor(direction), dim=0)
    lighting.directional.append(DirectionalLight(toward, torch.tensor([2.5, 2.5, 2.5])))
    return lighting


def _irradiance(mesh: Mesh, points: torch.Tensor, normals: torch.Tensor, lighting: Lighting):
    """(with the mesh's visibility, without) [N]: the direct irradiance of lighting at surface
    points [N, 3] with normals [N, 3], the visibility ray cast as the evidence casts it (the
    world's direct light is the evidence's nuisance, projected out; its bounce is what is
    tested, and that is computed apart, in world_bounce)."""
    directions = fibonacci_directions(SETTINGS.bounce.directions).double()
    receivers = Receivers.cast(mesh, points, normals, directions, SETTINGS.bounce.cells)
    light = Light.of(lighting, directions)
    return receivers.irradiance(light, receivers.sun_visible(mesh, light.sun_directions, 12))


def world_bounce(mesh: Mesh, radiosity: torch.Tensor) -> torch.Tensor:
    """One-bounce irradiance [V] at each vertex from the vertices' radiosity [V]: sum over
    faces of J / pi cos cos / r^2 A (a vertex-to-face form factor, no visibility)."""
    verts, faces = mesh.verts.double(), mesh.faces
    corners = verts[faces]
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * cross.norm(dim=-1)
    face_normals = torch.nn.functional.normalize(cross, dim=-1)
    centres = corners.mean(dim=1)
    normals = vertex_normals(mesh.verts, faces).double()
    offset = centres[None] - verts[:, None]  # [V, F, 3]
    distance = offset.norm(dim=-1).clamp_min(1e-6)
    direction = offset / distance[..., None]
    leaving = (direction * normals[:, None]).sum(-1).clamp_min(0)
    arriving = -(direction * face_normals[None]).sum(-1)
    factor = leaving * arriving.clamp_min(0) * area / (math.pi * distance**2)
    return (factor * radiosity.double()[faces].mean(dim=1)).sum(dim=1)


def _per_pixel(values: torch.Tensor, mesh: Mesh, output, views: int) -> torch.Tensor:
    fragments = output.fragments
    packed = interpolate_packed(values[:, None].float(), fragments, mesh.faces)
    height, width = fragments.resolution
    return scatter_to_image(packed, fragments.covered_index, views, height, width)


def _fitted(mesh: Mesh, albedo: torch.Tensor, training: Lighting, bounce: bool) -> Mesh:
    """The model a fit under the training light ends with: its albedo holds the training
    light's visibility (and its bounce, in a world with interreflection)."""
    normals = vertex_normals(mesh.verts, mesh.faces).double()
    visible, total = _irradiance(mesh, mesh.verts.double(), normals, training)
    baked = visible + (world_bounce(mesh, albedo * visible) if bounce else 0.0)
    colours = (albedo * baked / total).float()[:, None].expand(-1, 3)
    return Mesh(mesh.verts, mesh.faces, vertex_colors=colours)


@pytest.fixture(scope="module")
def scene():
    mesh, cameras = a_corner()
    return mesh, cameras, mesh.vertex_colors.mean(dim=-1).double()


def _turned(direction: tuple[float, float, float], degrees: float) -> tuple[float, float, float]:
    """direction turned by degrees about the vertical axis (y)."""
    angle = math.radians(degrees)
    x, y, z = direction
    return (
        x * math.cos(angle) + z * math.sin(angle),
        y,
        -x * math.sin(angle) + z * math.cos(angle),
    )


def _views(
    scene,
    bounce: float = 0.0,
    darker: float = 0.0,
    brighter: float = 0.0,
    seed=0,
    sun_error_degrees: float = 0.0,
):
    """Relight views of the world (its direct light with the mesh's visibility, plus bounce x
    its one-bounce light) against the model fitted in that world, under the relight light.
    darker: the world's albedo is (1 - darker x the mesh's occlusion) times the scene's (the fit
    learns it); brighter: the relight views are (1 + brighter x the occlusion) times brighter, a
    pattern that follows the concavities whatever the sun; sun_error_degrees: the world's relight
    sun stands this far from the declared one (its shading and shadow edges move). Returns
    (views, training light)."""
    mesh, cameras, albedo = scene
    occlusion = vertex_occlusion(mesh.verts, mesh.faces).double()
    albedo = albedo * (1 - darker * occlusion)
    training = _sun_light(TRAINING_SUN, 0.3)
    fitted = _fitted(mesh, albedo, training, bounce != 0)
    relight = _sun_light(RELIGHT_SUN, 0.25)
    world_light = _sun_light(_turned(RELIGHT_SUN, sun_error_degrees), 0.25)
    views = len(cameras)
    normals = vertex_normals(mesh.verts, mesh.faces).double()
    with torch.no_grad():
        output = Renderer().render(fitted, cameras, relight)
        world = Mesh(mesh.verts, mesh.faces, vertex_colors=albedo.float()[:, None].expand(-1, 3))
        lit = Renderer().render(world, cameras, world_light).color
        keep = output.fragments.tri_id >= 0
        points, _ = view_directions(
            build_diagnosis_data(lit, output.alpha, output, cameras, relight, world)
        )
        visible, total = _irradiance(
            mesh, points.double()[keep], output.normals.double()[keep], world_light
        )
        share = torch.zeros(keep.shape, dtype=torch.float64)
        share[keep] = visible / total.clamp_min(1e-12)
        observed = lit * share[..., None].float()
        if bounce:
            visible, _ = _irradiance(mesh, mesh.verts.double(), normals, world_light)
            light = albedo * world_bounce(mesh, albedo * visible)
            observed = observed + bounce * _per_pixel(light, mesh, output, views)
        if brighter:
            observed = observed * (1 + brighter * _per_pixel(occlusion, mesh, output, views))
    generator = torch.Generator().manual_seed(seed)
    observed = observed + 0.003 * torch.randn(observed.shape, generator=generator)
    data = build_diagnosis_data(observed, output.alpha, output, cameras, relight, fitted)
    return data, training


def _decided(data, training) -> Candidate:
    candidate = Candidate("interreflection")
    candidate.add(bounce_evidence(data, training, "interreflection", SETTINGS))
    return decide(candidate, SETTINGS.decision)


def test_first_hits_agree_with_brute_force(scene):
    mesh = scene[0]
    generator = torch.Generator().manual_seed(3)
    origins = torch.rand(300, 3, generator=generator, dtype=torch.float64) * 1.6 - 0.8
    directions = torch.nn.functional.normalize(
        torch.randn(5, 3, generator=generator, dtype=torch.float64), dim=-1
    )
    hits = first_hits(mesh.verts, mesh.faces, origins, directions, cells=16)
    corners = mesh.verts.double()[mesh.faces]  # Moeller-Trumbore against every face
    edge_one, edge_two = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    for k, direction in enumerate(directions):
        normal = torch.linalg.cross(direction.expand_as(edge_two), edge_two)
        det = (edge_one * normal).sum(-1)
        offset = origins[:, None] - corners[None, :, 0]
        u = (offset * normal).sum(-1) / det
        q = torch.linalg.cross(offset, edge_one.expand_as(offset))
        v = (q * direction).sum(-1) / det
        t = (q * edge_two).sum(-1) / det
        inside = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (det.abs() > 1e-12)
        t = torch.where(inside, t, torch.full_like(t, math.inf))
        nearest, face = t.min(dim=1)
        expected = torch.where(torch.isfinite(nearest), face, torch.full_like(face, -1))
        agree = (hits[k] == expected).double().mean()
        assert agree > 0.98, (k, float(agree))
        assert (expected >= 0).any() and (expected < 0).any()


def test_the_predicted_bounce_is_the_worlds(scene):
    # The evidence's one bounce (ray-cast gathering from the faces) against the world's
    # (vertex-to-face form factors, coarse near the walls' shared edge), both under the
    # relight light, at the relight pixels.
    data, _ = _views(scene)
    mesh, cameras, albedo = scene
    keep = interior_pixels(data)
    directions = fibonacci_directions(128).double()  # the gathering's sampling, finer
    points, _ = view_directions(data)
    pixels = Receivers.cast(
        mesh, points.double()[keep], data.normals.double()[keep], directions, 12
    )
    verts = mesh.verts.double()
    surface = Receivers.cast(
        mesh, verts[mesh.faces].mean(dim=1), face_normals(verts, mesh.faces), directions, 12
    )
    light = Light.of(data.lighting, directions)
    lit, _ = surface.irradiance(light, surface.sun_visible(mesh, light.sun_directions, 12))
    predicted = pixels.bounce(face_albedo(mesh) * lit)
    normals = vertex_normals(mesh.verts, mesh.faces).double()
    visible, _ = _irradiance(mesh, verts, normals, data.lighting)
    output = Renderer().render(mesh, cameras, data.lighting)
    world = _per_pixel(world_bounce(mesh, albedo * visible), mesh, output, len(cameras))
    world = world[..., 0][keep].double()
    correlation = torch.corrcoef(torch.stack([predicted, world]))[0, 1]
    assert correlation > 0.85, float(correlation)
    assert 0.7 < float(predicted.mean() / world.mean()) < 1.4


def test_the_relight_suns_bounce_is_measured_with_its_strength(scene):
    candidate = _decided(*_views(scene, bounce=1.0))
    measured = candidate.evidence_of("bounce").details
    # The residual follows the predicted bounce, at about the one bounce the world holds. (Its
    # significance against placebo suns is weak here: a sun turned 45 degrees that still
    # lights wall A predicts nearly the same pattern; docs/decisions/0210.)
    assert measured["correlation"] > 0.5, measured
    assert 0.5 < measured["strength"] < SETTINGS.decision.bounce_maximum_strength, measured


def test_an_albedo_darker_in_the_concavity_is_not_bounce(scene):
    candidate = _decided(*_views(scene, darker=0.6))
    assert not candidate.significant, candidate.why


def test_concavities_brighter_whatever_the_sun_are_not_bounce(scene):
    candidate = _decided(*_views(scene, brighter=0.4))
    assert not candidate.significant, candidate.why


def test_noise_alone_gives_nothing_and_no_sun_no_evidence(scene):
    candidate = _decided(*_views(scene, seed=1))
    assert not candidate.significant, candidate.why
    data, training = _views(scene)
    data.lighting = Lighting.constant(0.5)  # no directional sun: nothing to test against
    assert bounce_evidence(data, training, "interreflection", SETTINGS) is None


def test_a_strength_no_bounce_can_have_is_not_named(scene):
    candidate = _decided(*_views(scene, bounce=8.0))
    measured = candidate.evidence_of("bounce").details
    assert measured["strength"] > SETTINGS.decision.bounce_maximum_strength, measured
    assert not candidate.significant, candidate.why


def test_the_producer_is_registered_and_reads_the_relight_split_only(scene):
    from recon.diagnose.bounce import bounce_producer
    from recon.diagnose.data import FittedModel
    from recon.diagnose.producers import PRODUCERS, EvidenceInputs

    assert bounce_producer in PRODUCERS
    relight, training = _views(scene, bounce=1.0)
    model = FittedModel(relight.mesh, training)
    candidates = [Candidate("interreflection"), Candidate("exposure")]
    without = EvidenceInputs(relight, None, None, None, model)
    assert bounce_producer(without, candidates, SETTINGS) == []
    inputs = EvidenceInputs(relight, None, None, None, model, relight=relight)
    evidence = bounce_producer(inputs, candidates, SETTINGS)
    assert [(item.candidate, item.kind) for item in evidence] == [("interreflection", "bounce")]
    disabled = replace(SETTINGS, bounce=replace(SETTINGS.bounce, enabled=False))
    assert bounce_producer(inputs, candidates, disabled) == []


def test_penumbra_suns_turn_the_sun_by_the_pixel_footprint_over_the_radius(scene):
    data, _ = _views(scene)
    sun = torch.nn.functional.normalize(torch.tensor(RELIGHT_SUN, dtype=torch.float64), dim=0)
    assert penumbra_suns(data, sun, 0.0).shape == (0, 3)
    one, two = penumbra_suns(data, sun, 1.0), penumbra_suns(data, sun, 2.0)
    assert one.shape == (4, 3)
    torch.testing.assert_close(one.norm(dim=-1), torch.ones(4, dtype=torch.float64))
    verts = data.mesh.verts.double()
    center = (verts.min(0).values + verts.max(0).values) / 2
    radius = float((verts - center).norm(dim=-1).max())
    distance = (data.cameras.centers().double() - center).norm(dim=-1)
    footprint = float((distance / data.cameras.intrinsics[:, 0, 0].double()).median())
    angles = torch.rad2deg(torch.arccos((one @ sun).clamp(max=1.0)))
    expected = math.degrees(math.atan(footprint / radius))
    torch.testing.assert_close(angles, torch.full((4,), expected, dtype=torch.float64))
    # Four sides: opposite turns cancel; twice the pixels, about twice the angle.
    torch.testing.assert_close(torch.nn.functional.normalize(one.sum(0), dim=0), sun)
    assert 1.9 < float(torch.arccos((two @ sun).clamp(max=1.0))[0] / math.radians(expected)) < 2.1


PENUMBRA = replace(SETTINGS, bounce=replace(SETTINGS.bounce, penumbra_pixels=1.0))


def test_a_relight_sun_a_few_pixels_off_is_not_bounce_with_the_penumbra_nuisance(scene):
    # The world's sun stands 4 degrees (about 2 pixel footprints) from the declared one: its
    # shading and shadow edges move. The point sun's nuisance leaves that to the bounce (it
    # follows it beyond the placebos); the turned suns' columns take it.
    data, training = _views(scene, sun_error_degrees=4.0)
    point_sun = bounce_evidence(data, training, "interreflection", SETTINGS)
    turned = bounce_evidence(data, training, "interreflection", PENUMBRA)
    assert point_sun.statistic > 0.0 and point_sun.details["p_value"] < 0.05, point_sun.details
    assert turned.statistic < 0.0, turned.details
    candidate = Candidate("interreflection")
    candidate.add(turned)
    assert not decide(candidate, PENUMBRA.decision).significant
    # With the bounce on top, the bounce is still measured through the nuisance.
    bounced, training = _views(scene, bounce=1.0, sun_error_degrees=4.0)
    measured = bounce_evidence(bounced, training, "interreflection", PENUMBRA).details
    assert measured["correlation"] > 0.5, measured
