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

import math
from dataclasses import dataclass

import torch

from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.data import DiagnosisData, box_erode
from recon.diagnose.records import Evidence
from recon.effects.light_transport import dominant_light, vertex_light_visibility
from recon.effects.registry import effects_with_evidence
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import scatter_to_image
from recon.render.renderer import RenderOutput


@dataclass
class VisibilityFingerprint:
    """share: the share of the predicted self-shadowing baked into the fitted albedo; interval:
    its 90 % block-bootstrap interval; coverage: share of interior pixels the fitted mesh
    shadows by more than 10 %."""

    share: float
    interval: tuple[float, float]
    coverage: float

    def names(self, config: DecisionConfig) -> str | None:
        """The effect the fingerprint names (recon.diagnose.decision's fingerprint row), or
        None: blocked light missing entirely, or partly filled back by bounces."""
        for name in effects_with_evidence("fingerprint"):
            if self.evidence(name).passed_under(config):
                return name
        return None

    def evidence(self, candidate: str) -> FingerprintEvidence:
        return FingerprintEvidence(self, candidate)

    def to_json(self, config: DecisionConfig) -> dict:
        return {
            "share": self.share,
            "interval": list(self.interval),
            "coverage": self.coverage,
            "names": self.names(config),
        }


@dataclass
class FingerprintEvidence:
    """The fingerprint as one candidate's Evidence."""

    fingerprint: VisibilityFingerprint
    candidate: str

    def record(self) -> Evidence:
        return Evidence(
            kind="fingerprint",
            candidate=self.candidate,
            statistic=self.fingerprint.share,
            threshold=math.nan,
            passed=False,
            reason="visibility fingerprint: share of the fitted mesh's self-shadowing baked "
            "into the albedo",
            details={
                "interval": list(self.fingerprint.interval),
                "coverage": self.fingerprint.coverage,
            },
        )

    def passed_under(self, config: DecisionConfig) -> bool:
        from recon.diagnose.decision import rethreshold

        return rethreshold(self.record(), config).passed


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
    # (the 3 x 3 minimum of alpha above 0.999: every pixel of the box above it)
    eroded = box_erode((alpha[:, None] > 0.999).float(), 1)[:, 0]
    return (eroded > 0.5) & (output.albedo.sum(-1) > 1e-4)


def _solve(grams: torch.Tensor, moments: torch.Tensor) -> torch.Tensor:
    """The log-share coefficient [S] of S ridge-stabilised normal equations (grams [S, 16],
    moments [S, 4]): a mesh that shadows nothing gets a zero coefficient, not a singular system."""
    grams = grams.view(-1, 4, 4)
    ridge = 1e-6 * grams.diagonal(dim1=1, dim2=2).mean(-1)[:, None, None] * torch.eye(4)
    return torch.linalg.solve(grams + ridge, moments)[:, 3]


def visibility_fingerprint(
    data: DiagnosisData, output: RenderOutput, settings: DiagnoseConfig, seed: int = 0
) -> VisibilityFingerprint:
    """The visibility fingerprint of the fitted albedo (see the module docstring).

    output: the fitted scene rendered at data's cameras (the probe's base render); settings:
    its block size (diagnose.fingerprint_block_pixels) and bootstrap samples.
    """
    block_pixels = settings.fingerprint_block_pixels
    samples = settings.bootstrap_samples
    signatures = _signatures(data, output)
    interior = _interior(output)
    batch, height, width = interior.shape
    if int(interior.sum()) < 50:
        return VisibilityFingerprint(0.0, (0.0, 0.0), 0.0)
    rows = torch.arange(height) // block_pixels
    columns = torch.arange(width) // block_pixels
    blocks_per_row = (width + block_pixels - 1) // block_pixels
    blocks_per_view = ((height + block_pixels - 1) // block_pixels) * blocks_per_row
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
    picks = torch.randint(0, len(unique_blocks), (samples, len(unique_blocks)), generator=generator)
    counts = torch.zeros(samples, len(unique_blocks), dtype=torch.float64)
    counts.scatter_add_(1, picks, torch.ones_like(picks, dtype=torch.float64))
    ones = torch.ones(1, len(unique_blocks), dtype=torch.float64)
    share = float(_solve(ones @ block_gram.flatten(1), ones @ block_moment)[0])
    values = _solve(counts @ block_gram.flatten(1), counts @ block_moment)
    interval = (float(torch.quantile(values, 0.05)), float(torch.quantile(values, 0.95)))
    return VisibilityFingerprint(share, interval, coverage)
