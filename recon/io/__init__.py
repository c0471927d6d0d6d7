"""File input/output: images (PNG sRGB <-> linear, EXR), meshes, capture datasets, atomic writes."""

from recon.io.atomic import atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text
from recon.io.datasets import (
    CaptureSet,
    llff_to_world_to_cam,
    read_llff,
    read_nerf_synthetic,
    write_nerf_synthetic,
)
from recon.io.images import (
    linear_to_srgb,
    read_exr,
    read_exr_channels,
    read_image,
    read_png,
    read_png_pixels,
    save_contact_sheet,
    srgb_to_linear,
    write_exr,
    write_png,
)
from recon.io.meshes import load_mesh, load_texture_image, save_mesh

__all__ = [
    "CaptureSet",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "linear_to_srgb",
    "llff_to_world_to_cam",
    "load_mesh",
    "load_texture_image",
    "read_exr",
    "read_exr_channels",
    "read_image",
    "read_llff",
    "read_nerf_synthetic",
    "read_png",
    "read_png_pixels",
    "save_contact_sheet",
    "save_mesh",
    "srgb_to_linear",
    "write_exr",
    "write_nerf_synthetic",
    "write_png",
]
