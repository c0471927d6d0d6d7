"""Which effect: the probe finds a per-view exposure change, and conditioning on it stops a
look-alike (white balance) from riding along, while an effect that really is there on top
(a defocus blur) survives the conditioning. (Only candidates significant on their own are
re-probed; a second effect hidden entirely behind the first is the absorption refits' job.)"""

from __future__ import annotations

import torch
from diagnose_scenes import patterned_torus

from recon.camera import orbit_cameras
from recon.config.run_config import DecisionConfig
from recon.diagnose.data import build_diagnosis_data
from recon.diagnose.decision import decide
from recon.diagnose.records import Candidate
from recon.diagnose.which import (
    EffectProbe,
    conditional_probes,
    conditioning_effect,
    probe_effect,
    probe_evidence,
    rank_candidates,
)
from recon.effects import make_effect
from recon.effects.forward import apply_camera_effects
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

SIZE = 48
VIEWS = 16


def observed_scene(blur: bool):
    mesh = patterned_torus((3, 2), 0.3, lambda p: [p, 0.8 * p + 0.1, 0.6 * (1 - p) + 0.2])
    cameras = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.4, fov_x_deg=45, elevation_deg=30)
    lighting = Lighting.constant(0.8)
    output = Renderer(texture_filter="linear").render(mesh, cameras, lighting)
    generator = torch.Generator().manual_seed(0)
    gains = torch.exp(0.3 * torch.randn(VIEWS, generator=generator))
    observed = output.color * gains[:, None, None, None]
    if blur:
        effect = make_effect("defocus_blur")
        with torch.no_grad():
            for parameter in effect.parameters():
                parameter.fill_(3.0)
            observed, _ = effect(observed, output.alpha, cameras, torch.arange(VIEWS))
    observed = observed + 0.002 * torch.randn(observed.shape, generator=generator)
    return build_diagnosis_data(observed, output.alpha, output, cameras, lighting, mesh)


def by_name(ranking: list[Candidate]) -> dict[str, Candidate]:
    return {candidate.name: candidate for candidate in ranking}


def test_conditioning_removes_a_look_alike():
    data = observed_scene(blur=False)
    ranking = rank_candidates(data, ["exposure", "white_balance", "defocus_blur"])
    assert ranking[0].name == "exposure" and ranking[0].significant
    assert conditioning_effect(ranking) == "exposure"
    conditional_probes(ranking, EffectProbe(data), "exposure")
    results = by_name(ranking)
    assert results["exposure"].significant and results["exposure"].conditional_on is None
    assert not results["white_balance"].significant
    assert results["white_balance"].evidence_of("probe").details["reduction"] < 0.02


def test_a_real_second_effect_survives_the_conditioning():
    data = observed_scene(blur=True)
    ranking = rank_candidates(data, ["exposure", "defocus_blur"])
    assert conditioning_effect(ranking) == "exposure"
    assert by_name(ranking)["defocus_blur"].significant
    conditional_probes(ranking, EffectProbe(data), "exposure")
    blur = by_name(ranking)["defocus_blur"]
    assert blur.conditional_on == "exposure"
    assert blur.significant, blur


def test_the_pose_probe_warp_follows_a_re_render():
    # The pose probe warps the cached render along each pixel's flow instead of rasterising
    # again: exact at zero, and close to a real re-render for a small correction.
    data = observed_scene(blur=False)
    probe = EffectProbe(data)
    pose = probe_effect("pose_error", VIEWS, torch.device("cpu"))
    torch.testing.assert_close(probe.render(pose), probe.base_output.color, atol=1e-5, rtol=0)
    with torch.no_grad():
        pose.rotation.copy_(torch.tensor([0.004, 0.012, -0.006]).expand(VIEWS, 3))
    warped = probe.render(pose)
    moved = apply_camera_effects([pose], data.cameras, torch.arange(VIEWS))
    with torch.no_grad():
        rendered = probe.renderer.render(data.mesh, moved, data.lighting).color
    change = (rendered - probe.base_output.color).abs().mean()
    error = (rendered - warped).abs().mean()
    assert change > 0.005
    assert error < 0.35 * change, (float(error), float(change))


def test_only_a_probe_decided_top_effect_conditions():
    def candidate(name, evidence):
        result = Candidate(name, significant=bool(evidence), decided_by=evidence)
        result.add(probe_evidence(name, 0.5, (0.4, 0.6), {}))
        return result

    assert conditioning_effect([candidate("pose_error", "probe")]) == "pose_error"
    # A global blur too: motion blur, distortion and pose refinement all imitate part of it.
    assert conditioning_effect([candidate("defocus_blur", "probe")]) == "defocus_blur"
    assert conditioning_effect([candidate("vignetting", "absorption")]) is None
    assert conditioning_effect([candidate("exposure", "")]) is None


