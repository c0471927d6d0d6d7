"""Camera effect: per-view pose corrections, applied to the cameras before rendering.

world_to_cam' = [R(rotation_v) | translation_v] @ world_to_cam for the view v of each batch
entry: a small rigid motion in the camera's own frame (rotation about the camera centre, then a
shift along the camera axes). rotation_v is an axis-angle vector in radians (Rodrigues' formula
with a series near zero, so it is smooth and exactly the identity at 0); translation_v is in
world units times translation_scale. View 0 is pinned: it fixes the gauge of the world frame
that a joint fit of geometry and all poses would otherwise leave free.

The correction maps the recorded cameras to the ones that explain the images; when the recorded
poses carry an error E (recorded = E @ true), the recovered correction is about E^-1.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from recon.camera import Cameras
from recon.effects.base import ModelEffect, to_list
from recon.effects.facts import DiagnosisFacts
from recon.errors import ReconError

# Below this squared angle (rad^2) the Rodrigues coefficients use their Taylor series.
_SMALL_ANGLE_SQUARED = 1e-8


def skew(vectors: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices [..., 3, 3] of vectors [..., 3]."""
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def axis_angle_to_matrix(rotation_vectors: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] of axis-angle vectors [..., 3] (radians).

    R = I + (sin t / t) K + ((1 - cos t) / t^2) K^2 with K = skew(r), t = |r|; near t = 0 the
    coefficients use their series (1 - t^2 / 6, 1 / 2 - t^2 / 24), so R(0) = I exactly and the
    gradient there is skew(dr).
    """
    squared = (rotation_vectors * rotation_vectors).sum(-1)[..., None, None]
    small = squared < _SMALL_ANGLE_SQUARED
    safe_squared = torch.where(small, torch.ones_like(squared), squared)
    angle = safe_squared.sqrt()
    first = torch.where(small, 1 - squared / 6, torch.sin(angle) / angle)
    second = torch.where(small, 0.5 - squared / 24, (1 - torch.cos(angle)) / safe_squared)
    cross = skew(rotation_vectors)
    identity = torch.eye(3, dtype=rotation_vectors.dtype, device=rotation_vectors.device)
    return identity + first * cross + second * (cross @ cross)


class PoseError(ModelEffect):
    """Per-view rigid corrections of world_to_cam: rotation (axis-angle, 3) and translation (3).

    translation_scale: world units per unit of the translation parameter (the scene size
    suits: it balances the two parameter kinds under one learning rate).
    """

    name = "pose_error"
    diagnosis = DiagnosisFacts(
        family="camera",
        # At the capture distance a small translation moves the image as a rotation does,
        # except for a change of scale, which a distortion or a blur the texture absorbed also
        # leaves: with translations free, this probe explains those better than their own.
        probe_frozen=("translation",),
        confusable=("lens_distortion", "motion_blur"),
        identifiable_when="texture or silhouette edges in every view",
        distinct_from_confusers=True,
    )
    stage = "camera"
    per_view = True
    pins_a_view = True
    default_learning_rate = 0.001
    default_lock_fraction = 0.3

    def __init__(self, view_count: int, translation_scale: float = 1.0, **options) -> None:
        super().__init__(view_count, **options)
        if not translation_scale > 0:
            raise ReconError(
                f"effect {self.name}: translation_scale must be positive, got {translation_scale}"
            )
        self.translation_scale = float(translation_scale)
        self.rotation = torch.nn.Parameter(torch.zeros(self.view_count, 3))
        self.translation = torch.nn.Parameter(torch.zeros(self.view_count, 3))

    def corrections(self) -> torch.Tensor:
        """[V, 4, 4] per-view rigid corrections (the pinned view the identity)."""
        rotation = axis_angle_to_matrix(self.masked(self.rotation))
        translation = self.masked(self.translation) * self.translation_scale
        top = torch.cat([rotation, translation[..., None]], dim=-1)  # [V, 3, 4]
        bottom = torch.zeros_like(top[:, :1])
        bottom[..., 3] = 1.0
        return torch.cat([top, bottom], dim=1)

    def apply_to_cameras(
        self, cameras: Cameras, view_indices: torch.Tensor | None = None
    ) -> Cameras:
        """The cameras with each batch entry's view correction applied (differentiable).

        view_indices: [B] training view per camera; None (held-out views) leaves them as is.
        """
        if view_indices is None:
            return cameras
        corrections = self.select_views(self.corrections(), view_indices, len(cameras))
        world_to_cam = corrections.to(cameras.world_to_cam) @ cameras.world_to_cam
        return replace(cameras, world_to_cam=world_to_cam)

    def forward(self, cameras: Cameras, view_indices: torch.Tensor | None = None) -> Cameras:
        return self.apply_to_cameras(cameras, view_indices)

    def parameters_summary(self) -> dict:
        rotation = self.masked(self.rotation).detach().double()
        translation = self.masked(self.translation).detach().double() * self.translation_scale
        return {
            "rotation_deg": to_list(rotation.norm(dim=-1) * (180.0 / math.pi)),
            "rotation_vectors_deg": to_list(rotation * (180.0 / math.pi)),
            "translations": to_list(translation),
            "translation_norms": to_list(translation.norm(dim=-1)),
            "pinned_view": self.pinned_view,
            "convention": "world_to_cam' = [R | t] @ world_to_cam (camera frame)",
        }
