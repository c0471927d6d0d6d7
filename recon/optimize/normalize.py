"""Scene normalisation: where the object is, from the cameras and masks, and the similarity
transform that puts it in a box of half-size `radius` around the origin.

Published poses rarely put the object at the origin or at a known scale (LLFF/NeRD, COLMAP and
photogrammetry frames are arbitrary), while the fit's visual hull and remesher work in a box
around the origin. The estimate: the point nearest to every camera's optical axis (where an
object-centric capture looks), then a coarse carving of the masks around it, grown until the
carved volume clears the grid's border; the carved box's centre and half-size give the transform
    x_normalised = scale * (x_dataset - centre)
(no rotation, so light directions and spherical-harmonic environments mean the same in both
frames). The cameras' mean up direction is recorded for figures.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from recon.camera import (
    Cameras,
    camera_forward_directions,
    camera_up_directions,
    similarity_transformed,
)
from recon.config.run_config import NormalizeConfig
from recon.errors import ReconError, warn_user
from recon.io.atomic import atomic_write_json
from recon.optimize.visual_hull import border_share, carve

NORMALIZATION_FILE = "normalization.json"
# Coarse carving: up to this many growths of the grid (x GROWTH each) while it touches the border.
GROWTH = 1.6
MAX_GROWTHS = 3
_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class SceneTransform:
    """x_normalised = scale * (x_dataset - centre); up: unit [3] (the scene's up, any frame:
    the transform has no rotation)."""

    scale: float
    centre: list[float]
    up: list[float]
    warnings: list[str] = field(default_factory=list)

    def to_normalised(self, points: torch.Tensor) -> torch.Tensor:
        """[..., 3] dataset-frame points -> normalised frame."""
        centre = torch.tensor(self.centre, dtype=points.dtype, device=points.device)
        return (points - centre) * self.scale

    def to_dataset(self, points: torch.Tensor) -> torch.Tensor:
        """[..., 3] normalised-frame points -> the dataset's own frame."""
        centre = torch.tensor(self.centre, dtype=points.dtype, device=points.device)
        return points / self.scale + centre

    def light_to_dataset(self, light: dict) -> dict:
        """A light.json record of the normalised frame in the dataset's own frame.

        Directional lights and the SH environment are unchanged (no rotation); point lights move
        with the inverse transform and keep the irradiance they give the object (intensity over
        scale squared: distances grow by 1 / scale). A camera-frame light is in camera axes,
        which the transform does not touch except for positions' scale about the camera.
        """
        converted = dict(light)
        camera_frame = light.get("frame", "world") == "camera"
        points = []
        for point in light.get("points", []):
            position = torch.tensor(point["position"], dtype=torch.float64)
            if camera_frame:
                position = position / self.scale
            else:
                position = self.to_dataset(position)
            intensity = [value / self.scale**2 for value in point["intensity"]]
            points.append({**point, "position": position.tolist(), "intensity": intensity})
        if "points" in light:
            converted["points"] = points
        return converted

    def cameras(self, cameras: Cameras) -> Cameras:
        """Dataset-frame cameras in the normalised frame."""
        return similarity_transformed(cameras, self.scale, torch.tensor(self.centre))

    def to_json(self) -> dict:
        return {
            "maps": "x_normalised = scale * (x_dataset - centre)",
            "scale": self.scale,
            "centre": self.centre,
            "up": self.up,
            "warnings": self.warnings,
            # What the fit wrote in each frame (the dataset's is what later stages read).
            "exports": {
                "dataset_frame": ["mesh/model.obj", "mesh/model.glb", "light/light.json"],
                "normalised_frame": ["mesh/normalized/model.obj", "light/normalized/light.json"],
            },
        }

    @staticmethod
    def from_json(data: dict) -> SceneTransform:
        return SceneTransform(
            float(data["scale"]),
            [float(v) for v in data["centre"]],
            [float(v) for v in data["up"]],
            list(data.get("warnings", [])),
        )

    def write(self, path: Path) -> None:
        atomic_write_json(path, self.to_json())

    @staticmethod
    def read(path: Path) -> SceneTransform:
        return SceneTransform.from_json(json.loads(Path(path).read_text()))