def test_probe_evidence_is_decided_from_the_config():
    candidate = Candidate("exposure")
    candidate.add(probe_evidence("exposure", 0.5, (0.4, 0.6), {"ratios": [1.0, 1.2]}, score=0.3))
    decide(candidate, DecisionConfig())
    assert candidate.significant and candidate.parameters == {"ratios": [1.0, 1.2]}
    assert not decide(candidate, DecisionConfig(minimum_share=0.5)).significant


def test_pixel_packing_round_trips_the_chosen_pixels():
    from recon.diagnose.which import PixelPacking

    generator = torch.Generator().manual_seed(1)
    image = torch.rand(3, 5, 4, 2, generator=generator)
    index = torch.tensor([0, 7, 19, 25, 26, 45, 59])  # views 0, 1 and 2 (20 pixels each)
    packing = PixelPacking(index, (3, 5, 4))
    packed = packing.pack(image)
    assert packed.shape == (3, 3, 1, 2)  # view 0 holds three of the pixels, the most
    assert torch.equal(packing.unpack(packed), image.reshape(-1, 2)[index])


def test_counted_render_of_pixelwise_effects_is_the_full_render_at_the_counted_pixels():
    from recon.diagnose.gauss_newton import GaussNewtonProblem
    from recon.diagnose.which import block_halves

    data = observed_scene(blur=False)
    probe = EffectProbe(data)
    generator = torch.Generator().manual_seed(2)
    effects = [probe_effect(name, VIEWS, "cpu") for name in ("exposure", "response_curve")]
    with torch.no_grad():
        for parameter in (p for effect in effects for p in effect.parameters()):
            parameter.copy_(0.2 * torch.randn(parameter.shape, generator=generator))
    first, _ = block_halves(VIEWS, SIZE, SIZE, "cpu", 4)
    weight = first * data.region
    render = probe.counted_render(effects, weight)
    problem = GaussNewtonProblem(effects, lambda: probe.render(effects), data.observed, weight)
    with torch.no_grad():
        full = problem.counted(probe.render(effects))
    assert torch.allclose(render(), full, rtol=1e-6, atol=1e-7)
    # Vignetting depends on where a pixel is: no shortcut.
    assert probe.counted_render([probe_effect("vignetting", VIEWS, "cpu")], weight) is None


def test_counted_render_of_a_warp_or_a_distortion_is_the_full_render_at_the_counted_pixels():
    """A pose correction (the cached render warped) and a lens distortion (the image
    resampled), alone or followed by pixelwise effects, are sampled at the counted pixels
    only: the full render's values there, bit for bit."""
    from recon.diagnose.gauss_newton import counted_pixels
    from recon.diagnose.which import block_halves

    data = observed_scene(blur=False)
    probe = EffectProbe(data)
    first, _ = block_halves(VIEWS, SIZE, SIZE, "cpu", 4)
    weight = first * data.region
    index = counted_pixels(weight, data.observed.shape)
    generator = torch.Generator().manual_seed(4)
    for names in (
        ("pose_error",),
        ("lens_distortion",),
        ("pose_error", "exposure"),
        ("response_curve", "lens_distortion", "white_balance"),  # applied in IMAGE_ORDER
    ):
        effects = [probe_effect(name, VIEWS, "cpu") for name in names]
        with torch.no_grad():
            for parameter in (p for effect in effects for p in effect.parameters()):
                parameter.copy_(0.05 * torch.randn(parameter.shape, generator=generator))
        render = probe.counted_render(effects, weight)
        assert render is not None, names
        with torch.no_grad():
            full = probe.render(effects).reshape(-1, 3).index_select(0, index)
            counted = render()
        assert float((full - data.observed.reshape(-1, 3)[index]).abs().max()) > 0
        assert torch.equal(counted, full), names
    # A blur, or a pixelwise effect before a distortion, needs the whole image.
    blurred = [probe_effect(name, VIEWS, "cpu") for name in ("defocus_blur", "lens_distortion")]
    assert probe.counted_render(blurred, weight) is None
    both = [probe_effect(name, VIEWS, "cpu") for name in ("pose_error", "lens_distortion")]
    assert probe.counted_render(both, weight) is None
