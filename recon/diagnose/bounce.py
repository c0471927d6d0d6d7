"""Interreflection evidence: does the relight split's residual carry the relight sun's one
diffuse bounce off the fitted mesh?

Under the training light the fit bakes whatever light reaches a point, bounced light
included, into its albedo; no held-out residual shows it. A relight split is taken under a
second, known light (lighting_relight.json). recon's renderer has neither visibility nor
bounced light, so on the relight views a world with interreflection leaves a residual that
the physics of one bounce predicts from the fitted model alone:

- E_L^vis(x): the direct irradiance of light L at surface point x with the mesh's visibility
  (the SH sky sampled along K Fibonacci directions, each kept where the ray from x escapes the
  fitted mesh, plus each sun where its ray escapes); E_L^m(x): the same without visibility
  (what the renderer shades with);
- B_L(x) = sum_k max(0, n_x . w_k) (4 / K) J_L(y_k): the one-bounce irradiance, y_k the face
  of the fitted mesh the ray from x along w_k hits first (when it faces x), J_L(y) = a(y)
  E_L^vis(y) its radiosity, a(y) the fitted albedo with the training light's baked occlusion
  undone (a_fit E_T^m / E_T^vis);
- the fitted albedo a_fit(x) = a(x) (E_T^vis + B_T) / E_T^m under the fitted light T, so the
  relight observation is a_fit E_T^m (E_R^vis + B_R) / (E_T^vis + B_T) and the relight render
  a_fit E_R^m. Their difference splits into the direct light's visibility (cast shadows, the
  sky's occlusion: f_direct = a_fit (E_T^m E_R^vis / E_T^vis - E_R^m), in every path-traced
  render) and the bounce: f_bounce = a_fit E_T^m ((E_R^vis + B_R) / (E_T^vis + B_T) - E_R^vis
  / E_T^vis): the relight sun's bounce minus the training light's that the albedo absorbed.

The check, on the relight views' interior pixels (N, luminance), as recon.diagnose.cast_shadow
does for the shadow: the residual's partial correlation with f_bounce once one gain per view
on the render and f_direct (with a free coefficient; also f_direct with the sun turned by the
shadow edges' uncertainty, diagnose.bounce.penumbra_pixels, four more free columns, so a soft
or misplaced shadow edge is not read as bounce) are projected out; its null: the same
with the relight sun turned to placebo directions (diagnose.bounce.placebo_lights Fibonacci
directions at least diagnose.bounce.placebo_separation_degrees away; the nuisance stays the
true sun's). A residual that is brighter or darker in concavities for another reason (an
albedo darker there, a misfit of the geometry, the sky's occlusion) follows every placebo's
bounce as much; one bounce follows its own sun's. The statistic is the correlation's excess
over the placebos' 95th percentile, the p-value the share of placebos that reach it.

Visibility is exact ray casting against the fitted mesh's triangles (first_hits: a grid over
the triangles projected along each direction), not shadow maps: the bounce needs the face a
ray hits first, which a depth map along the direction (the face nearest the light) is not.

The decision (recon.diagnose.decision, row 'bounce') names the candidate when the excess
clears diagnose.decision.bounce_minimum and p < diagnose.decision.bounce_alpha. Without a
relight split whose light has a directional sun nothing is measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

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
from recon.effects.light_transport import fibonacci_directions
from recon.effects.registry import effects_with_evidence
from recon.mesh.mesh import Mesh
from recon.render.shading import Lighting, sh_basis

if TYPE_CHECKING:  # producers imports this module to register the producer
    from recon.diagnose.producers import EvidenceInputs

KIND = "bounce"
# A ray leaves its surface point lifted this share of the mesh's bounding-box diagonal along the
# normal, and a hit must lie this much further along the ray (self-intersection, not tuned).
LIFT = 1e-3
# Barycentric slack of the point-in-triangle test (rays through shared edges still hit).
EDGE_SLACK = 1e-6


def _frame(direction: torch.Tensor) -> torch.Tensor:
    """[3, 2] two unit axes perpendicular to the unit direction [3]."""
    helper = torch.zeros(3, dtype=direction.dtype)
    helper[int(direction.abs().argmin())] = 1.0
    first = torch.nn.functional.normalize(torch.linalg.cross(direction, helper), dim=0)
    return torch.stack([first, torch.linalg.cross(direction, first)], dim=1)


def first_hits(
    verts: torch.Tensor,
    faces: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    cells: int = 24,
) -> torch.Tensor:
    """The face [K, N] int64 each ray from origins [N, 3] along unit directions [K, 3] hits
    first (-1: it escapes), by exact ray-triangle tests against the triangles whose projection
    along the direction shares the origin's cell of a cells x cells grid. No gradient."""
    with torch.no_grad():
        verts = verts.detach().double()
        origins = origins.detach().double()
        hits = torch.full((directions.shape[0], origins.shape[0]), -1, dtype=torch.int64)
        face_index = torch.arange(faces.shape[0])
        for k, direction in enumerate(directions.detach().double()):
            axes = _frame(direction / direction.norm())
            flat = verts @ axes  # [V, 2]
            depth = verts @ direction  # [V]
            low = flat.min(dim=0).values
            size = ((flat.max(dim=0).values - low) / cells).clamp_min(1e-12) * (1 + 1e-9)
            corners = flat[faces]  # [F, 3, 2]
            first_cell = ((corners.min(dim=1).values - low) / size).floor().long()
            last_cell = ((corners.max(dim=1).values - low) / size).floor().long()
            first_cell, last_cell = first_cell.clamp(0, cells - 1), last_cell.clamp(0, cells - 1)
            spans = last_cell - first_cell + 1  # [F, 2]
            counts = spans[:, 0] * spans[:, 1]
            owner = torch.repeat_interleave(face_index, counts)
            starts = torch.cumsum(counts, 0) - counts
            local = torch.arange(owner.numel()) - starts[owner]
            column = first_cell[owner, 0] + local % spans[owner, 0]
            row = first_cell[owner, 1] + local // spans[owner, 0]
            cell = column * cells + row
            order = torch.argsort(cell, stable=True)
            cell, owner = cell[order], owner[order]
            per_cell = torch.bincount(cell, minlength=cells * cells)
            offsets = torch.cumsum(per_cell, 0) - per_cell

            # Per face: its first corner, two edges (projected), the determinant, the depths.
            base = corners[:, 0]
            edge_one, edge_two = corners[:, 1] - base, corners[:, 2] - base
            determinant = edge_one[:, 0] * edge_two[:, 1] - edge_one[:, 1] * edge_two[:, 0]
            usable = determinant.abs() > 1e-20
            safe = torch.where(usable, determinant, torch.ones_like(determinant))
            face_depth = depth[faces]  # [F, 3]
            packed = torch.cat(
                [base, edge_one / safe[:, None], edge_two / safe[:, None], face_depth], dim=1
            )  # [F, 9]

            point = origins @ axes  # [N, 2]
            start = origins @ direction  # [N]
            where = ((point - low) / size).floor().long()
            inside = ((where >= 0) & (where < cells)).all(dim=1)
            query_cell = where[:, 0].clamp(0, cells - 1) * cells + where[:, 1].clamp(0, cells - 1)
            # (query, candidate face) pairs: every face of the query's cell, no padding.
            counts = torch.where(inside, per_cell[query_cell], torch.zeros_like(query_cell))
            query = torch.repeat_interleave(torch.arange(origins.shape[0]), counts)
            first = torch.cumsum(counts, 0) - counts
            slot = torch.arange(query.numel()) - first[query]
            face = owner[offsets[query_cell[query]] + slot]
            data = packed[face]
            offset = point[query] - data[:, 0:2]
            one = offset[:, 0] * data[:, 5] - offset[:, 1] * data[:, 4]
            two = data[:, 2] * offset[:, 1] - data[:, 3] * offset[:, 0]
            zero = 1 - one - two
            along = zero * data[:, 6] + one * data[:, 7] + two * data[:, 8]
            ahead = (
                usable[face]
                & (zero >= -EDGE_SLACK)
                & (one >= -EDGE_SLACK)
                & (two >= -EDGE_SLACK)
                & (along > start[query])
            )
            query, face, along = query[ahead], face[ahead], along[ahead]
            nearest = torch.full((origins.shape[0],), math.inf, dtype=torch.float64)
            nearest = nearest.scatter_reduce(0, query, along, reduce="amin")
            winner = along == nearest[query]
            hits[k].scatter_(0, query[winner], face[winner])
        return hits


