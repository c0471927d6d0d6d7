"""Cameras (OpenCV axes), projection to clip space, OpenGL/Blender conversion."""

from recon.camera.cameras import (
    Cameras,
    check_rigid,
    intrinsics_from_fov,
    look_at,
    opengl_cam_to_world_to_world_to_cam,
    orbit_cameras,
    rigid_inverse,
    world_to_cam_to_opengl_cam_to_world,
)

__all__ = [
    "Cameras",
    "check_rigid",
    "intrinsics_from_fov",
    "look_at",
    "opengl_cam_to_world_to_world_to_cam",
    "orbit_cameras",
    "rigid_inverse",
    "world_to_cam_to_opengl_cam_to_world",
]
