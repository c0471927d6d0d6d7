"""Absorption fingerprint: what missing light visibility leaves in the fitted albedo.

Under one light, a cast shadow, a concavity that sees less of the sky, or the light bounced
back into it look the same from every view, so the fit bakes them into the texture and no probe
on the frozen scene can see them (the held-out residual does not change). What they leave is a
fingerprint: the fitted albedo is darker exactly where the fitted mesh hides its own light. The
true albedo knows nothing of the lighting geometry, so on a correct fit the fitted mesh's
self-shadowing explains none of it.

The model predicts the self-shadowing itself: per vertex, the share of the fitted light's
irradiance the fitted mesh does not block (recon.effects.light_transport.vertex_light_visibility,
SH environment sampled along 64 directions plus any directional light). Per covered interior
pixel of the held-out renders (the fitted scene only; no observed pixel is used), the log
luminance of the fitted albedo is regressed on [1, L, L^2, log visible share], L = max(0, n.l)
toward the dominant fitted light (so a light that is slightly off is held fixed). The last
coefficient is the share of the predicted self-shadowing the fit baked into its albedo:
about 0 on a correct fit, near 1 when blocked light is missing from the model (shadows), and in
between when bounced light fills part of it back (interreflection: about 1 - albedo of it
remains). A block bootstrap (8 x 8 pixel blocks across views) gives its interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.diagnose.calibration import SHADOW_SHARE, VISIBILITY_SHARE_MINIMUM
from recon.diagnose.data import DiagnosisData
from recon.effects.light_transport import dominant_light, vertex_light_visibility
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import scatter_to_image
from recon.render.renderer import RenderOutput

FINGERPRINT_EFFECTS = ("shadows", "interreflection")
BLOCK_PIXELS = 8
BOOTSTRAP_SAMPLES = 400
# The self-shadowing must matter (visible share below 0.9) on this share of the interior
# pixels for the fingerprint to be testable at all.
MINIMUM_COVERAGE = 0.02


@dataclass
class VisibilityFingerprint:
    """share: the share of the predicted self-shadowing baked into the fitted albedo; interval:
    its 90 % block-bootstrap interval; coverage: share of interior pixels the fitted mesh
    shadows by more than 10 %."""

    share: float
    interval: tuple[float, float]
    coverage: float

    @property
    def testable(self) -> bool:
        return self.coverage >= MINIMUM_COVERAGE

    @property
    def significant(self) -> bool:
        return self.testable and self.interval[0] > VISIBILITY_SHARE_MINIMUM

    @property
    def effect(self) -> str | None:
        """The effect the fingerprint names when significant: blocked light missing entirely
        (shadows) or partly filled back by bounces (interreflection)."""
        if not self.significant:
            return None
        return "shadows" if self.share >= SHADOW_SHARE else "interreflection"

    def to_json(self) -> dict:
        return {
            "share": self.share,
            "interval": list(self.interval),
            "coverage": self.coverage,
            "names": self.effect,
        }


def _signatures(data: DiagnosisData, output: RenderOutput) -> dict[str, torch.Tensor]:
    """Per-pixel [B, H, W] signatures and the fitted albedo's log luminance."""
    direction, _ = dominant_light(data.lighting)
    direction = direction.to(output.color)
    with torch.no_grad():
        cosine = (output.normals * direction).sum(-1).clamp(min=0.0)
        share = vertex_light_visibility(data.mesh.verts, data.mesh.faces, data.lighting)
        log_share = share.clamp(min=0.02).log().to(output.color)
        fragments = output.fragments
        packed = interpolate_packed(log_share[:, None], fragments, data.mesh.faces)
        batch = fragments.batch_size
        height, width = fragments.resolution
        visible = scatter_to_image(packed, fragments.covered_index, batch, height, width)[..., 0]
    weights = torch.tensor([0.2126, 0.7152, 0.0722], dtype=output.albedo.dtype)
    luminance = (output.albedo * weights).sum(-1)
    return {
        "log_albedo": torch.log(luminance.clamp_min(1e-3)),
        "lambert": cosine,
        "log_visible_share": visible.to(cosine),
    }


