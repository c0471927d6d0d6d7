"""DiagnosisData: the region is the object plus a band, and shapes are checked by name."""

from __future__ import annotations

import pytest
import torch
from diagnose_where_scene import make_scene

from recon.diagnose.data import DiagnosisData
from recon.errors import ReconError


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def test_region_is_the_object_plus_a_band(scene):
    data = scene.data(scene.output.color)
    covered = scene.output.alpha[..., 0] > 0.5
    region = data.region[..., 0] > 0.5
    assert bool(region[covered].all())
    # Chebyshev distance to the object: <= 3 pixels inside the band, farther outside it.
    distance = torch.full_like(covered, False)
    grown = covered.float()[:, None]
    for band in range(1, 6):
        grown = torch.nn.functional.max_pool2d(grown, 3, stride=1, padding=1)
        ring = (grown[:, 0] > 0.5) & ~distance & ~covered
        if band <= 3:
            assert bool(region[ring].all())
        else:
            assert not bool(region[ring].any())
        distance |= ring
    uv = data.texel_uv
    assert bool((uv[data.rendered_mask] >= 0).all()) and bool((uv[data.rendered_mask] <= 1).all())
    assert bool((uv[~data.rendered_mask] == -1).all())


def test_diagnosis_data_checks_shapes(scene):
    data = scene.data(scene.output.color)
    with pytest.raises(ReconError, match="diagnosis_data.rendered"):
        DiagnosisData(
            observed=data.observed,
            rendered=data.rendered[:, :-1],
            observed_alpha=data.observed_alpha,
            rendered_alpha=data.rendered_alpha,
            region=data.region,
            normals=data.normals,
            depth=data.depth,
            texel_uv=data.texel_uv,
            triangle_id=data.triangle_id,
            cameras=data.cameras,
            lighting=data.lighting,
            mesh=data.mesh,
        )


@pytest.mark.parametrize("radius", [0, 1, 3, 4])
def test_box_dilation_and_erosion_equal_the_max_pool_they_replace(radius):
    from recon.diagnose.data import box_dilate, box_erode

    generator = torch.Generator().manual_seed(radius)
    # sparse and dense masks, touching the border
    for density in (0.05, 0.7):
        mask = (torch.rand(3, 1, 21, 17, generator=generator) < density).float()
        size = 2 * radius + 1
        pooled = torch.nn.functional.max_pool2d(mask, size, stride=1, padding=radius)
        eroded = -torch.nn.functional.max_pool2d(-mask, size, stride=1, padding=radius)
        assert torch.equal(box_dilate(mask, radius), pooled)
        assert torch.equal(box_erode(mask, radius), eroded)


def test_views_rendered_once_are_the_batched_render_and_its_output():
    """render_views_once (one batch, the render kept for the EffectProbe) gives the same data
    as render_diagnosis_data's batches of VIEWS_PER_BATCH: a view's render does not depend on
    the views beside it."""
    from diagnose_scenes import patterned_torus

    from recon.camera import orbit_cameras
    from recon.diagnose.data import (
        VIEWS_PER_BATCH,
        FittedModel,
        render_diagnosis_data,
        render_views_once,
    )
    from recon.io.datasets import CaptureSet
    from recon.render.shading import Lighting

    mesh = patterned_torus((2, 3), 0.25, lambda p: [p, 0.7 * p + 0.2, 0.5 * (1 - p) + 0.2])
    views = VIEWS_PER_BATCH + 2
    cameras = orbit_cameras(views, (24, 24), distance=2.0, fov_x_deg=60, elevation_deg=35)
    images = torch.rand(views, 24, 24, 3, generator=torch.Generator().manual_seed(0))
    masks = torch.ones(views, 24, 24, 1)
    captures = CaptureSet(cameras, images, masks, [str(i) for i in range(views)], "test")
    model = FittedModel(mesh, Lighting.constant(0.9))
    batched = render_diagnosis_data(captures, model, "cpu", 2)
    once, output = render_views_once(captures, model, 2)
    for name in ("observed", "rendered", "rendered_alpha", "region", "normals", "depth"):
        assert torch.equal(getattr(once, name), getattr(batched, name)), name
    assert torch.equal(once.texel_uv, batched.texel_uv)
    assert torch.equal(once.triangle_id, batched.triangle_id)
    assert once.names == batched.names and once.split == "test"
    assert torch.equal(output.color, once.rendered)
