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

V comes from two occluders: the fitted mesh's shadow map and the observed silhouettes' visual
hull (SilhouetteHull). A short fit at 48 px drops thin parts (the teapot's spout and handle,
spot's ears: the fitted meshes shadow 1-2 % of the sun-facing surface where the true ones
shadow 9-12 %), while every view's mask still holds them. Each direction's statistic is the
larger correlation of the two, for the relight sun and every placebo direction alike
(docs/decisions/0211-shadows-specular-mitsuba.md). Where an occluder shadows the relight sun,
the relight split has tested the shadows: the fingerprint's "one light cannot tell" condition
is void (answered_condition).

The decision (recon.diagnose.decision, row 'cast_shadow') names the candidate when the excess
clears diagnose.decision.cast_shadow_minimum and p < diagnose.decision.cast_shadow_alpha. The
evidence needs a relight split whose light has a directional sun; without it nothing is
measured (the fingerprint still speaks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from recon.camera import Cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData
from recon.diagnose.lobe import (
    LUMINANCE,
    divide_view_gains,
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
from recon.optimize.visual_hull import border_share, carve

if TYPE_CHECKING:  # producers imports this module to register the producer
    from recon.diagnose.producers import EvidenceInputs

KIND = "cast_shadow"
# How the reason names each occluder, with its verb.
OCCLUDER_PHRASES = {
    "fitted mesh": "the fitted mesh shadows",
    "silhouettes": "the observed silhouettes' hull shadows",
}
# Directions whose shadow maps are drawn together (memory, not a tuned number).
DIRECTIONS_PER_CHUNK = 32
# Points marched through the silhouette hull together (memory, not a tuned number).
POINTS_PER_MARCH = 1024
# Most voxels a side of the silhouette hull (memory: a high-resolution capture's pixel footprint
# would ask for billions of voxels; at 48 px the grid is 45-60 a side).
MAXIMUM_HULL_RESOLUTION = 160
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


@dataclass(frozen=True)
class SilhouetteHull:
    """The observed silhouettes' visual hull as an occupancy grid: an occluder for the cast
    shadows that holds the object's thin parts (a spout, a handle, legs, ears), which a short
    fit at 48 px shrinks or drops while every view's mask still shows them. A superset of the
    object (concavities no silhouette sees into stay filled).

    occupancy: [R, R, R] bool over the cube center + [-radius, radius]^3 (index order x, y, z).
    """

    occupancy: torch.Tensor
    center: torch.Tensor
    radius: float

    @classmethod
    def carve(
        cls,
        views: list[tuple[Cameras, torch.Tensor]],
        mesh: Mesh,
        voxel_pixels: float,
        margin: float,
    ) -> SilhouetteHull | None:
        """The hull of every (cameras, masks [B, H, W, 1]) set, intersected, on a grid around
        the fitted mesh (its half extent x margin) whose voxel is voxel_pixels of the views'
        median pixel footprint at the object (finer voxels than the masks resolve carve their
        aliasing into the hull); None when the masks do not bound the object (occupied grid
        border, e.g. masks that are all 1) or carve everything away."""
        verts = mesh.verts.detach().float().cpu()
        center = (verts.min(0).values + verts.max(0).values) / 2
        radius = float((verts - center).abs().max()) * margin
        footprints = torch.cat(
            [
                (cameras.centers().float().cpu() - center).norm(dim=-1)
                / cameras.intrinsics[:, 0, 0].float().cpu()
                for cameras, _ in views
            ]
        )
        voxel = voxel_pixels * float(footprints.median())
        resolution = min(MAXIMUM_HULL_RESOLUTION, max(8, math.ceil(2 * radius / voxel)))
        occupancy = None
        with torch.no_grad():
            for cameras, masks in views:
                carved, _ = carve(
                    cameras.to("cpu"),
                    masks.detach().float().cpu(),
                    resolution,
                    radius,
                    center=center,
                )
                occupancy = carved if occupancy is None else occupancy * carved
        if occupancy is None or float(occupancy.sum()) == 0 or border_share(occupancy) > 0:
            return None
        return cls(occupancy.bool(), center, radius)

    def visibility(self, points: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """Visibility [K, N] in {0, 1} of directional lights along unit directions [K, 3] from
        surface points [N, 3]: a point is shadowed when the ray toward the light leaves the
        hull and enters it again. A fitted surface point lies inside the hull or near its skin,
        so the first stretch inside is its own body, not an occluder. Marched at half a voxel
        (the hull's resolution) until the ray leaves the grid; no gradient."""
        resolution = self.occupancy.shape[0]
        # One free voxel of padding on every side: samples outside the grid read it (clamped).
        padded = torch.nn.functional.pad(self.occupancy, (1, 1, 1, 1, 1, 1)).flatten()
        side = resolution + 2
        step = 0.5 / resolution  # half a voxel, in grid units (the grid spans 0..1)
        origin = (points.detach().float().cpu() - self.center) / (2 * self.radius) + 0.5
        rows = []
        with torch.no_grad():
            for direction in directions.detach().float().cpu():
                march = direction / (2 * self.radius)  # grid units per world unit
                # March only until the ray leaves the grid (the farthest point of the chunk).
                bound = torch.where(march > 0, 1.0 - origin, -origin) / torch.where(
                    march.abs() > 1e-12, march, torch.full_like(march, 1e-12)
                )
                exits = bound.abs().min(dim=-1).values  # [N] world units to the grid's border
                visible = torch.ones(origin.shape[0])
                for start in range(0, origin.shape[0], POINTS_PER_MARCH):
                    chunk = origin[start : start + POINTS_PER_MARCH]
                    reach = float(exits[start : start + POINTS_PER_MARCH].max())
                    steps = max(1, math.ceil(reach * float(march.norm()) / step) + 1)
                    distances = (torch.arange(steps, dtype=torch.float32) + 1) * step
                    unit = march / march.norm()
                    samples = chunk[:, None] + distances[None, :, None] * unit  # [n, S, 3]
                    index = ((samples * resolution).floor().long() + 1).clamp(0, side - 1)
                    flat = (index[..., 0] * side + index[..., 1]) * side + index[..., 2]
                    occupied = padded[flat]  # [n, S]
                    # Shadowed: a free sample before an occupied one (the ray left the hull
                    # and entered it again).
                    free = ~occupied
                    first_free = torch.where(free.any(1), free.float().argmax(1), steps)
                    last_occupied = steps - 1 - occupied.flip(1).float().argmax(1)
                    hidden = occupied.any(1) & (first_free < last_occupied)
                    visible[start : start + POINTS_PER_MARCH] = 1.0 - hidden.float()
                rows.append(visible)
        return torch.stack(rows).double()


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
    relight: DiagnosisData, settings: DiagnoseConfig, hull: SilhouetteHull | None = None
) -> dict[str, float | int | str] | None:
    """The cast-shadow statistic of the relight views (rendered under their own light), its
    placebo-direction null and the recovered share of the sun's light the shadows remove, or
    None when the relight light has no directional sun, turns with the camera, or too few
    pixels are seen.

    Two occluders predict the shadows: the fitted mesh and, given, the silhouettes' hull
    (thin parts the fit lost). Each direction's statistic is the larger of the two
    correlations, for the relight sun as for every placebo direction, so the null is the same
    maximum. Keys: correlation, p_value, placebo_quantile, placebo_lights, strength (the
    coefficient of the missing-shadow term: about 1 when a hard shadow removes all of the sun's
    light), shadowed (share of pixels facing the sun that the deciding occluder shadows),
    shadowed_mesh, shadowed_silhouettes (-1 without a hull), occluder ('fitted mesh' or
    'silhouettes'), pixels, views."""
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
    occluders = {
        "fitted mesh": sun_visibility(
            relight.mesh, points, normals, directions, options.map_resolution
        )
    }
    if hull is not None:
        occluders["silhouettes"] = hull.visibility(points, directions)
    one_cell = torch.zeros_like(view)
    residual = divide_view_gains(residual, rendered, view)
    residual = project_out(residual[:, None], one_cell, view, rendered)[:, 0]
    lambert = (normals @ directions.T).clamp_min(0.0) * rendered[:, None]  # [N, K]
    lambert_projected = project_out(lambert, one_cell, view, rendered)
    count = directions.shape[0]
    scored = {}
    for occluder, visibility in occluders.items():
        missing = project_out(-(1 - visibility.T) * lambert, one_cell, view, rendered)
        scored[occluder] = [
            _partial_correlation(residual, missing[:, k], lambert_projected[:, k])
            for k in range(count)
        ]
    # Each direction's statistic: the larger correlation over the occluders (nan: no shadow).
    best = torch.tensor(
        [[score[k][0] for k in range(count)] for score in scored.values()], dtype=torch.float64
    ).nan_to_num(-1.0)
    statistic = best.max(0).values
    chosen = list(scored)[int(best[:, 0].argmax())]
    _, coefficient = scored[chosen][0]
    null = statistic[1:]
    correlation = float(statistic[0])
    facing = (normals @ direction) > 0.1

    def shadowed(visibility: torch.Tensor) -> float:
        hidden = visibility[0][facing] < 0.5
        return float(hidden.double().mean()) if hidden.numel() else 0.0

    return {
        "correlation": correlation,
        "p_value": float((1 + (null >= correlation).sum()) / (1 + null.numel())),
        "placebo_quantile": float(torch.quantile(null, 0.95)) if null.numel() else math.nan,
        "placebo_lights": int(null.numel()),
        "strength": coefficient,
        "shadowed": shadowed(occluders[chosen]),
        "shadowed_mesh": shadowed(occluders["fitted mesh"]),
        "shadowed_silhouettes": shadowed(occluders["silhouettes"]) if hull else -1.0,
        "occluder": chosen,
        "pixels": int(view.numel()),
        "views": relight.view_count,
    }


def cast_shadow_evidence(
    relight: DiagnosisData,
    name: str,
    settings: DiagnoseConfig,
    hull: SilhouetteHull | None = None,
) -> Evidence | None:
    """Whether the relight residual falls where the fitted mesh (or the silhouettes' hull)
    shadows the relight sun, beyond placebo directions (threshold and passed are the decision
    config's; the decision re-derives them); None when it cannot be measured."""
    measured = cast_shadow_statistic(relight, settings, hull)
    if measured is None:
        return None
    decision = settings.decision
    occluder = OCCLUDER_PHRASES[measured["occluder"]]
    reason = (
        f"{name}: the relight views are darker than the render where {occluder} the relight "
        f"sun (r = {measured['correlation']:.3f} over {measured['views']} views, "
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
    hull = silhouette_hull(inputs, settings) if settings.cast_shadow.silhouette_occluders else None
    by_name = {candidate.name: candidate for candidate in candidates}
    records = []
    for name in wanted:
        evidence = cast_shadow_evidence(inputs.relight, name, settings, hull)
        if evidence is None:
            continue
        records.append(evidence)
        answered = answered_condition(by_name[name], evidence, settings)
        if answered is not None:
            records.append(answered)
    return records


def answered_condition(
    candidate: Candidate, evidence: Evidence, settings: DiagnoseConfig
) -> Evidence | None:
    """The candidate's failed identifiability condition "one light cannot tell baked shadows
    from a darker albedo" (recon.diagnose.fingerprint), revised by the relight split's
    cast-shadow test, or None when it has none. Where an occluder shadows at least
    diagnose.cast_shadow.identifiable_shadowed of the sun-facing relight pixels, the second
    light was there and was tested: the condition is void (the cast-shadow test decides,
    whatever its outcome). Where neither does, the capture it asks for is a relight sun that
    the object shadows itself, not the relight split it already has."""
    condition = candidate.evidence_of("identifiability")
    if condition is None or condition.passed or not condition.counts:
        return None
    details = evidence.details
    shadowed = max(details["shadowed_mesh"], details["shadowed_silhouettes"])
    if shadowed >= settings.cast_shadow.identifiable_shadowed:
        return replace(
            condition,
            void=(
                f"the relight split tested it: its sun is shadowed on {shadowed:.1%} of the "
                "sun-facing pixels, and the cast-shadow evidence decides"
            ),
        )
    return replace(
        condition,
        details={
            **condition.details,
            "capture": (
                "a relight light whose sun the object shadows itself (this relight split's sun "
                f"is shadowed on {shadowed:.1%} of the sun-facing pixels by the fitted mesh or "
                "the silhouettes)"
            ),
        },
    )


def silhouette_hull(inputs: EvidenceInputs, settings: DiagnoseConfig) -> SilhouetteHull | None:
    """The visual hull of every split's observed masks (training, held-out, relight) around
    the fitted mesh, or None without a relight split or masks that bound the object."""
    if inputs.relight is None:
        return None
    views = [
        (captures.cameras, captures.masks)
        for captures in (inputs.training, inputs.heldout)
        if captures is not None and captures.mask_source != "none"
    ]
    views.append((inputs.relight.cameras, inputs.relight.observed_alpha))
    options = settings.cast_shadow
    return SilhouetteHull.carve(
        views, inputs.relight.mesh, options.silhouette_voxel_pixels, options.silhouette_margin
    )
