"""Absorption fingerprint: what missing light visibility leaves in the fitted albedo.

Under one light, a cast shadow, a concavity that sees less of the sky, or the light bounced
back into it look the same from every view, so the fit bakes them into the texture and no probe
on the frozen scene can see them (the held-out residual does not change). What they leave is a
fingerprint: the fitted albedo is darker exactly where the fitted mesh hides its own light. The
true albedo knows nothing of the lighting geometry.

The model predicts the self-shadowing itself: per vertex, the share of the fitted light's
irradiance the fitted mesh does not block (recon.effects.light_transport.vertex_light_visibility,
SH environment sampled along 64 directions plus any directional light). Per covered interior
pixel of the held-out renders (the fitted scene only; no observed pixel is used), the log
luminance of the fitted albedo y is compared with the log visible share x, given [1, L, L^2],
L = max(0, n.l) toward the dominant fitted light (a light that is slightly off is held fixed):

- the statistic is the partial correlation of y and x (bounded, -1..1);
- its null comes from the run itself: the same partial correlation with the fitted light turned
  so that its dominant direction points elsewhere (diagnose.fingerprint.placebo_lights Fibonacci
  directions at least placebo_separation_degrees away; environment and suns turned together,
  recon.effects.light_transport.rotated_light_visibility). A texture that is darker in
  concavities, or a fitted mesh whose concavities are wrong, correlates with the self-shadowing
  of every such light; a baked shadow with its own light's. The evidence is the correlation's
  excess over the placebo lights' 95th percentile, with the share of placebo lights that reach
  it as p-value (recon.diagnose.lobe.placebo_excess_evidence, like the lobe and cast-shadow
  evidence). Under an even light (no dominant direction) every placebo light is the light
  itself: nothing is testable, and the evidence says so.
- the slope of y on x (a block bootstrap, 8 x 8 pixel blocks across views, gives its interval)
  says how much darker: 1 when the albedo holds all of the predicted self-shadowing, 0 when none;
  it is not a share of anything when the predicted self-shadowing barely varies (coverage) or is
  weaker than the baked one (then it exceeds 1), and the reason line says which. The reported
  share is the slope clipped to its meaning, 0..1.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import torch

from recon.config.run_config import DecisionConfig, DiagnoseConfig
from recon.diagnose.data import DiagnosisData, box_erode
from recon.diagnose.records import Evidence
from recon.effects.light_transport import (
    dominant_light,
    fibonacci_directions,
    rotated_light_visibility,
    rotation_between,
)
from recon.effects.registry import effects_with_evidence
from recon.render.interpolate import interpolate_packed
from recon.render.rasterize import scatter_to_image
from recon.render.renderer import RenderOutput

KIND = "fingerprint"
# Rec. 709 luminance weights of the albedo's log luminance.
LUMINANCE = (0.2126, 0.7152, 0.0722)
# A pixel counts as shadowed by the fitted mesh below this predicted visible share (coverage).
SHADOWED_SHARE = 0.9
# Rows of the [N, 1 + K] pixel x light arrays gathered per pass of the partial correlations
# (a cache-sized block; memory, not a tuned number: every block size gives the same sums).
ROWS_PER_PASS = 512


@dataclass
class VisibilityFingerprint:
    """The fingerprint of one fitted albedo.

    slope: the log-log slope of the albedo on the predicted visible share (unbounded);
    interval: its 90 % block-bootstrap interval; coverage: share of interior pixels the fitted
    mesh shadows by more than 10 %; correlation: the partial correlation of the two (-1..1);
    placebo_quantile: the placebo lights' 95th percentile of it; p_value: the share of placebo
    lights reaching it; placebo_lights: how many were tried (0: an even light, none).
    """

    slope: float
    interval: tuple[float, float]
    coverage: float
    correlation: float = 0.0
    placebo_quantile: float = math.nan
    p_value: float = 1.0
    placebo_lights: int = 0
    pixels: int = 0
    placebo_correlations: list[float] = field(default_factory=list, repr=False)

    @property
    def share(self) -> float:
        """The share of the predicted self-shadowing baked into the albedo: the slope clipped
        to 0..1 (a slope outside it is reported as what it is, see slope_note)."""
        return min(1.0, max(0.0, self.slope))

    @property
    def excess(self) -> float:
        """The correlation's excess over the placebo lights' 95th percentile (NaN without
        placebo lights)."""
        return self.correlation - self.placebo_quantile

    def slope_note(self, minimum_coverage: float) -> str:
        """What the slope means here, in words."""
        if self.coverage < minimum_coverage:
            return (
                f"the fitted mesh shadows {self.coverage:.1%} of the pixels: the slope "
                f"{self.slope:.2f} is not a share of anything"
            )
        if self.slope > 1:
            return (
                f"slope {self.slope:.2f}: the albedo is darker than the predicted self-shadowing "
                "alone would make it (the fitted mesh or light predicts weaker shadows than the "
                "baked ones), so all of it counts (share 1)"
            )
        if self.slope < 0:
            return f"slope {self.slope:.2f}: the albedo is brighter where the light is blocked"
        return f"share {self.share:.2f} of the predicted self-shadowing baked into the albedo"

    def names(self, config: DecisionConfig) -> str | None:
        """The effect the fingerprint names (recon.diagnose.decision's fingerprint row), or
        None: blocked light missing entirely, or partly filled back by bounces."""
        for name in effects_with_evidence(KIND):
            if self.evidence(name).passed_under(config):
                return name
        return None

    def evidence(self, candidate: str) -> FingerprintEvidence:
        return FingerprintEvidence(self, candidate)

    def identifiability(self, candidate: str, config: DecisionConfig) -> Evidence | None:
        """A failed identifiability condition when the albedo holds a self-shadowing pattern
        (the slope's bootstrap interval above 0) that placebo lights explain as well as the
        fitted one (p at or above fingerprint_alpha): baked light transport of this light, or
        an albedo or fitted mesh that is darker in concavities under any light, which one light
        cannot tell apart. None when the fingerprint is untestable, shows no such pattern, or
        beats its placebo lights."""
        testable = self.placebo_lights > 0 and self.coverage >= config.fingerprint_minimum_coverage
        if not testable or self.interval[0] <= 0 or self.p_value < config.fingerprint_alpha:
            return None
        return Evidence(
            kind="identifiability",
            candidate=candidate,
            statistic=self.p_value,
            threshold=math.nan,
            passed=False,
            reason=(
                f"the fitted albedo is darker where the fitted mesh hides light (slope "
                f"{self.slope:.2f}, interval {self.interval[0]:.2f} to {self.interval[1]:.2f}) "
                f"and as much under placebo lights turned elsewhere (p = {self.p_value:.2g} "
                f"against {self.placebo_lights}): baked light transport or an albedo darker in "
                "concavities, which one light cannot tell apart"
            ),
            details={
                "capture": "views under a second, known light whose sun the object shadows "
                "itself (a relight split)",
                # the relight split's evidences measure under that second light
                "settled_by": ["cast_shadow", "relight", "bounce"],
                "slope": self.slope,
                "interval": list(self.interval),
                "p_value": self.p_value,
            },
        )

    def to_json(self, config: DecisionConfig) -> dict:
        return {
            "share": self.share,
            "slope": self.slope,
            "interval": list(self.interval),
            "coverage": self.coverage,
            "correlation": self.correlation,
            "placebo_quantile": self.placebo_quantile,
            "excess": self.excess,
            "p_value": self.p_value,
            "placebo_lights": self.placebo_lights,
            "names": self.names(config),
        }


@dataclass
class FingerprintEvidence:
    """The fingerprint as one candidate's Evidence (statistic: the placebo excess; NaN when no
    placebo light exists, which the decision reads as not testable)."""

    fingerprint: VisibilityFingerprint
    candidate: str

    def record(self, minimum_coverage: float | None = None) -> Evidence:
        fingerprint = self.fingerprint
        if minimum_coverage is None:
            minimum_coverage = DecisionConfig().fingerprint_minimum_coverage
        if fingerprint.placebo_lights == 0:
            measured = "no placebo light: the fitted light has no dominant direction"
        else:
            measured = (
                f"r = {fingerprint.correlation:.3f}, p = {fingerprint.p_value:.2g} against "
                f"{fingerprint.placebo_lights} placebo lights"
            )
        reason = (
            f"{self.candidate}: the fitted albedo is darker where the fitted mesh hides the "
            f"fitted light ({measured}; {fingerprint.slope_note(minimum_coverage)}); its excess "
            "over the placebo lights' 95th percentile"
        )
        return Evidence(
            kind=KIND,
            candidate=self.candidate,
            statistic=fingerprint.excess if fingerprint.placebo_lights else math.nan,
            threshold=math.nan,
            passed=False,
            reason=reason,
            details={
                "share": fingerprint.share,
                "slope": fingerprint.slope,
                "interval": list(fingerprint.interval),
                "coverage": fingerprint.coverage,
                "correlation": fingerprint.correlation,
                "placebo_quantile": fingerprint.placebo_quantile,
                "p_value": fingerprint.p_value,
                "placebo_lights": fingerprint.placebo_lights,
                "pixels": fingerprint.pixels,
            },
        )

    def passed_under(self, config: DecisionConfig) -> bool:
        from recon.diagnose.decision import rethreshold

        return rethreshold(self.record(config.fingerprint_minimum_coverage), config).passed


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


def _placebo_rotations(direction: torch.Tensor, count: int, separation_degrees: float):
    """Rotations [1 + K, 3, 3] (the identity first) that turn the dominant direction [3] onto
    the Fibonacci directions at least separation_degrees from it."""
    targets = fibonacci_directions(count)
    targets = targets[(targets @ direction) < math.cos(math.radians(separation_degrees))]
    rotations = [torch.eye(3, dtype=torch.float64)]
    rotations += [rotation_between(direction, target) for target in targets]
    return torch.stack(rotations)


def _partial_correlations(
    target: torch.Tensor, features: torch.Tensor, lamberts: torch.Tensor, rows: int = ROWS_PER_PASS
) -> torch.Tensor:
    """Partial correlation [K] of target [N] with each feature column [N, K] given
    [1, L_k, L_k^2] of its own lambert column [N, K].

    From the normal equations: the residuals' inner products after projecting out the nuisance
    are the raw ones less m^T G^-1 m (G the nuisance's 3 x 3 Gram matrix, m its moments with
    target and feature). The sums they need are gathered a block of rows at a time, so the
    [rows, K] temporaries stay in cache (one pass over the [N, K] inputs)."""
    blocks = (
        (features[start : start + rows], lamberts[start : start + rows])
        for start in range(0, features.shape[0], rows)
    )
    return _correlations_of_blocks(target, blocks, features.shape[1], rows, features.dtype)


def _lit_blocks(
    log_share: torch.Tensor,
    normals: torch.Tensor,
    lights: torch.Tensor,
    rows: int = ROWS_PER_PASS,
    first_column: torch.Tensor | None = None,
) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """The features and lambert columns of _partial_correlations a block of rows at a time:
    (log_share[rows].double() [rows, K], (normals[rows] @ lights.T).clamp(min=0) [rows, K])
    from log_share [N, K] (float32), normals [N, 3] and lights [K, 3] (float64), so the two
    [N, K] float64 arrays (hundreds of MB at 384 px with 175 lights) are never formed: each
    element is the same conversion and the same three-term product as in the whole arrays.
    first_column: [N] float64, filled with the lambert column of the first light as the blocks
    go by (a product with that light alone would take another kernel, rounded otherwise)."""
    for start in range(0, log_share.shape[0], rows):
        lambert = (normals[start : start + rows] @ lights.T).clamp(min=0.0)
        if first_column is not None:
            first_column[start : start + rows] = lambert[:, 0]
        yield log_share[start : start + rows].double(), lambert


def _correlations_of_blocks(
    target: torch.Tensor,
    blocks: Iterable[tuple[torch.Tensor, torch.Tensor]],
    columns: int,
    rows: int,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """_partial_correlations from its (features, lamberts) blocks of `rows` rows, in order."""
    # Per column: sums of L^1..L^4, target L, target L^2, F, F L, F L^2, target F, F^2.
    sums = torch.zeros(11, columns, dtype=dtype, device=target.device)
    for index, (feature, lambert) in enumerate(blocks):
        start = index * rows
        part = target[start : start + rows]
        square = lambert * lambert
        sums += torch.stack(
            [
                lambert.sum(0),
                square.sum(0),
                (square * lambert).sum(0),
                (square * square).sum(0),
                part @ lambert,
                part @ square,
                feature.sum(0),
                (feature * lambert).sum(0),
                (feature * square).sum(0),
                part @ feature,
                (feature * feature).sum(0),
            ]
        )
    count = torch.full_like(sums[0], float(len(target)))
    power_sums = torch.cat([count[None], sums[:4]])  # [5, C]: sum of L^p for p = 0..4
    index = torch.arange(3)
    gram = power_sums[index[:, None] + index[None, :]].permute(2, 0, 1)  # [C, 3, 3]
    # the moments of target and feature with [1, L, L^2]
    target_moments = torch.stack([target.sum().expand(columns), sums[4], sums[5]], 1)
    feature_moments = torch.stack([sums[6], sums[7], sums[8]], 1)
    moments = torch.stack([target_moments, feature_moments], 2)  # [C, 3, 2]
    scale = gram.diagonal(dim1=1, dim2=2).mean(-1)[:, None, None]
    coefficients = torch.linalg.solve(
        gram + 1e-12 * scale * torch.eye(3, dtype=gram.dtype), moments
    )
    explained = moments.transpose(1, 2) @ coefficients  # [C, 2, 2]
    cross = sums[9]
    raw = torch.stack(
        [
            torch.stack([(target @ target).expand_as(cross), cross], 1),
            torch.stack([cross, sums[10]], 1),
        ],
        1,
    )  # [C, 2, 2]
    rest = raw - explained
    variances = rest.diagonal(dim1=1, dim2=2).clamp(min=0.0)
    norms = variances.sqrt()
    # A column the nuisance explains to rounding (a constant share: a convex mesh) has no
    # residual to correlate; the subtraction above leaves only cancellation noise there.
    degenerate = (variances <= 1e-9 * raw.diagonal(dim1=1, dim2=2)).any(1)
    correlation = rest[:, 0, 1] / (norms[:, 0] * norms[:, 1]).clamp_min(1e-300)
    return torch.where(degenerate, torch.zeros_like(correlation), correlation)


def _bootstrap_slope(
    design: torch.Tensor,
    target: torch.Tensor,
    block: torch.Tensor,
    samples: int,
    seed: int,
) -> tuple[float, tuple[float, float]]:
    """The log-share slope and its block-bootstrap 90 % interval.

    Normal equations per block; a bootstrap sample of blocks is then a count-weighted sum of
    them (the same as repeating the blocks' rows), solved for all samples at once."""
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
    slope = float(_solve(ones @ block_gram.flatten(1), ones @ block_moment)[0])
    values = _solve(counts @ block_gram.flatten(1), counts @ block_moment)
    return slope, (float(torch.quantile(values, 0.05)), float(torch.quantile(values, 0.95)))


def visibility_fingerprint(
    data: DiagnosisData, output: RenderOutput, settings: DiagnoseConfig, seed: int = 0
) -> VisibilityFingerprint:
    """The visibility fingerprint of the fitted albedo (see the module docstring).

    output: the fitted scene rendered at data's cameras (the probe's base render); settings:
    its block size (diagnose.fingerprint_block_pixels), bootstrap samples and placebo lights
    (diagnose.fingerprint).
    """
    options = settings.fingerprint
    interior = _interior(output)
    batch, height, width = interior.shape
    if int(interior.sum()) < 50:
        return VisibilityFingerprint(0.0, (0.0, 0.0), 0.0)
    direction, irradiance = dominant_light(data.lighting)
    direction = direction.detach().double().cpu()
    even = float(direction.norm()) < 1e-9 or float(irradiance.detach().abs().max()) < 1e-9
    if even:
        rotations = torch.eye(3, dtype=torch.float64)[None]
    else:
        direction = direction / direction.norm()
        rotations = _placebo_rotations(
            direction, options.placebo_lights, options.placebo_separation_degrees
        )
    with torch.no_grad():
        shares = rotated_light_visibility(
            data.mesh.verts, data.mesh.faces, data.lighting, rotations
        )
        log_shares = shares.clamp(min=0.02).log().T.to(output.color)  # [V, 1 + K]
        fragments = output.fragments
        # Interior pixels are covered ones, and covered_index is in raster order, so the
        # covered pixels picked by interior's mask come in that mask's order.
        picked = interior.reshape(-1)[fragments.covered_index]
        if int(picked.sum()) == int(interior.sum()):
            log_share = interpolate_packed(log_shares, fragments, data.mesh.faces, pixels=picked)
        else:
            packed = interpolate_packed(log_shares, fragments, data.mesh.faces)
            per_pixel = scatter_to_image(packed, fragments.covered_index, batch, height, width)
            log_share = per_pixel[interior]
        # log_share: [N, 1 + K] in the render's precision; converted a block at a time below.
        dominant_share = log_share[:, 0].double()  # [N]
        normals = output.normals[interior].double()
        lights = torch.einsum("rde,e->rd", rotations, direction if not even else rotations[0, 1])
    albedo = (output.albedo[interior].double() * torch.tensor(LUMINANCE, dtype=torch.float64)).sum(
        -1
    )
    target = torch.log(albedo.clamp_min(1e-3))
    coverage = float((dominant_share < math.log(SHADOWED_SHARE)).double().mean())

    block_pixels = settings.fingerprint_block_pixels
    rows = torch.arange(height) // block_pixels
    columns = torch.arange(width) // block_pixels
    blocks_per_row = (width + block_pixels - 1) // block_pixels
    blocks_per_view = ((height + block_pixels - 1) // block_pixels) * blocks_per_row
    block = rows[:, None] * blocks_per_row + columns[None, :]
    block = (block[None] + torch.arange(batch)[:, None, None] * blocks_per_view)[interior]
    # Every light's lambert column is formed a block of rows at a time (_lit_blocks), the
    # dominant light's kept for the slope's design.
    lambert = torch.empty(len(target), dtype=torch.float64)  # [N]
    blocks = _lit_blocks(log_share, normals, lights, ROWS_PER_PASS, first_column=lambert)
    correlations = _correlations_of_blocks(target, blocks, log_share.shape[1], ROWS_PER_PASS)
    design = torch.stack([torch.ones_like(lambert), lambert, lambert * lambert, dominant_share], 1)
    slope, interval = _bootstrap_slope(design, target, block, settings.bootstrap_samples, seed)
    null = correlations[1:]
    correlation = float(correlations[0])
    if null.numel() == 0:
        return VisibilityFingerprint(
            slope, interval, coverage, correlation, pixels=int(target.numel())
        )
    return VisibilityFingerprint(
        slope,
        interval,
        coverage,
        correlation,
        placebo_quantile=float(torch.quantile(null, 0.95)),
        p_value=float((1 + (null >= correlation).sum()) / (1 + null.numel())),
        placebo_lights=int(null.numel()),
        pixels=int(target.numel()),
        placebo_correlations=[float(value) for value in null],
    )
