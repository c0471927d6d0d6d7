"""Cameras in OpenCV axes (x right, y down, z forward) and their projection to clip space.

This module is the only place where OpenGL/Blender camera conventions are converted.

Clip space used by the rasterizer: for a camera-space point (x, y, z) with z > 0 forward,
    clip = (2 fx x / W + (2 cx / W - 1) z,  2 fy y / H + (2 cy / H - 1) z,  z_clip,  z)
so that x_clip / w = 2 u / W - 1 and y_clip / w = 2 v / H - 1, where (u, v) is the pixel position
(column, row) with pixel centres at i + 0.5 and row 0 at the top. NDC y therefore points DOWN
(row 0 is y_ndc = -1), unlike OpenGL. z_clip / w maps [near, far] to [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from recon.errors import ReconError

# Flips y and z: OpenGL/Blender camera axes (x right, y up, camera looks down -z) <-> OpenCV.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


@dataclass
class Cameras:
    """A batch of B pinhole cameras sharing one image size.

    world_to_cam: [B, 4, 4] float32, maps homogeneous world points (column vectors) to OpenCV
        camera space.
    intrinsics: [B, 3, 3] float32 pixel intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
    image_size: (height, width) in pixels.
    near, far: clip distances along +z in world units.
    """

    world_to_cam: torch.Tensor
    intrinsics: torch.Tensor
    image_size: tuple[int, int]
    near: float = 0.05
    far: float = 100.0

    def __post_init__(self) -> None:
        if self.world_to_cam.ndim == 2:
            self.world_to_cam = self.world_to_cam[None]
        if self.intrinsics.ndim == 2:
            self.intrinsics = self.intrinsics[None].expand(self.world_to_cam.shape[0], 3, 3)
        if self.world_to_cam.ndim != 3 or self.world_to_cam.shape[1:] != (4, 4):
            raise ReconError(
                f"cameras.world_to_cam: expected shape [B, 4, 4], got {tuple(self.world_to_cam.shape)}"
            )
        if self.intrinsics.shape != (self.world_to_cam.shape[0], 3, 3):
            raise ReconError(
                f"cameras.intrinsics: expected shape [{self.world_to_cam.shape[0]}, 3, 3], "
                f"got {tuple(self.intrinsics.shape)}"
            )
        height, width = self.image_size
        if int(height) <= 0 or int(width) <= 0:
            raise ReconError(f"cameras.image_size: expected positive (H, W), got {self.image_size}")
        self.image_size = (int(height), int(width))
        if not 0 < self.near < self.far:
            raise ReconError(
                f"cameras: expected 0 < near < far, got near={self.near}, far={self.far}"
            )

    def __len__(self) -> int:
        return self.world_to_cam.shape[0]

    @property
    def device(self) -> torch.device:
        return self.world_to_cam.device

    def to(self, device: torch.device | str) -> Cameras:
        return replace(
            self, world_to_cam=self.world_to_cam.to(device), intrinsics=self.intrinsics.to(device)
        )

    def __getitem__(self, index: int | slice | torch.Tensor) -> Cameras:
        if isinstance(index, int):
            index = slice(index, index + 1)
        return replace(
            self, world_to_cam=self.world_to_cam[index], intrinsics=self.intrinsics[index]
        )

    def with_image_size(self, image_size: tuple[int, int]) -> Cameras:
        """The same cameras at another resolution (intrinsics scaled, field of view kept)."""
        height, width = self.image_size
        scale = torch.tensor(
            [image_size[1] / width, image_size[0] / height, 1.0],
            device=self.intrinsics.device,
            dtype=self.intrinsics.dtype,
        )
        return replace(
            self, intrinsics=self.intrinsics * scale[None, :, None], image_size=image_size
        )

    def centers(self) -> torch.Tensor:
        """Camera centres in world space [B, 3]."""
        rotation = self.world_to_cam[:, :3, :3]
        translation = self.world_to_cam[:, :3, 3]
        return -(rotation.transpose(1, 2) @ translation[..., None])[..., 0]

    def projection(self) -> torch.Tensor:
        """Camera-to-clip matrices [B, 4, 4] (see the module docstring for the clip space)."""
        height, width = self.image_size
        fx, fy = self.intrinsics[:, 0, 0], self.intrinsics[:, 1, 1]
        cx, cy = self.intrinsics[:, 0, 2], self.intrinsics[:, 1, 2]
        skew = self.intrinsics[:, 0, 1]
        projection = torch.zeros(len(self), 4, 4, device=self.device, dtype=self.intrinsics.dtype)
        projection[:, 0, 0] = 2 * fx / width
        projection[:, 0, 1] = 2 * skew / width
        projection[:, 0, 2] = 2 * cx / width - 1
        projection[:, 1, 1] = 2 * fy / height
        projection[:, 1, 2] = 2 * cy / height - 1
        near, far = self.near, self.far
        projection[:, 2, 2] = (far + near) / (far - near)
        projection[:, 2, 3] = -2 * far * near / (far - near)
        projection[:, 3, 2] = 1.0
        return projection

    def world_to_clip(self) -> torch.Tensor:
        """World-to-clip matrices [B, 4, 4]."""
        return self.projection() @ self.world_to_cam

    def project_to_clip(self, points_world: torch.Tensor) -> torch.Tensor:
        """Homogeneous clip positions [B, V, 4] of points_world [V, 3] or [B, V, 3]."""
        if points_world.shape[-1] != 3:
            raise ReconError(
                f"points_world: expected last dimension 3, got shape {tuple(points_world.shape)}"
            )
        ones = torch.ones_like(points_world[..., :1])
        homogeneous = torch.cat([points_world, ones], dim=-1)
        return homogeneous @ self.world_to_clip().transpose(1, 2)

    def project_to_pixels(self, points_world: torch.Tensor) -> torch.Tensor:
        """Pixel positions (column, row) [B, V, 2] of points_world [V, 3] (pixel centres at i+0.5)."""
        clip = self.project_to_clip(points_world)
        height, width = self.image_size
        ndc = clip[..., :2] / clip[..., 3:4]
        scale = torch.tensor([width, height], device=clip.device, dtype=clip.dtype)
        return (ndc + 1) * 0.5 * scale

    def cam_to_world_opengl(self) -> torch.Tensor:
        """OpenGL/Blender camera-to-world matrices [B, 4, 4] (as in NeRF-synthetic JSON)."""
        return world_to_cam_to_opengl_cam_to_world(self.world_to_cam)


def similarity_transformed(cameras: Cameras, scale: float, centre: torch.Tensor) -> Cameras:
    """The same cameras in the frame x' = scale * (x - centre) (a recentred, rescaled world).

    A camera point p = R x + t becomes scale * p = R x' + scale * (R centre + t): the rotation
    is kept, the camera frame scales with the world (projection is unchanged), near and far scale.
    centre: [3] in the old world frame; scale > 0.
    """
    if not scale > 0:
        raise ReconError(f"scale: expected a positive number, got {scale}")
    centre = torch.as_tensor(centre, dtype=cameras.world_to_cam.dtype, device=cameras.device)
    rotation = cameras.world_to_cam[:, :3, :3]
    translation = cameras.world_to_cam[:, :3, 3]
    world_to_cam = cameras.world_to_cam.clone()
    world_to_cam[:, :3, 3] = scale * ((rotation @ centre) + translation)
    return replace(
        cameras, world_to_cam=world_to_cam, near=cameras.near * scale, far=cameras.far * scale
    )


def camera_up_directions(cameras: Cameras) -> torch.Tensor:
    """Each camera's up direction in world space [B, 3] (OpenCV's -y axis)."""
    return -cameras.world_to_cam[:, 1, :3]


def camera_forward_directions(cameras: Cameras) -> torch.Tensor:
    """Each camera's viewing direction in world space [B, 3] (OpenCV's +z axis)."""
    return cameras.world_to_cam[:, 2, :3]


def look_at(
    eyes: torch.Tensor,
    targets: torch.Tensor | None = None,
    up: tuple[float, float, float] = (0, 1, 0),
) -> torch.Tensor:
    """World-to-camera matrices [B, 4, 4] for cameras at eyes [B, 3] looking at targets [B, 3].

    OpenCV axes: z toward the target, x = z x up (right), y = z x x (down in the image).
    """
    if eyes.ndim == 1:
        eyes = eyes[None]
    if targets is None:
        targets = torch.zeros_like(eyes)
    targets = targets.expand_as(eyes)
    up_vector = torch.tensor(up, dtype=eyes.dtype, device=eyes.device).expand_as(eyes)
    forward = torch.nn.functional.normalize(targets - eyes, dim=-1)
    right = torch.linalg.cross(forward, up_vector, dim=-1)
    # Looking straight along up: pick another up so the basis stays defined.
    degenerate = right.norm(dim=-1) < 1e-6
    if bool(degenerate.any()):
        other = torch.tensor([0.0, 0.0, 1.0], dtype=eyes.dtype, device=eyes.device)
        right[degenerate] = torch.linalg.cross(
            forward[degenerate], other.expand_as(forward[degenerate]), dim=-1
        )
    right = torch.nn.functional.normalize(right, dim=-1)
    down = torch.linalg.cross(forward, right, dim=-1)
    rotation = torch.stack([right, down, forward], dim=1)  # rows = camera axes in world
    world_to_cam = torch.eye(4, dtype=eyes.dtype, device=eyes.device).repeat(eyes.shape[0], 1, 1)
    world_to_cam[:, :3, :3] = rotation
    world_to_cam[:, :3, 3] = -(rotation @ eyes[..., None])[..., 0]
    return world_to_cam


def intrinsics_from_fov(
    fov_x_deg: float, image_size: tuple[int, int], fov_y_deg: float | None = None
) -> torch.Tensor:
    """Pixel intrinsics [3, 3] from the horizontal field of view (NeRF's camera_angle_x).

    Square pixels unless fov_y_deg is given; principal point at the image centre.
    """
    height, width = image_size
    if not 0 < fov_x_deg < 180:
        raise ReconError(f"fov_x_deg: expected a value in (0, 180), got {fov_x_deg}")
    focal_x = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    focal_y = focal_x if fov_y_deg is None else 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor(
        [[focal_x, 0.0, width / 2], [0.0, focal_y, height / 2], [0.0, 0.0, 1.0]],
        dtype=torch.float32,
    )


def opengl_cam_to_world_to_world_to_cam(cam_to_world_opengl: torch.Tensor) -> torch.Tensor:
    """Convert OpenGL/Blender camera-to-world [B, 4, 4] to OpenCV world-to-camera [B, 4, 4].

    Raises ReconError when the rotation part is not rigid (orthonormal, det +1).
    """
    check_rigid(cam_to_world_opengl, "transform_matrix")
    flip = _GL_TO_CV.to(cam_to_world_opengl)
    cam_to_world_cv = cam_to_world_opengl @ flip
    return rigid_inverse(cam_to_world_cv)


def world_to_cam_to_opengl_cam_to_world(world_to_cam: torch.Tensor) -> torch.Tensor:
    """Inverse of opengl_cam_to_world_to_world_to_cam."""
    flip = _GL_TO_CV.to(world_to_cam)
    return rigid_inverse(world_to_cam) @ flip


def rigid_inverse(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4] (rotation transposed, translation rotated back)."""
    rotation = transform[..., :3, :3]
    translation = transform[..., :3, 3:]
    inverse = torch.zeros_like(transform)
    inverse[..., :3, :3] = rotation.transpose(-1, -2)
    inverse[..., :3, 3:] = -rotation.transpose(-1, -2) @ translation
    inverse[..., 3, 3] = 1.0
    return inverse


def check_rigid(transform: torch.Tensor, name: str, tolerance: float = 1e-3) -> None:
    """Raise ReconError unless transform [..., 4, 4] is a finite rigid transform."""
    if transform.shape[-2:] != (4, 4):
        raise ReconError(f"{name}: expected 4x4 matrices, got shape {tuple(transform.shape)}")
    if not bool(torch.isfinite(transform).all()):
        raise ReconError(f"{name}: contains NaN or inf")
    rotation = transform[..., :3, :3].double()
    identity = torch.eye(3, dtype=rotation.dtype, device=rotation.device)
    orthogonality = (rotation.transpose(-1, -2) @ rotation - identity).abs().amax(dim=(-1, -2))
    determinant = torch.linalg.det(rotation)
    bottom = transform[..., 3, :].double() - torch.tensor(
        [0, 0, 0, 1.0], dtype=torch.float64, device=transform.device
    )
    bad = (
        (orthogonality > tolerance)
        | ((determinant - 1).abs() > tolerance)
        | (bottom.abs().amax(-1) > tolerance)
    )
    if bool(bad.any()):
        index = int(torch.nonzero(bad.reshape(-1))[0])
        raise ReconError(
            f"{name}: matrix {index} is not rigid (expected orthonormal rotation with det 1 and "
            f"bottom row [0, 0, 0, 1]; got max |R^T R - I| = {float(orthogonality.reshape(-1)[index]):.3g}, "
            f"det = {float(determinant.reshape(-1)[index]):.4g})"
        )


def orbit_cameras(
    count: int,
    image_size: tuple[int, int],
    distance: float = 3.0,
    fov_x_deg: float = 40.0,
    elevation_deg: float = 20.0,
    device: torch.device | str = "cpu",
) -> Cameras:
    """count cameras on a ring around the origin (y up), a convenience for tests and demos."""
    azimuth = torch.arange(count, dtype=torch.float32) * (2 * math.pi / count)
    elevation = math.radians(elevation_deg)
    eyes = distance * torch.stack(
        [
            torch.sin(azimuth) * math.cos(elevation),
            torch.full_like(azimuth, math.sin(elevation)),
            torch.cos(azimuth) * math.cos(elevation),
        ],
        dim=-1,
    )
    intrinsics = intrinsics_from_fov(fov_x_deg, image_size)
    return Cameras(
        world_to_cam=look_at(eyes).to(device),
        intrinsics=intrinsics[None].repeat(count, 1, 1).to(device),
        image_size=image_size,
        near=max(0.01, distance * 0.05),
        far=distance * 10,
    )
