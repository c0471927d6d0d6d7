"""ModelEffect.pixelwise: an effect that says so maps each pixel by its view's parameters alone,
so applying it to a subset of a view's pixels, packed in any arrangement, gives the full image's
values there (the diagnosis' probes render only the pixels they count)."""

from __future__ import annotations

import pytest
import torch

from recon.camera import orbit_cameras
from recon.effects.registry import MODEL_EFFECTS, make_effect

VIEWS, SIZE = 3, 12
PIXELWISE = sorted(name for name, effect in MODEL_EFFECTS.items() if effect.pixelwise)


def test_the_photometric_gains_and_curve_are_pixelwise():
    assert set(PIXELWISE) == {"exposure", "white_balance", "response_curve"}


@pytest.mark.parametrize("name", PIXELWISE)
def test_a_pixelwise_effect_on_a_packed_subset_gives_the_full_image_there(name):
    generator = torch.Generator().manual_seed(4)
    effect = make_effect(name, view_count=VIEWS, pinned_view=None)
    with torch.no_grad():
        for parameter in effect.parameters():
            parameter.copy_(0.2 * torch.randn(parameter.shape, generator=generator))
    color = torch.rand(VIEWS, SIZE, SIZE, 3, generator=generator)
    alpha = torch.ones(VIEWS, SIZE, SIZE, 1)
    cameras = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.0, fov_x_deg=45)
    with torch.no_grad():
        full, _ = effect(color, alpha, cameras, None)
        # Each view keeps 7 of its pixels, in a shuffled order, as a [B, 7, 1, C] batch.
        picks = torch.stack(
            [torch.randperm(SIZE * SIZE, generator=generator)[:7] for _ in range(VIEWS)]
        )
        views = torch.arange(VIEWS)[:, None]
        packed_color = color.reshape(VIEWS, -1, 3)[views, picks][:, :, None]
        packed_alpha = alpha.reshape(VIEWS, -1, 1)[views, picks][:, :, None]
        packed, _ = effect(packed_color, packed_alpha, cameras, None)
    expected = full.reshape(VIEWS, -1, 3)[views, picks]
    assert torch.allclose(packed[:, :, 0], expected, rtol=1e-6, atol=1e-7)
    assert not torch.allclose(expected, color.reshape(VIEWS, -1, 3)[views, picks])