def _interior(output: RenderOutput) -> torch.Tensor:
    """[B, H, W] bool: fully covered pixels with a real albedo (silhouettes left out)."""
    alpha = output.alpha[..., 0]
    eroded = -torch.nn.functional.max_pool2d(-alpha[:, None], 3, stride=1, padding=1)[:, 0]
    return (eroded > 0.999) & (output.albedo.sum(-1) > 1e-4)


def _solve(grams: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """The log-share coefficient [S] of S ridge-stabilised normal equations (grams [S, 16],
    moments [S, 4]): a mesh that shadows nothing gets a zero coefficient, not a singular system."""
    grams = grams.view(-1, 4, 4)
    ridge = 1e-6 * grams.diagonal(dim1=1, dim2=2).mean(-1)[:, None, None] * torch.eye(4)
    return torch.linalg.solve(grams + ridge, moments)[:, 3]


def visibility_fingerprint(
    data: DiagnosisData, output: RenderOutput, seed: int = 0
) -> VisibilityFingerprint:
    """The visibility fingerprint of the fitted albedo (see the module docstring).

    output: the fitted scene rendered at data's cameras (the probe's base render).
    """
    signatures = _signatures(data, output)
    interior = _interior(output)
    batch, height, width = interior.shape
    if int(interior.sum()) < 50:
        return VisibilityFingerprint(0.0, (0.0, 0.0), 0.0)
    rows = torch.arange(height) // BLOCK_PIXELS
    columns = torch.arange(width) // BLOCK_PIXELS
    blocks_per_row = (width + BLOCK_PIXELS - 1) // BLOCK_PIXELS
    blocks_per_view = ((height + BLOCK_PIXELS - 1) // BLOCK_PIXELS) * blocks_per_row
    block = rows[:, None] * blocks_per_row + columns[None, :]
    block = (block[None] + torch.arange(batch)[:, None, None] * blocks_per_view)[interior]
    lambert = signatures["lambert"][interior].double()
    log_share = signatures["log_visible_share"][interior].double()
    design = torch.stack([torch.ones_like(lambert), lambert, lambert * lambert, log_share], 1)
    target = signatures["log_albedo"][interior].double()
    coverage = float((log_share < torch.log(torch.tensor(0.9))).double().mean())

    # Normal equations per 8 x 8 block; a bootstrap sample of blocks is then a count-weighted
    # sum of them (the same as repeating the blocks' rows), solved for all samples at once.
    unique_blocks, inverse = torch.unique(block, return_inverse=True)
    outer = design[:, :, None] * design[:, None, :]  # [N, 4, 4]
    block_gram = torch.zeros(len(unique_blocks), 4, 4, dtype=torch.float64)
    block_gram.index_add_(0, inverse, outer)
    block_moment = torch.zeros(len(unique_blocks), 4, dtype=torch.float64)
    block_moment.index_add_(0, inverse, design * target[:, None])
    generator = torch.Generator().manual_seed(seed)
    picks = torch.randint(
        0, len(unique_blocks), (BOOTSTRAP_SAMPLES, len(unique_blocks)), generator=generator
    )
    counts = torch.zeros(BOOTSTRAP_SAMPLES, len(unique_blocks), dtype=torch.float64)
    counts.scatter_add_(1, picks, torch.ones_like(picks, dtype=torch.float64))
    ones = torch.ones(1, len(unique_blocks), dtype=torch.float64)
    share = float(_solve(ones @ block_gram.flatten(1), ones @ block_moment)[0])
    values = _solve(counts @ block_gram.flatten(1), counts @ block_moment)
    interval = (float(torch.quantile(values, 0.05)), float(torch.quantile(values, 0.95)))
    return VisibilityFingerprint(share, interval, coverage)