def look_at_point(cameras: Cameras) -> torch.Tensor:
    """The point [3] nearest (least squares) to every camera's optical axis.

    Minimises sum_i |(I - d_i d_i^T)(p - c_i)|^2; a small pull toward the cameras' centroid
    keeps it defined when the axes are near parallel (a forward-facing capture).
    """
    centres = cameras.centers().double()
    directions = torch.nn.functional.normalize(camera_forward_directions(cameras).double(), dim=-1)
    projectors = torch.eye(3, dtype=torch.float64) - directions[:, :, None] * directions[:, None]
    ridge = 1e-3 * len(cameras)
    system = projectors.sum(0) + ridge * torch.eye(3, dtype=torch.float64)
    right = (projectors @ centres[..., None]).sum(0)[:, 0] + ridge * centres.mean(0)
    return torch.linalg.solve(system, right).float()


def mean_up(cameras: Cameras, config_up: str = "auto") -> torch.Tensor:
    """The scene's up [3]: the cameras' mean up direction, or a configured axis."""
    if config_up != "auto":
        up = torch.zeros(3)
        up[_AXES[config_up[-1]]] = -1.0 if config_up.startswith("-") else 1.0
        return up
    mean = camera_up_directions(cameras).double().mean(0)
    if float(mean.norm()) < 1e-6:
        return torch.tensor([0.0, 1.0, 0.0])
    return torch.nn.functional.normalize(mean, dim=0).float()


def estimate_scene_transform(
    cameras: Cameras, masks: torch.Tensor, config: NormalizeConfig
) -> SceneTransform:
    """The transform that centres the masks' carved volume and scales it to config.radius.

    cameras: B dataset-frame cameras; masks: [B, H, W, 1] coverage (read at config.image_size).
    """
    if masks.ndim != 4 or masks.shape[0] != len(cameras):
        raise ReconError(
            f"masks: expected shape [{len(cameras)}, H, W, 1], got {tuple(masks.shape)}"
        )
    height, width = cameras.image_size
    shrink = min(1.0, config.image_size / max(height, width))
    size = (max(1, round(height * shrink)), max(1, round(width * shrink)))
    small_masks = torch.nn.functional.interpolate(
        masks.permute(0, 3, 1, 2).float(), size=size, mode="area"
    ).permute(0, 2, 3, 1)
    small_cameras = cameras.with_image_size(size).to(masks.device)
    centre = look_at_point(cameras.to("cpu")).to(masks.device)
    distance = float((small_cameras.centers() - centre).norm(dim=-1).min())
    radius = 0.8 * distance
    warnings: list[str] = []
    occupancy = None
    for _ in range(MAX_GROWTHS + 1):
        occupancy, radius = carve(
            small_cameras, small_masks, config.grid, radius=radius, center=centre
        )
        if occupancy.sum() == 0 or border_share(occupancy) == 0:
            break
        radius *= GROWTH
    if occupancy is None or occupancy.sum() == 0:
        warnings.append(
            "normalisation: the masks carve every voxel around the cameras' look-at point "
            "away; the scene is centred on that point instead. Check that the masks are white "
            "on the object and that the poses belong to the images"
        )
        half_size = 0.5 * distance
        box_centre = centre
    else:
        if border_share(occupancy) > 0:
            warnings.append(
                f"normalisation: the masks' carved volume still touches a grid of half-size "
                f"{radius:.3g} around the look-at point: the masks may not cut the object out "
                "(background marked as object?) or the cameras do not surround it"
            )
        voxel = 2 * radius / config.grid
        indices = torch.nonzero(occupancy > 0).float()
        lower = (indices.amin(0)) * voxel - radius + centre
        upper = (indices.amax(0) + 1) * voxel - radius + centre
        box_centre = (lower + upper) / 2
        half_size = float((upper - lower).amax()) / 2
    for message in warnings:
        warn_user(message)
    return SceneTransform(
        scale=config.radius / half_size,
        centre=[float(v) for v in box_centre.cpu()],
        up=[float(v) for v in mean_up(cameras.to("cpu"), config.up)],
        warnings=warnings,
    )
