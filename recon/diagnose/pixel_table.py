"""The diagnosis's object pixels as a flat table, with the covariates the specificity checks bin
them by, and additive log-gain models fitted on one half of the pixels and scored on the other.

A gain-like effect (exposure, white balance, a tone curve, a falloff) multiplies the rendered
colour. Which factor the gain follows is its signature: one gain per view (exposure), per view
and channel (white balance), per intensity (a response curve), per image position (vignetting),
per surface region (shadows, interreflection, a texture error) or per angle to the light
(view-dependent reflectance). Every pixel carries a label per factor; a model is a set of terms
(tuples of factors), each term one log gain per level; it is fitted by weighted least squares on
per-cell log gains of the first half of the pixel blocks and scored by the squared error it
leaves on the second half. Comparing nested models on held-out pixels says which factor the
gain really follows, without a tuned cut-off.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from recon.diagnose.data import DiagnosisData

# Rendered values below this carry no gain information (a gain multiplies them into nothing):
# background and the darkest antialiased edge pixels are left out of the table.
MINIMUM_RENDERED = 1e-4


class LastResult:
    """The last result of a function of some objects (tensors, a light), kept while the same
    objects (by identity, and tensors at the same version) are asked about again: the
    diagnosis asks for the same views' directions and angles from several checks. Callers
    must not change the returned tensors in place."""

    def __init__(self) -> None:
        self._key: list[tuple[object, int | None]] | None = None
        self._value: Any = None

    def get(self, objects: Sequence[object], compute: Callable[[], Any]) -> Any:
        key = [(item, getattr(item, "_version", None)) for item in objects]
        if self._key is not None and len(self._key) == len(key):
            if all(a is b and u == v for (a, u), (b, v) in zip(self._key, key, strict=True)):
                return self._value
        self._key, self._value = None, None  # (the old inputs are let go first)
        self._value = compute()
        self._key = key
        return self._value


_LAST_DIRECTIONS = LastResult()


def view_directions(data: DiagnosisData) -> tuple[torch.Tensor, torch.Tensor]:
    """World surface points [B, H, W, 3] (unprojected depth) and unit directions from them to
    the camera [B, H, W, 3] (the last views' kept, LastResult)."""
    cameras = data.cameras
    return _LAST_DIRECTIONS.get(
        (data.depth, cameras.world_to_cam, cameras.intrinsics), lambda: _view_directions(data)
    )


def _view_directions(data: DiagnosisData) -> tuple[torch.Tensor, torch.Tensor]:
    """view_directions, computed."""
    batch, height, width, _ = data.depth.shape
    depth = data.depth[..., 0]
    rows, columns = torch.meshgrid(
        torch.arange(height, dtype=depth.dtype) + 0.5,
        torch.arange(width, dtype=depth.dtype) + 0.5,
        indexing="ij",
    )
    intrinsics = data.cameras.intrinsics.to(depth)
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    camera_points = torch.stack(
        [(columns - cx) / fx * depth, (rows - cy) / fy * depth, depth, torch.ones_like(depth)],
        dim=-1,
    ).view(batch, -1, 4)
    cam_to_world = torch.linalg.inv(data.cameras.world_to_cam.to(depth))
    world = (camera_points @ cam_to_world.transpose(1, 2))[..., :3].view(batch, height, width, 3)
    to_camera = data.cameras.centers().to(depth)[:, None, None, :] - world
    return world, to_camera / to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def dominant_light_direction(data: DiagnosisData) -> tuple[torch.Tensor | None, str]:
    """The fitted light's main direction toward the light, [3] in the lighting's frame, and
    where it came from: the strongest directional light, else the strongest point light's
    direction from the origin, else the environment's first SH band (its mean direction);
    (None, "none") for a uniform environment (no direction to measure a highlight against)."""
    lighting = data.lighting
    if lighting.directional:
        strongest = max(lighting.directional, key=lambda light: float(light.irradiance.sum()))
        direction = strongest.direction_to_light.detach().float().cpu()
        return direction / direction.norm().clamp_min(1e-9), "directional light"
    if lighting.points:
        strongest = max(lighting.points, key=lambda light: float(light.intensity.sum()))
        direction = strongest.position.detach().float().cpu()
        if float(direction.norm()) > 1e-6:
            return direction / direction.norm(), "point light"
    sh = lighting.sh_coefficients.detach().float().cpu().sum(dim=-1)
    # Band 1 in sh_basis order (y, z, x): the environment's dipole, pointing toward the light.
    dipole = torch.stack([sh[3], sh[1], sh[2]])
    if float(dipole.norm()) <= 1e-3 * max(float(sh[0].abs()), 1e-9):
        return None, "none"
    return dipole / dipole.norm(), "environment"


def quantile_labels(values: torch.Tensor, bins: int) -> torch.Tensor:
    """Labels [N] in 0..bins-1 with (about) equal counts per bin."""
    if values.numel() == 0:
        return torch.zeros(0, dtype=torch.long)
    edges = torch.quantile(values.double(), torch.linspace(0, 1, bins + 1, dtype=torch.float64))
    return torch.bucketize(values.double(), edges[1:-1].contiguous(), right=True).clamp(0, bins - 1)


@dataclass
class PixelTable:
    """The object pixels of a DiagnosisData, flattened (N pixels).

    view: [N] view index; observed, rendered: [N, 3] linear colour; first_half: [N] bool, the
    pixel's block belongs to the fitting half (a checkerboard of block_pixels blocks, like the
    probes'); labels: factor name -> [N] int64 level; values: covariate name -> [N] float (the
    raw value a label bins, for slopes); view_count: B.
    """

    view: torch.Tensor
    observed: torch.Tensor
    rendered: torch.Tensor
    first_half: torch.Tensor
    labels: dict[str, torch.Tensor]
    values: dict[str, torch.Tensor]
    view_count: int
    light_source: str = "none"


def pixel_table(
    data: DiagnosisData,
    angle_bins: int = 6,
    intensity_bins: int = 6,
    surface_cells: int = 3,
    position_cells: int = 3,
    block_pixels: int = 4,
    normal_cells: int = 4,
) -> PixelTable:
    """The table of data's rendered object pixels with the labels of every domain:

    view; surface (the fitted surface point's cell in a surface_cells^3 grid over the object's
    bounding box: a region of the fitted mesh, whatever its UVs); n_dot_h (quantile bins of n.h
    against the fitted light's main direction, or of n.v without one); n_dot_v; intensity
    (quantile bins of the rendered luminance); image_position (a position_cells^2 grid of the
    image); radius (quantile bins of the distance from the principal point); camera_normal (a
    normal_cells^2 grid over the x and y components of the shading normal in the view's camera
    axes: under a light fixed to the camera, everything the light does at a pixel follows it).
    """
    batch, height, width, _ = data.observed.shape
    world, to_camera = view_directions(data)
    normals = data.normals
    normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    rendered = data.rendered
    luminance = rendered.mean(dim=-1)
    keep = table_pixels(data)

    light, source = dominant_light_direction(data)
    if light is not None and data.lighting.frame == "camera":
        # A light in camera axes: the same direction in every view's camera frame.
        rotation = data.cameras.world_to_cam[:, :3, :3].to(normals)
        light_world = (rotation.transpose(1, 2) @ light.to(normals))[:, None, None, :]
    elif light is not None:
        light_world = light.to(normals)[None, None, None, :]
    else:
        light_world = to_camera  # no light direction: the reflection angle against the view
    halfway = light_world + to_camera
    halfway = halfway / halfway.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    n_dot_h = (normals * halfway).sum(-1)
    n_dot_v = (normals * to_camera).sum(-1)
    camera_rotation = data.cameras.world_to_cam[:, :3, :3].to(normals)
    camera_normals = (normals.reshape(batch, -1, 3) @ camera_rotation.transpose(1, 2)).view(
        batch, height, width, 3
    )

    rows = torch.arange(height)[:, None].expand(height, width)
    columns = torch.arange(width)[None, :].expand(height, width)
    first = ((rows // block_pixels + columns // block_pixels) % 2 == 0).expand(batch, -1, -1)
    position = (
        rows * position_cells // height
    ) * position_cells + columns * position_cells // width
    position = position.expand(batch, -1, -1)
    radius = pixel_radius(data)
    surface = surface_labels(world[keep], surface_cells)
    view = torch.arange(batch)[:, None, None].expand(batch, height, width)[keep]
    facing = camera_normals[keep]
    normal_column = ((facing[:, 0] + 1) / 2 * normal_cells).long().clamp(0, normal_cells - 1)
    normal_row = ((facing[:, 1] + 1) / 2 * normal_cells).long().clamp(0, normal_cells - 1)
    values = {
        "n_dot_h": n_dot_h[keep],
        "n_dot_v": n_dot_v[keep],
        "intensity": luminance[keep],
        "radius": radius[keep],
    }
    labels = {
        "view": view,
        "surface": surface,
        "n_dot_h": quantile_labels(values["n_dot_h"], angle_bins),
        "n_dot_v": quantile_labels(values["n_dot_v"], angle_bins),
        "intensity": quantile_labels(values["intensity"], intensity_bins),
        "image_position": position[keep],
        "radius": quantile_labels(values["radius"], angle_bins),
        "camera_normal": normal_row * normal_cells + normal_column,
    }
    return PixelTable(
        view=view,
        observed=data.observed[keep].double(),
        rendered=rendered[keep].double(),
        first_half=first[keep],
        labels=labels,
        values=values,
        view_count=batch,
        light_source=source if light is not None else "view direction (no light direction)",
    )


def table_pixels(data: DiagnosisData) -> torch.Tensor:
    """[B, H, W] bool: the pixels of pixel_table (rendered object, in the region, not black)."""
    luminance = data.rendered.mean(dim=-1)
    return data.rendered_mask & (luminance > MINIMUM_RENDERED) & (data.region[..., 0] > 0.5)


def pixel_radius(data: DiagnosisData) -> torch.Tensor:
    """[B, H, W] distance of each pixel centre from the principal point over the half image
    diagonal (float32, pixel_table's 'radius' values)."""
    _, height, width, _ = data.observed.shape
    rows = torch.arange(height)[:, None].expand(height, width)
    columns = torch.arange(width)[None, :].expand(height, width)
    intrinsics = data.cameras.intrinsics.float()
    dx = columns[None].float() + 0.5 - intrinsics[:, 0, 2, None, None]
    dy = rows[None].float() + 0.5 - intrinsics[:, 1, 2, None, None]
    return torch.sqrt(dx * dx + dy * dy) / (0.5 * math.hypot(height, width))


def surface_labels(points: torch.Tensor, surface_cells: int) -> torch.Tensor:
    """[N] cell of each world point [N, 3] in a surface_cells^3 grid over their bounding box."""
    low = points.min(dim=0).values if points.numel() else torch.zeros(3)
    high = points.max(dim=0).values if points.numel() else torch.ones(3)
    cell = ((points - low) / (high - low).clamp_min(1e-9) * surface_cells).long()
    cell = cell.clamp(0, surface_cells - 1)
    return (cell[:, 0] * surface_cells + cell[:, 1]) * surface_cells + cell[:, 2]


# A model term: a tuple of factor names ("channel" is the colour channel); () is one global gain.
Term = tuple[str, ...]


def _cell_index(table: PixelTable, factors: list[str]) -> tuple[torch.Tensor, list[int]]:
    """A combined [N] cell id over the factors (channel excluded) and each factor's size."""
    index = torch.zeros_like(table.view)
    sizes = []
    for name in factors:
        labels = table.labels[name]
        size = int(labels.max()) + 1 if labels.numel() else 1
        index = index * size + labels
        sizes.append(size)
    return index, sizes


class GainModels:
    """Additive log-gain models over a PixelTable's cells, fitted on the first half, scored on
    the second (per-view squared error sums).

    factors: every factor any compared model uses (besides "channel"); the table is reduced to
    cells of their joint levels, per channel: y = log(sum o r / sum r^2) (the least-squares
    gain of the cell's first-half pixels) with weight sum r^2 (the information about it).
    all_pixels: fit on every pixel instead (for the F-tests, which count degrees of freedom
    instead of holding pixels out).
    """

    def __init__(self, table: PixelTable, factors: list[str], all_pixels: bool = False) -> None:
        # The same models of one table are asked for again and again (the specificity checks
        # of several candidates share factors): built once per table, their fits kept.
        kept = table.__dict__.setdefault("_gain_models", {})
        key = (tuple(factors), bool(all_pixels))
        if key in kept:
            self.__dict__.update(kept[key])
            return
        self.table = table
        self.factors = list(factors)
        cell, sizes = _cell_index(table, self.factors)
        unique, inverse = torch.unique(cell, return_inverse=True)
        self.cell_count = unique.numel()
        self.inverse = inverse  # [N] the pixel's cell
        # Each cell's level of every factor (decoded from the combined id).
        levels = {}
        remainder = unique.clone()
        for name, size in zip(reversed(self.factors), reversed(sizes), strict=True):
            levels[name] = remainder % size
            remainder = remainder // size
        self.levels = levels
        first = torch.ones_like(table.first_half) if all_pixels else table.first_half
        channels = table.observed.shape[1]
        cross = torch.zeros(self.cell_count, channels, dtype=torch.float64)
        energy = torch.zeros(self.cell_count, channels, dtype=torch.float64)
        cross.index_add_(0, inverse[first], (table.observed * table.rendered)[first])
        energy.index_add_(0, inverse[first], (table.rendered**2)[first])
        self.weight = energy
        # A cell whose first half saw no light has no gain to learn (weight 0).
        self.log_gain = torch.log(cross.clamp_min(1e-12) / energy.clamp_min(1e-12))
        self.log_gain = torch.where(energy > 0, self.log_gain, torch.zeros_like(self.log_gain))
        second = ~first
        self.second_view = table.view[second]
        self.second_cell = inverse[second]
        self.second_observed = table.observed[second]
        self.second_rendered = table.rendered[second]
        self._residual_sums: dict[tuple, tuple[float, int]] = {}
        kept[key] = dict(self.__dict__)

    def _design(self, terms: list[Term]) -> torch.Tensor:
        """[cells * channels, columns] one-hot design of the terms."""
        channels = self.log_gain.shape[1]
        channel = torch.arange(channels).repeat(self.cell_count)
        columns = []
        for term in terms:
            index = torch.zeros(self.cell_count * channels, dtype=torch.long)
            size = 1
            for name in term:
                if name == "channel":
                    level, count = channel, channels
                else:
                    level = self.levels[name].repeat_interleave(channels)
                    count = int(self.levels[name].max()) + 1 if self.cell_count else 1
                index = index * count + level
                size *= count
            columns.append(torch.nn.functional.one_hot(index, size).double())
        return torch.cat(columns, dim=1)

    def _weighted(self, terms: list[Term]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        design = self._design(terms)
        root = self.weight.reshape(-1, 1).sqrt()
        # Normalised weights keep the least-squares system well scaled.
        root = root / root.max().clamp_min(1e-30)
        return design, root * design, root * self.log_gain.reshape(-1, 1)

    def fit(self, terms: list[Term]) -> torch.Tensor:
        """Fitted log gains [cells, channels] of the model with these terms."""
        design, weighted, target = self._weighted(terms)
        solution = torch.linalg.lstsq(weighted, target, driver="gelsd").solution
        return (design @ solution).reshape(self.cell_count, -1)

    def residual_sum(self, terms: list[Term]) -> tuple[float, int]:
        """The model's weighted residual sum of squares over the cells' log gains and its
        rank (the parameters it really has), for nested-model F-tests."""
        key = tuple(terms)
        if key not in self._residual_sums:
            _, weighted, target = self._weighted(terms)
            solution = torch.linalg.lstsq(weighted, target, driver="gelsd").solution
            residual = float(((weighted @ solution - target) ** 2).sum())
            self._residual_sums[key] = (residual, int(torch.linalg.matrix_rank(weighted)))
        return self._residual_sums[key]

    def heldout_errors(self, terms: list[Term]) -> torch.Tensor:
        """Per-view squared error sums [B] on the second half with the model's gains."""
        gains = self.fit(terms).exp()[self.second_cell]
        squared = ((self.second_observed - self.second_rendered * gains) ** 2).sum(dim=1)
        errors = torch.zeros(self.table.view_count, dtype=torch.float64)
        return errors.index_add_(0, self.second_view, squared)

    def view_log_gains(self, terms: list[Term]) -> torch.Tensor:
        """The model's mean log gain per view [B] (luminance-weighted over its cells): what a
        per-view gain fitted under the model amounts to."""
        fitted = self.fit(terms).mean(dim=1)
        weight = self.weight.sum(dim=1)
        view = self.levels["view"]
        total = torch.zeros(self.table.view_count, dtype=torch.float64)
        norm = torch.zeros(self.table.view_count, dtype=torch.float64)
        total.index_add_(0, view, fitted * weight)
        norm.index_add_(0, view, weight)
        return total / norm.clamp_min(1e-30)
