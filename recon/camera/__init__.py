"""Cameras (OpenCV axes), projection to clip space, OpenGL/Blender conversion."""

from recon.camera.cameras import (
    Cameras,
    camera_forward_directions,
    camera_up_directions,
    check_rigid,
    intrinsics_from_fov,
    look_at,
    opengl_cam_to_world_to_world_to_cam,
    orbit_cameras,
    rigid_inverse,
    similarity_transformed,
    world_to_cam_to_opengl_cam_to_world,
)

__all__ = [
    "Cameras",
    "camera_forward_directions",
    "camera_up_directions",
    "check_rigid",
    "intrinsics_from_fov",
    "look_at",
    "opengl_cam_to_world_to_world_to_cam",
    "orbit_cameras",
    "rigid_inverse",
    "similarity_transformed",
    "world_to_cam_to_opengl_cam_to_world",
]
