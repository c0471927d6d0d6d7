"""Camera-stage world effect: pose error (the dataset records perturbed cameras).

The images stay rendered from the true cameras; the cameras written to the dataset are the true
ones composed with a small random rigid motion per view, as a structure-from-motion solve leaves
them. The model side refines poses with small per-view corrections; the world draws isotropic
rotations about a uniformly random axis and translations scaled by the camera's distance.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from data_synth.effects.base import AppliedEffect, Capture
from data_synth.effects.world_effect import (
    ParameterSpec,
    WorldEffect,
    check_capture,
    round_float,
    sample_uniform,
    standard_normal,
    to_list,
)
from recon.camera import Cameras


def axis_angle_to_matrix(rotation_vectors: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [B, 3, 3] of axis-angle vectors [B, 3] (radians), by Rodrigues' formula."""
    angle = rotation_vectors.norm(dim=-1, keepdim=True)  # [B, 1]
    axis = rotation_vectors / angle.clamp(min=1e-30)
    zero = torch.zeros_like(axis[:, 0])
    cross = torch.stack(
        [
            torch.stack([zero, -axis[:, 2], axis[:, 1]], dim=-1),
            torch.stack([axis[:, 2], zero, -axis[:, 0]], dim=-1),
            torch.stack([-axis[:, 1], axis[:, 0], zero], dim=-1),
        ],
        dim=1,
    )
    identity = torch.eye(3, dtype=rotation_vectors.dtype, device=rotation_vectors.device)
    sine, cosine = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    return identity + sine * cross + (1 - cosine) * (cross @ cross)


class PoseError(WorldEffect):
    """Per-view rigid pose error in the camera frame: world_to_cam' = [R_d | t_d] world_to_cam.

    R_d rotates by rotation_deg * N(0, 1) degrees about a uniformly random axis (about the
    camera's own centre); t_d ~ N(0, (translation * distance)^2 I) with distance the camera's
    distance from the world origin (where data_synth centres its scenes). pin_first_view keeps
    view 0 exact. Images and alpha are unchanged. Realised: per-view rotation angles (degrees),
    rotation vectors (degrees), camera-frame translations and camera-centre shifts (world
    units).
    """

    name = "pose_error"
    stage = "camera"
    PARAMETERS = {
        "rotation_deg": ParameterSpec(
            0.5, 0.0, 30.0, "std of the per-view rotation angle in degrees"
        ),
        "translation": ParameterSpec(
            0.005, 0.0, 0.5, "std of each translation component relative to the camera distance"
        ),
        "pin_first_view": ParameterSpec(False, 0, 1, "leave view 0 unperturbed", kind="bool"),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """rotation 0.2-0.8 degrees, translation 0.2-1 % of the camera distance (about 0.5-3 px
        at 128 px and 40 degrees field of view), every view perturbed."""
        return {
            "rotation_deg": round_float(sample_uniform(generator, 0.2, 0.8)),
            "translation": round_float(sample_uniform(generator, 0.002, 0.01)),
            "pin_first_view": False,
        }

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """capture.cameras.world_to_cam [B, 4, 4] <- perturbation [B, 4, 4] @ world_to_cam."""
        count = check_capture(capture, self.name)[0]
        cameras = capture.cameras
        like = torch.empty(0, dtype=torch.float64, device=cameras.world_to_cam.device)
        draws = standard_normal((count, 7), generator, like)
        axes = torch.nn.functional.normalize(draws[:, :3], dim=-1)
        angles_deg = float(self.parameters["rotation_deg"]) * draws[:, 3]
        world_to_cam = cameras.world_to_cam.double()
        distance = cameras.centers().double().norm(dim=-1)  # [B]
        translations = (float(self.parameters["translation"]) * distance)[:, None] * draws[:, 4:]
        if self.parameters["pin_first_view"]:
            angles_deg[0] = 0.0
            translations[0] = 0.0
        rotation_vectors = axes * torch.deg2rad(angles_deg)[:, None]
        perturbation = torch.eye(4, dtype=torch.float64, device=like.device).repeat(count, 1, 1)
        perturbation[:, :3, :3] = axis_angle_to_matrix(rotation_vectors)
        perturbation[:, :3, 3] = translations
        perturbed = perturbation @ world_to_cam
        capture.cameras = replace(cameras, world_to_cam=perturbed.to(cameras.world_to_cam.dtype))
        # The centre moves by -R^T R_d^T t_d: as far as |t_d|, in world axes.
        centre_shift = capture.cameras.centers().double() - cameras.centers().double()
        return AppliedEffect(
            self.name,
            {
                "rotation_deg": to_list(angles_deg.abs()),
                "rotation_vectors_deg": to_list(axes * angles_deg[:, None]),
                "translations": to_list(translations),
                "centre_shifts": to_list(centre_shift),
                "rotation_std_deg": self.parameters["rotation_deg"],
                "translation_std": self.parameters["translation"],
                "pin_first_view": self.parameters["pin_first_view"],
            },
        )
