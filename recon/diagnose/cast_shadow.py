"""Cast-shadow evidence: does the relight split's residual fall where the fitted mesh hides the
relight sun?

Under the training light a cast shadow looks the same from every view: the fit bakes it into
the albedo, and no held-out residual shows it (docs/decisions/0196-diagnosis-light-transport-
lobe.md: the visibility fingerprint sees it mixed with the environment's occlusion and bounced
light, and no threshold on one fit separates them). A relight split is taken under a second,
known light (lighting_relight.json). recon's renderer has no visibility, so a world that casts
shadows leaves, on the relight views, a residual darker than the render exactly where the
fitted mesh shadows the relight sun: the missing term is (1 - V) x the sun's Lambertian light,
V the sun's visibility from the fitted mesh's shadow map. A world without cast shadows leaves
no such pattern, whatever else its fit gets wrong.

The check, on the relight views' interior pixels (N, luminance):

1. the residual r [N] with one gain per view on the render projected out (an exposure);
2. for the relight sun's direction d: the missing shadow f_d = -(1 - V_d) max(0, n.d) x the
   rendered luminance [N] (the render stands in for albedo x irradiance), and its partial
   correlation with r given the unshadowed term max(0, n.d) x the rendered luminance (a sun
   that is only too bright or too dark in the model is not a shadow), both with the per-view
   gains projected out too;
3. its null: the same statistic with the relight sun replaced by placebo directions
   (diagnose.cast_shadow.placebo_lights Fibonacci directions at least
   diagnose.cast_shadow.placebo_separation_degrees away). A residual that is darker in
   concavities (the environment's occlusion, a misfit of the geometry) correlates with the
   shadows of every direction; a cast shadow with its own light's. The statistic is the
   correlation's excess over the placebo directions' 95th percentile; the p-value is the share
   of placebo directions that reach it.

The decision (recon.diagnose.decision, row 'cast_shadow') names the candidate when the excess
clears diagnose.decision.cast_shadow_minimum and p < diagnose.decision.cast_shadow_alpha. The
evidence needs a relight split whose light has a directional sun; without it nothing is
measured (the fingerprint still speaks).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.lobe import (
    LUMINANCE,
    interior_pixels,
    placebo_excess_evidence,
    project_out,
)
from recon.diagnose.pixel_table import view_directions
from recon.diagnose.records import Candidate, Evidence
from recon.effects.light_transport import (
    OrthographicFrames,
    dominant_light,
    fibonacci_directions,
    filtered_visibility,
)
from recon.effects.registry import effects_with_evidence
from recon.mesh.mesh import Mesh

if TYPE_CHECKING:  # producers imports this module to register the producer
    from recon.diagnose.producers import EvidenceInputs

KIND = "cast_shadow"
# Directions whose shadow maps are drawn together (memory, not a tuned number).
DIRECTIONS_PER_CHUNK = 32
# Shadow-map depth test as recon.effects.light_transport.Shadows draws it (texels): a bias of
# 2 + 2 tan(angle to the normal) and a softness of half a texel, so lit surfaces stay lit.
BIAS_TEXELS = 2.0
SLOPE_BIAS_TEXELS = 2.0
SOFTNESS_TEXELS = 0.5


def sun_visibility(
    mesh: Mesh,
    points: torch.Tensor,
    normals: torch.Tensor,
    directions: torch.Tensor,
    resolution: int,
) -> torch.Tensor:
    """Visibility [K, N] in [0, 1] of directional lights along unit world directions [K, 3]
    from surface points [N, 3] with unit normals [N, 3], from shadow maps of the mesh
    (resolution texels a side). No gradient."""
    with torch.no_grad():
        verts = mesh.verts.detach().float()
        rows = []
        for chunk in directions.float().split(DIRECTIONS_PER_CHUNK):
            frames = OrthographicFrames.build(verts, chunk)
            maps = frames.depth_maps(verts, mesh.faces, resolution)
            texel = 2.0 / resolution
            cosine = (normals.float()[None] * chunk[:, None]).sum(-1).clamp(0.05, 1.0)
            slope = torch.sqrt(1 - cosine * cosine) / cosine
            bias = texel * (BIAS_TEXELS + SLOPE_BIAS_TEXELS * slope.clamp(max=10.0))
            softness = torch.tensor(SOFTNESS_TEXELS * texel)
            rows.append(filtered_visibility(maps, frames.to_ndc(points.float()), bias, softness))
        return torch.cat(rows).double()


def _partial_correlation(
    residual: torch.Tensor, feature: torch.Tensor, nuisance: torch.Tensor
) -> tuple[float, float]:
    """(correlation, coefficient) of residual [N] with feature [N] once nuisance [N] is
    regressed out of both."""

    def without(values: torch.Tensor) -> torch.Tensor:
        scale = (nuisance @ values) / (nuisance @ nuisance).clamp_min(1e-30)
        return values - scale * nuisance

    feature, residual = without(feature), without(residual)
    norm = feature.norm().clamp_min(1e-30)
    correlation = float((feature @ residual) / (norm * residual.norm().clamp_min(1e-30)))
    return correlation, float((feature @ residual) / norm**2)


def cast_shadow_statistic(
    relight: DiagnosisData, settings: DiagnoseConfig
) -> dict[str, float | int] | None:
    """The cast-shadow statistic of the relight views (rendered under their own light), its
    placebo-direction null and the recovered share of the sun's light the shadows remove, or
    None when the relight light has no directional sun, turns with the camera, or too few
    pixels are seen. Keys: correlation, p_value, placebo_quantile, placebo_lights, strength
    (the coefficient of the missing-shadow term: about 1 when a hard shadow removes all of the
    sun's light), shadowed (share of pixels facing the sun that the mesh shadows), pixels,
    views."""
    options = settings.cast_shadow
    if relight.lighting.frame == "camera" or not relight.lighting.directional:
        return None
    direction, _ = dominant_light(relight.lighting)
    direction = direction.detach().double().cpu()
    if float(direction.norm()) < 1e-9:
        return None
    direction = direction / direction.norm()
    keep = interior_pixels(relight)
    if int(keep.sum()) < options.minimum_pixels:
        return None
    weights = torch.tensor(LUMINANCE, dtype=torch.float64)
    points, _ = view_directions(relight)
    view = torch.arange(relight.view_count)[:, None, None].expand_as(keep)[keep]
    residual = (relight.residual.double() * weights).sum(-1)[keep]
    rendered = (relight.rendered.double() * weights).sum(-1)[keep]
    normals = torch.nn.functional.normalize(relight.normals.double(), dim=-1)[keep]
    points = points.double()[keep]
    # An even stride through the pixels: the cost is pixels x directions.
    stride = max(1, math.ceil(view.numel() / options.maximum_pixels))
    view, residual, rendered = view[::stride], residual[::stride], rendered[::stride]
    normals, points = normals[::stride], points[::stride]

    placebos = fibonacci_directions(options.placebo_lights).double()
    separation = math.cos(math.radians(options.placebo_separation_degrees))
    placebos = placebos[(placebos @ direction) < separation]
    directions = torch.cat([direction[None], placebos])
    visibility = sun_visibility(relight.mesh, points, normals, directions, options.map_resolution)
    one_cell = torch.zeros_like(view)
    residual = project_out(residual[:, None], one_cell, view, rendered)[:, 0]
    lambert = (normals @ directions.T).clamp_min(0.0) * rendered[:, None]  # [N, K]
    missing = -(1 - visibility.T) * lambert
    projected = project_out(torch.cat([lambert, missing], 1), one_cell, view, rendered)
    count = directions.shape[0]
    scores = [
        _partial_correlation(residual, projected[:, count + k], projected[:, k])
        for k in range(count)
    ]
    correlation, coefficient = scores[0]
    null = torch.tensor([score[0] for score in scores[1:]], dtype=torch.float64)
    facing = (normals @ direction) > 0.1
    shadowed = visibility[0][facing] < 0.5
    return {
        "correlation": correlation,
        "p_value": float((1 + (null >= correlation).sum()) / (1 + null.numel())),
        "placebo_quantile": float(torch.quantile(null, 0.95)) if null.numel() else math.nan,
        "placebo_lights": int(null.numel()),
        "strength": coefficient,
        "shadowed": float(shadowed.double().mean()) if shadowed.numel() else 0.0,
        "pixels": int(view.numel()),
        "views": relight.view_count,
    }


def cast_shadow_evidence(
    relight: DiagnosisData, name: str, settings: DiagnoseConfig
) -> Evidence | None:
    """Whether the relight residual falls where the fitted mesh shadows the relight sun,
    beyond placebo directions (threshold and passed are the decision config's; the decision
    re-derives them); None when it cannot be measured."""
    measured = cast_shadow_statistic(relight, settings)
    if measured is None:
        return None
    decision = settings.decision
    reason = (
        f"{name}: the relight views are darker than the render where the fitted mesh shadows "
        f"the relight sun (r = {measured['correlation']:.3f} over {measured['views']} views, "
        f"p = {measured['p_value']:.2g} against {measured['placebo_lights']} placebo "
        "directions); its excess over the placebo directions' 95th percentile"
    )
    return placebo_excess_evidence(
        KIND,
        name,
        measured,
        decision.cast_shadow_minimum,
        decision.cast_shadow_alpha,
        reason,
        {"strength": measured["strength"]},
    )


def cast_shadow_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Cast-shadow evidence for the candidates whose facts list it (shadows), on the relight
    split (none without one)."""
    names = {candidate.name for candidate in candidates}
    wanted = [name for name in effects_with_evidence(KIND) if name in names]
    if not settings.cast_shadow.enabled or not wanted or inputs.relight is None:
        return []
    evidence = [cast_shadow_evidence(inputs.relight, name, settings) for name in wanted]
    return [item for item in evidence if item is not None]