def face_albedo(mesh: Mesh) -> torch.Tensor:
    """Fitted albedo luminance [F] at each face's centre: the texture sampled bilinearly at the
    face's mean UV, else the mean of its vertex colours, else 1."""
    weights = torch.tensor(LUMINANCE, dtype=torch.float64)
    faces = mesh.faces
    if mesh.texture is not None and mesh.uvs is not None and mesh.uv_faces is not None:
        texture = mesh.texture.detach().double()
        channels = texture.shape[-1]
        centre = mesh.uvs.detach().double()[mesh.uv_faces].mean(dim=1)  # [F, 2]
        grid = (centre * 2 - 1)[None, None]  # (0, 0) is the top-left corner
        image = texture.permute(2, 0, 1)[None]
        sampled = torch.nn.functional.grid_sample(
            image, grid, mode="bilinear", padding_mode="border", align_corners=False
        )[0, :, 0].T  # [F, C]
    elif mesh.vertex_colors is not None:
        sampled = mesh.vertex_colors.detach().double()[faces].mean(dim=1)
        channels = sampled.shape[-1]
    else:
        return torch.ones(faces.shape[0], dtype=torch.float64)
    if channels == 1:
        return sampled[:, 0]
    return sampled[:, :3] @ (weights / weights.sum())


