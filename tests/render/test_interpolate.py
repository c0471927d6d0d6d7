"""interpolate_packed: attributes at covered pixels, all of them or a chosen few."""

from __future__ import annotations

import pytest
import torch

from recon.camera import orbit_cameras
from recon.errors import ReconError
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import rasterize


def _fragments():
    generator = torch.Generator().manual_seed(0)
    verts = torch.randn(30, 3, generator=generator) * 0.6
    faces = torch.randint(0, 30, (40, 3), generator=generator)
    cameras = orbit_cameras(2, (24, 20), distance=3.5)
    return rasterize(cameras.project_to_clip(verts), faces, (24, 20)), faces


@pytest.mark.parametrize("batched_attributes", [False, True])
def test_chosen_pixels_equal_those_pixels_of_the_whole(batched_attributes: bool) -> None:
    fragments, faces = _fragments()
    generator = torch.Generator().manual_seed(1)
    shape = (2, 30, 5) if batched_attributes else (30, 5)
    attributes = torch.randn(*shape, generator=generator)
    whole = interpolate_packed(attributes, fragments, faces)
    pixels = torch.rand(len(fragments.covered_index), generator=generator) < 0.3
    assert 0 < int(pixels.sum()) < len(pixels)
    chosen = interpolate_packed(attributes, fragments, faces, pixels=pixels)
    assert torch.equal(chosen, whole[pixels])


def test_chosen_pixels_must_be_a_mask_over_the_covered_pixels() -> None:
    fragments, faces = _fragments()
    with pytest.raises(ReconError, match="pixels: expected a bool tensor of shape"):
        interpolate_packed(torch.zeros(30, 1), fragments, faces, pixels=torch.tensor([0, 1]))


@pytest.mark.parametrize("batched_attributes", [False, True])
def test_wide_attributes_in_blocks_equal_the_whole_computation(
    batched_attributes: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Wide attributes without a gradient go a block of pixels at a time: the same values,
    bit for bit, as the one-pass computation (taken with a gradient), at chosen pixels too."""
    from recon.render import interpolate

    monkeypatch.setattr(interpolate, "INTERPOLATION_BLOCK_ROWS", 7)
    fragments, faces = _fragments()
    generator = torch.Generator().manual_seed(2)
    shape = (2, 30, interpolate.WIDE_ATTRIBUTES + 3)
    attributes = torch.randn(*(shape if batched_attributes else shape[1:]), generator=generator)
    pixels = torch.rand(len(fragments.covered_index), generator=generator) < 0.5
    for chosen in (None, pixels):
        blocked = interpolate_packed(attributes, fragments, faces, pixels=chosen)
        whole = interpolate_packed(attributes.requires_grad_(), fragments, faces, pixels=chosen)
        attributes = attributes.detach()
        assert len(blocked) > 2 * interpolate.INTERPOLATION_BLOCK_ROWS
        assert whole.requires_grad and not blocked.requires_grad
        assert torch.equal(blocked, whole.detach())
