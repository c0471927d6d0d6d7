"""The report's material figure of a `pbr` fit: every channel the fit has (base colour,
roughness, metalness, the normal map when fitted) and the environment, as panels."""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from recon.optimize.material_stage import PbrTextureResult, light_from_environment
from recon.render.shading import DirectionalLight
from recon.report.material_figure import material_figure, material_panels
from tests.material_scenes import textured_quad


def _result(normal_map: bool) -> PbrTextureResult:
    mesh, maps = textured_quad()
    if normal_map:
        tilt = torch.nn.functional.normalize(torch.tensor([0.6, 0.0, 0.8]), dim=0)
        normals = torch.tensor([0.0, 0.0, 1.0]).expand(8, 8, 3).clone()
        normals[:, 4:] = tilt  # right half tilted toward +u
        maps = torch.cat([maps, normals], dim=-1)
    environment = torch.zeros(4, 8, 3)
    environment[0] = 9.0  # a bright sky row
    return PbrTextureResult(mesh, maps, environment, light_from_environment(environment), 0.5, 4)


def test_panels_show_each_channel_of_the_material_and_the_environment():
    result = _result(normal_map=True)
    panels = material_panels(result)
    titles = [title for title, _, _ in panels]
    assert [title.split(" (")[0] for title in titles] == [
        "base colour",
        "roughness",
        "metalness",
        "normal map",
        "environment",
    ]
    np.testing.assert_allclose(panels[1][1], result.material[..., 0].numpy(), atol=1e-6)
    np.testing.assert_allclose(panels[2][1], result.material[..., 1].numpy(), atol=1e-6)
    assert f"median {float(result.material[..., 0].median()):.2f}" in titles[1]
    # The normal map as normal-map files code it: flat is (0.5, 0.5, 1), a +u tilt is redder.
    normal = panels[3][1]
    np.testing.assert_allclose(normal[0, 0], [0.5, 0.5, 1.0], atol=1e-6)
    np.testing.assert_allclose(normal[0, 7], [0.8, 0.5, 0.9], atol=1e-6)
    # The environment tone-mapped into [0, 1): the bright row up top, black below.
    environment = panels[4][1]
    assert environment.max() < 1 and environment[0].min() > 0.9 and environment[1:].max() == 0


def test_without_a_normal_map_the_figure_has_four_panels(tmp_path):
    assert len(material_panels(_result(normal_map=False))) == 4
    narrow, wide = tmp_path / "four.png", tmp_path / "five.png"
    material_figure(_result(normal_map=False), narrow)
    material_figure(_result(normal_map=True), wide)
    with Image.open(narrow) as four, Image.open(wide) as five:
        assert five.size[0] > 1.15 * four.size[0]


def test_the_roughness_comparison_shows_both_maps_and_their_difference():
    """The same sphere with two UV layouts: the fitted roughness (truth + 0.1) and the true
    one, rendered from one view through their own UVs, differ by 0.1 where both cover."""
    import math

    from recon.camera import Cameras, intrinsics_from_fov, look_at
    from recon.report.material_figure import roughness_comparison_panels
    from tests.material_scenes import unwrapped_sphere

    reference, true_maps = unwrapped_sphere(64)
    fitted, fitted_maps = unwrapped_sphere(48)
    eye = torch.tensor([[3.0 * math.sin(0.4), 0.5, 3.0 * math.cos(0.4)]])
    camera = Cameras(look_at(eye, torch.zeros(1, 3)), intrinsics_from_fov(45.0, (40, 40)), (40, 40))
    shifted = fitted_maps + torch.tensor([0.1, 0.0])
    panels = roughness_comparison_panels(fitted, shifted, reference, true_maps, camera)
    assert [title.split(" (")[0] for title, *_ in panels] == [
        "fitted roughness",
        "true roughness",
        "|fitted - true|",
    ]
    found, true, error = (image for _, image, _, _ in panels)
    covered = ~np.isnan(error)
    assert covered.mean() > 0.2 and np.isnan(found[0, 0]) and np.isnan(true[0, 0])
    # position_material's roughness on the unit sphere spans 0.15 .. 0.45.
    assert 0.14 < np.nanmin(true) and np.nanmax(true) < 0.46 and np.nanmax(true) > 0.35
    # Exact but where a bilinear tap straddles a chart border (95 % within 0.005 measured).
    assert abs(np.median(error[covered]) - 0.1) < 1e-3
    assert np.mean(np.abs(error[covered] - 0.1) < 0.005) > 0.9
    assert np.abs(error[covered] - 0.1).max() < 0.03
    assert "(mean 0.100)" in panels[2][0]


def test_the_environment_panel_shows_the_fits_suns():
    result = _result(normal_map=False)
    plain = material_panels(result)[-1]
    result.suns = [DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.full((3,), 5.0))]
    with_sun = material_panels(result)[-1]
    assert "1 sun(s) added" in with_sun[0] and "sun" not in plain[0]
    # The sun points down, so only the last row (row 0 looks up) brightens.
    assert (with_sun[1][-1] > plain[1][-1] + 0.1).any()
    np.testing.assert_allclose(with_sun[1][:-1], plain[1][:-1], atol=1e-6)