@dataclass
class Light:
    """A light reduced to luminance: the SH sky's radiance [K] along the hemisphere directions
    (clipped at 0) and its suns (directions [S, 3] toward them, irradiance [S])."""

    sky: torch.Tensor
    sun_directions: torch.Tensor
    sun_irradiance: torch.Tensor

    @staticmethod
    def of(lighting: Lighting, directions: torch.Tensor) -> Light:
        weights = torch.tensor(LUMINANCE, dtype=torch.float64)
        coefficients = lighting.sh_coefficients.detach().double().cpu()
        channels = coefficients.shape[-1]
        luminance = weights[:channels] / weights[:channels].sum()
        sky = (sh_basis(directions) @ coefficients).clamp_min(0.0) @ luminance
        if lighting.directional:
            suns = torch.stack(
                [light.direction_to_light.detach().double().cpu() for light in lighting.directional]
            )
            power = torch.stack(
                [
                    light.irradiance.detach().double().cpu()[:channels] @ luminance
                    for light in lighting.directional
                ]
            )
        else:
            suns, power = (
                torch.zeros(0, 3, dtype=torch.float64),
                torch.zeros(0, dtype=torch.float64),
            )
        return Light(sky, torch.nn.functional.normalize(suns, dim=-1), power)

    def turned(self, direction: torch.Tensor) -> Light:
        """The same light with its strongest sun moved to the unit direction [3]."""
        suns = self.sun_directions.clone()
        suns[int(self.sun_irradiance.argmax())] = direction
        return Light(self.sky, suns, self.sun_irradiance)


