"""Evaluation metrics: image metrics on held-out views and geometry metrics against a reference."""

from recon.metrics.geometry import (
    geometry_metrics,
    mesh_stats,
    per_vertex_error,
    sample_surface,
    sampling_floor,
)
from recon.metrics.image import (
    PSNR_CAP_DB,
    ViewMetric,
    composite_over,
    fit_channel_scale,
    image_metrics,
    mae,
    psnr_linear,
    psnr_srgb,
    scale_invariant_psnr,
    ssim,
    to_display,
)

__all__ = [
    "PSNR_CAP_DB",
    "ViewMetric",
    "composite_over",
    "fit_channel_scale",
    "geometry_metrics",
    "image_metrics",
    "mae",
    "mesh_stats",
    "per_vertex_error",
    "psnr_linear",
    "psnr_srgb",
    "sample_surface",
    "sampling_floor",
    "scale_invariant_psnr",
    "ssim",
    "to_display",
]