@dataclass
class Receivers:
    """Surface points that gather light: points [N, 3] (lifted off the surface), normals
    [N, 3], the face each direction's ray hits first [K, N] (-1: the sky), the cosines [K, N]
    max(0, n . w_k) and whether the hit face faces the point [K, N]."""

    points: torch.Tensor
    normals: torch.Tensor
    hits: torch.Tensor
    cosine: torch.Tensor
    facing: torch.Tensor

    @staticmethod
    def cast(
        mesh: Mesh,
        points: torch.Tensor,
        normals: torch.Tensor,
        directions: torch.Tensor,
        cells: int,
    ) -> Receivers:
        """Receivers at points [N, 3] with normals [N, 3], each lifted LIFT of the mesh's
        diagonal along its normal, casting along the unit directions [K, 3]."""
        verts = mesh.verts.detach().double().cpu()
        diagonal = float((verts.max(0).values - verts.min(0).values).norm())
        normals = torch.nn.functional.normalize(normals.double(), dim=-1)
        lifted = points.double() + LIFT * diagonal * normals
        hits = first_hits(verts, mesh.faces.cpu(), lifted, directions, cells)
        outward = face_normals(verts, mesh.faces.cpu())
        cosine = (directions @ normals.T).clamp_min(0.0)  # [K, N]
        toward = (outward[hits.clamp_min(0)] * directions[:, None, :]).sum(-1) < 0
        return Receivers(lifted, normals, hits, cosine, toward & (hits >= 0))

    def part(self, which: slice) -> Receivers:
        """The receivers of a slice of the points."""
        return Receivers(
            self.points[which],
            self.normals[which],
            self.hits[:, which],
            self.cosine[:, which],
            self.facing[:, which],
        )

    def sun_visible(self, mesh: Mesh, suns: torch.Tensor, cells: int) -> torch.Tensor:
        """[S, N] 1 where the ray toward each sun escapes the mesh."""
        verts = mesh.verts.detach().double().cpu()
        return (first_hits(verts, mesh.faces.cpu(), self.points, suns, cells) < 0).double()

    def irradiance(
        self, light: Light, sun_visible: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(E^vis [N], E^m [N]): the light's direct irradiance with and without the mesh's
        visibility (Monte Carlo over the K directions for the sky, 4 pi / K each)."""
        weight = 4 * math.pi / self.cosine.shape[0]
        sky = weight * light.sky[:, None] * self.cosine
        sun_cosine = (light.sun_directions @ self.normals.T).clamp_min(0.0)  # [S, N]
        suns = light.sun_irradiance[:, None] * sun_cosine
        open_sky = (self.hits < 0).double()
        visible = (sky * open_sky).sum(0) + (suns * sun_visible).sum(0)
        return visible, sky.sum(0) + suns.sum(0)

    def bounce(self, radiosity: torch.Tensor) -> torch.Tensor:
        """One-bounce irradiance [N] from the faces' radiosity [F]: sum_k cos_k (4 / K) J."""
        weight = 4.0 / self.cosine.shape[0]
        gathered = radiosity[self.hits.clamp_min(0)] * self.facing.double()
        return weight * (self.cosine * gathered).sum(0)


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit normals [F, 3] of the faces (counter-clockwise = front)."""
    corners = verts[faces]
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return torch.nn.functional.normalize(cross, dim=-1)


def _turned_suns(direction: torch.Tensor, count: int, separation_degrees: float) -> torch.Tensor:
    """Placebo sun directions [P, 3]: Fibonacci directions at least separation_degrees away
    from the unit direction [3]."""
    placebos = fibonacci_directions(count).double()
    return placebos[(placebos @ direction) < math.cos(math.radians(separation_degrees))]


def penumbra_suns(relight: DiagnosisData, sun: torch.Tensor, pixels: float) -> torch.Tensor:
    """The unit sun direction [3] turned in four directions [4, 3] by the angle pixels pixel
    footprints at the object (the views' median) subtend over the mesh's radius: how far a
    shadow edge moves on the object when the sun turns by it ([0, 3] for pixels 0)."""
    if pixels <= 0:
        return torch.zeros(0, 3, dtype=torch.float64)
    verts = relight.mesh.verts.detach().double().cpu()
    center = (verts.min(0).values + verts.max(0).values) / 2
    radius = float((verts - center).norm(dim=-1).max())
    cameras = relight.cameras
    footprint = (cameras.centers().detach().double().cpu() - center).norm(dim=-1) / (
        cameras.intrinsics[:, 0, 0].detach().double().cpu()
    )
    slope = pixels * float(footprint.median()) / max(radius, 1e-12)
    axes = _frame(sun)
    turns = torch.cat([axes.T, -axes.T])  # [4, 3]
    return torch.nn.functional.normalize(sun[None] + slope * turns, dim=-1)


def bounce_features(
    relight: DiagnosisData,
    fitted: Lighting,
    keep: torch.Tensor,
    settings: DiagnoseConfig,
    placebo_suns: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """The per-pixel terms of the module docstring on the kept relight pixels (keep [B, H, W]
    bool): f_direct [N, 1 + T] (the relight sun's, then one per penumbra turn of it,
    penumbra_suns), f_bounce [N, 1 + P] (the relight sun's, then one per placebo sun [P, 3])
    and the predicted bounce's share of the relight direct light at each pixel (B_R / E_R^vis)
    [N]."""
    options = settings.bounce
    mesh = relight.mesh
    directions = fibonacci_directions(options.directions).double()
    verts = mesh.verts.detach().double().cpu()
    faces = mesh.faces.cpu()
    points, _ = view_directions(relight)
    # The pixels and the faces' centres cast together: one grid per direction.
    receivers = Receivers.cast(
        mesh,
        torch.cat([points.double()[keep], verts[faces].mean(dim=1)]),
        torch.cat([relight.normals.double()[keep], face_normals(verts, faces)]),
        directions,
        options.cells,
    )
    count = int(keep.sum())
    pixels, surface = receivers.part(slice(0, count)), receivers.part(slice(count, None))
    albedo = face_albedo(mesh)
    trained = Light.of(fitted, directions)
    relit = Light.of(relight.lighting, directions)
    floor = options.visibility_floor
    # Every sun's visibility at once: the relight light's, the fitted light's, the placebos'.
    strongest = int(relit.sun_irradiance.argmax())
    suns = torch.cat([relit.sun_directions[strongest][None], placebo_suns])
    turns = penumbra_suns(relight, relit.sun_directions[strongest], options.penumbra_pixels)
    relit_count, trained_count = len(relit.sun_irradiance), len(trained.sun_irradiance)
    seen = receivers.sun_visible(
        mesh,
        torch.cat([relit.sun_directions, trained.sun_directions, suns, turns]),
        options.cells,
    )
    relit_seen, trained_seen = seen[:relit_count], seen[relit_count : relit_count + trained_count]
    placebo_seen = seen[relit_count + trained_count : len(seen) - len(turns)]  # [1 + P, N + F]
    turned_seen = seen[len(seen) - len(turns) :]  # [T, N + F]

    # The training light: the albedo with its baked occlusion undone, and its own bounce.
    face_visible, face_model = surface.irradiance(trained, trained_seen[:, count:])
    true_albedo = albedo * face_model / face_visible.clamp_min(floor * face_model).clamp_min(1e-12)
    train_visible, train_model = pixels.irradiance(trained, trained_seen[:, :count])
    train_visible = train_visible.clamp_min(floor * train_model).clamp_min(1e-12)
    train_bounce = pixels.bounce(true_albedo * face_visible)

    relit_visible, relit_model = pixels.irradiance(relit, relit_seen[:, :count])
    rendered = (relight.rendered.double() * torch.tensor(LUMINANCE, dtype=torch.float64)).sum(-1)
    fitted_albedo = rendered[keep] / relit_model.clamp_min(1e-12)
    direct = [fitted_albedo * (train_model * relit_visible / train_visible - relit_model)]
    # The sun turned by the shadow edges' uncertainty: where a soft or misplaced edge falls.
    for turn, turned in zip(turns, turned_seen, strict=True):
        visibility = relit_seen[:, :count].clone()
        visibility[strongest] = turned[:count]
        visible, model = pixels.irradiance(relit.turned(turn), visibility)
        direct.append(fitted_albedo * (train_model * visible / train_visible - model))

    # The relight sun and its placebos.
    pixels_base, surface_base = relit_seen[:, :count], relit_seen[:, count:]
    pixels_seen, surface_seen = placebo_seen[:, :count], placebo_seen[:, count:]
    columns = []
    share = torch.zeros_like(rendered[keep])
    for index, sun in enumerate(suns):
        light = relit.turned(sun)
        pixels_visible, surface_visible = pixels_base.clone(), surface_base.clone()
        pixels_visible[strongest], surface_visible[strongest] = (
            pixels_seen[index],
            surface_seen[index],
        )
        face_lit, _ = surface.irradiance(light, surface_visible)
        visible, _ = pixels.irradiance(light, pixels_visible)
        bounce = pixels.bounce(true_albedo * face_lit)
        if index == 0:
            share = bounce / visible.clamp_min(1e-12)
        with_bounce = (visible + bounce) / (train_visible + train_bounce)
        columns.append(fitted_albedo * train_model * (with_bounce - visible / train_visible))
    return {
        "direct": torch.stack(direct, dim=1),
        "bounce": torch.stack(columns, dim=1),
        "share": share,
    }


def bounce_statistic(
    relight: DiagnosisData, fitted: Lighting, settings: DiagnoseConfig
) -> dict[str, float | int] | None:
    """The bounce statistic of the relight views (rendered under their own light) against the
    fitted light, its placebo-sun null and the recovered strength of the bounce, or None when
    the relight light has no directional sun, a light turns with the camera, or too few pixels
    are seen. Keys: correlation, p_value, placebo_quantile, placebo_lights, strength (the
    coefficient of the predicted one-bounce term: about 1 for one bounce, more for several),
    bounce_share (the predicted bounce's mean share of the relight direct light), pixels,
    views."""
    options = settings.bounce
    if relight.lighting.frame == "camera" or fitted.frame == "camera":
        return None
    if not relight.lighting.directional:
        return None
    keep = interior_pixels(relight)
    if int(keep.sum()) < options.minimum_pixels:
        return None
    # An even stride through the pixels: the cost is pixels x directions.
    flat = keep.flatten().nonzero()[:, 0]
    stride = max(1, math.ceil(flat.numel() / options.maximum_pixels))
    keep = torch.zeros_like(keep.flatten())
    keep[flat[::stride]] = True
    keep = keep.view_as(interior_pixels(relight))
    strongest = max(relight.lighting.directional, key=lambda light: float(light.irradiance.mean()))
    direction = torch.nn.functional.normalize(
        strongest.direction_to_light.detach().double().cpu(), dim=0
    )
    placebos = _turned_suns(direction, options.placebo_lights, options.placebo_separation_degrees)
    features = bounce_features(relight, fitted, keep, settings, placebos)

    weights = torch.tensor(LUMINANCE, dtype=torch.float64)
    view = torch.arange(relight.view_count)[:, None, None].expand_as(keep)[keep]
    residual = (relight.residual.double() * weights).sum(-1)[keep]
    rendered = (relight.rendered.double() * weights).sum(-1)[keep]
    one_cell = torch.zeros_like(view)
    nuisance = features["direct"]
    residual = divide_view_gains(residual, rendered, view)
    residual = project_out(residual[:, None], one_cell, view, rendered, nuisance)[:, 0]
    bounce = project_out(features["bounce"], one_cell, view, rendered, nuisance)
    norms = bounce.norm(dim=0).clamp_min(1e-30)
    correlations = (bounce.T @ residual) / (norms * residual.norm().clamp_min(1e-30))
    correlation, null = float(correlations[0]), correlations[1:]
    return {
        "correlation": correlation,
        "p_value": float((1 + (null >= correlation).sum()) / (1 + null.numel())),
        "placebo_quantile": float(torch.quantile(null, 0.95)) if null.numel() else math.nan,
        "placebo_lights": int(null.numel()),
        "strength": float((bounce[:, 0] @ residual) / norms[0] ** 2),
        "bounce_share": float(features["share"].mean()),
        "pixels": int(view.numel()),
        "views": relight.view_count,
    }


def bounce_evidence(
    relight: DiagnosisData, fitted: Lighting, name: str, settings: DiagnoseConfig
) -> Evidence | None:
    """Whether the relight residual follows the relight sun's one bounce off the fitted mesh,
    beyond placebo suns (threshold and passed are the decision config's; the decision
    re-derives them); None when it cannot be measured."""
    measured = bounce_statistic(relight, fitted, settings)
    if measured is None:
        return None
    decision = settings.decision
    reason = (
        f"{name}: the relight views are brighter than the render where the fitted mesh bounces "
        f"the relight sun's light (r = {measured['correlation']:.3f} over {measured['views']} "
        f"views, strength {measured['strength']:.2f} of one bounce, p = "
        f"{measured['p_value']:.2g} against {measured['placebo_lights']} placebo suns); its "
        "excess over the placebo suns' 95th percentile"
    )
    return placebo_excess_evidence(
        KIND,
        name,
        measured,
        decision.bounce_minimum,
        decision.bounce_alpha,
        reason,
        {"strength": measured["strength"], "bounce_share": measured["bounce_share"]},
    )


def bounce_producer(
    inputs: EvidenceInputs, candidates: list[Candidate], settings: DiagnoseConfig
) -> list[Evidence]:
    """Bounce evidence for the candidates whose facts list it (interreflection), on the relight
    split (none without one)."""
    names = {candidate.name for candidate in candidates}
    wanted = [name for name in effects_with_evidence(KIND) if name in names]
    if not settings.bounce.enabled or not wanted or inputs.relight is None:
        return []
    lighting = inputs.model.lighting.to("cpu")
    evidence = [bounce_evidence(inputs.relight, lighting, name, settings) for name in wanted]
    return [item for item in evidence if item is not None]
