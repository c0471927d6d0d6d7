"""The full-frame vignetting falloff from a dataset's flat-field frames.

A flat-field frame is the capture camera looking at a uniformly lit card that fills the frame
(recon.config.run_config.FlatFieldConfig; data_synth writes it as the dataset's flat_field
split). Whatever is not flat in it is the camera's falloff: exposure and white balance scale a
frame as a whole, and a blur, a lens distortion or a pose error leave a uniform field uniform.

The object's own pixels reach only part of the way to the corners (0.57-0.61 of the half
diagonal on the benchmark); a falloff model fitted to them extrapolates beyond, and a
mechanical (barrel) falloff that sets in further out is invisible to it. The frames measure it
where it is defined: the mean of the four corner pixels and of a circle half-way to the corner,
each over the image centre, read off local quadratic fits to the frames' mean (so noise
averages and the value at a pixel centre needs no smooth global model).
"""

from __future__ import annotations

import math

import torch

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.residuals import luminance_of
from recon.errors import ReconError

# Points round the half-way circle (as data_synth realises its half_radius_falloff).
CIRCLE_POINTS = 64
# Radial bins of the profile that the figure draws (0 to the corner).
PROFILE_BINS = 16
# A pixel at or above this (an 8-bit white, or a sensor's full well normalised to 1) is
# clipped; a frame with too many (diagnose.flat_field_maximum_clipped_share) is refused:
# clipping flattens the falloff it measures.
CLIPPED_VALUE = 0.999


def local_value(image: torch.Tensor, column: float, row: float, half_window: int) -> float:
    """The value at (column, row) (pixel units, pixel centres at +0.5) of a quadratic fitted by
    least squares to image [H, W]'s pixels within half_window pixels of it."""
    height, width = image.shape
    first_row = max(0, int(math.floor(row)) - half_window)
    last_row = min(height, int(math.floor(row)) + half_window + 1)
    first_column = max(0, int(math.floor(column)) - half_window)
    last_column = min(width, int(math.floor(column)) + half_window + 1)
    rows = torch.arange(first_row, last_row, dtype=image.dtype) + 0.5 - row
    columns = torch.arange(first_column, last_column, dtype=image.dtype) + 0.5 - column
    dv, du = torch.meshgrid(rows, columns, indexing="ij")
    du, dv = du.reshape(-1), dv.reshape(-1)
    basis = torch.stack([torch.ones_like(du), du, dv, du * du, du * dv, dv * dv], -1)
    values = image[first_row:last_row, first_column:last_column].reshape(-1, 1)
    solution = torch.linalg.lstsq(basis, values).solution
    return float(solution[0, 0])


def measure_flat_field(
    frames: torch.Tensor,
    response_exponent: float | None = None,
    settings: DiagnoseConfig | None = None,
) -> dict:
    """Corner and half-way falloff of frames [N, H, W, 3] (linear), each over the image centre.

    settings: the local fits' half window and the largest clipped share a frame may have
    (diagnose.flat_field_*; the config's defaults when None). The window (13 x 13 at 6,
    clipped at the frame's edge) is wide enough to average noise, narrow enough that a
    quadratic follows a falloff that steepens toward the corners.

    response_exponent: a response curve's effective exponent g when one was found (observed
    ~ true^g); the measured ratios are raised to 1/g to undo it. Returns corner_falloff,
    half_radius_falloff, per-frame corner falloffs, deviation (the larger distance of either
    falloff from 1), a radial profile (normalised radius, mean relative luminance) and the
    frame count."""
    settings = settings or DiagnoseConfig()
    half_window = settings.flat_field_half_window
    maximum_clipped = settings.flat_field_maximum_clipped_share
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ReconError(
            f"flat_field.frames: expected shape [N >= 1, H, W, 3], got {tuple(frames.shape)}"
        )
    count, height, width, _ = frames.shape
    if not bool(torch.isfinite(frames).all()):
        raise ReconError("flat_field.frames: non-finite values (NaN or infinity)")
    luminance = luminance_of(frames.double())
    medians = luminance.flatten(1).median(dim=1).values
    peaks = frames.double().amax(dim=-1).flatten(1)
    for index in range(count):
        if float(medians[index]) <= 0:
            raise ReconError(f"flat_field.frames[{index}]: no light (median luminance 0)")
        # Clipped pixels flatten a falloff: an over-exposed card reads as no vignetting.
        clipped = float((peaks[index] >= CLIPPED_VALUE).double().mean())
        if clipped > maximum_clipped:
            raise ReconError(
                f"flat_field.frames[{index}]: {100 * clipped:.1f} % of the pixels clipped at "
                f"{CLIPPED_VALUE} or above (at most {100 * maximum_clipped:.0f} % expected); "
                "shoot the card darker"
            )
    # Exposure and white balance scale a frame as a whole: each is taken relative to itself.
    luminance = luminance / medians[:, None, None]
    exponent = 1.0 if not response_exponent else float(response_exponent)
    corners = [(0.5, 0.5), (width - 0.5, 0.5), (0.5, height - 0.5), (width - 0.5, height - 0.5)]
    half_radius = 0.25 * math.hypot(height, width)
    angles = [2 * math.pi * index / CIRCLE_POINTS for index in range(CIRCLE_POINTS)]
    circle = [
        (0.5 * width + half_radius * math.cos(angle), 0.5 * height + half_radius * math.sin(angle))
        for angle in angles
    ]

    def mean_value(image: torch.Tensor, points: list[tuple[float, float]]) -> float:
        return sum(local_value(image, u, v, half_window) for u, v in points) / len(points)

    def corner_falloff_of(image: torch.Tensor) -> tuple[float, float]:
        """(corner over centre, undone by the exponent; the centre value)."""
        centre = local_value(image, 0.5 * width, 0.5 * height, half_window)
        return (mean_value(image, corners) / centre) ** (1 / exponent), centre

    mean_image = luminance.mean(0)
    corner_falloff, centre_value = corner_falloff_of(mean_image)
    half_radius_falloff = (mean_value(mean_image, circle) / centre_value) ** (1 / exponent)
    # Per frame the corners only (the spread of the corner reading over frames).
    per_frame = (
        [corner_falloff_of(frame)[0] for frame in luminance] if count > 1 else [corner_falloff]
    )
    rows = torch.arange(height, dtype=torch.float64) + 0.5 - 0.5 * height
    columns = torch.arange(width, dtype=torch.float64) + 0.5 - 0.5 * width
    radius = torch.hypot(rows[:, None], columns[None, :]) / (0.5 * math.hypot(height, width))
    bins = torch.linspace(0.0, float(radius.max()) + 1e-9, PROFILE_BINS + 1, dtype=torch.float64)
    index = torch.bucketize(radius.reshape(-1), bins[1:-1])
    flat = mean_image.reshape(-1)
    sums = torch.zeros(PROFILE_BINS, dtype=torch.float64).index_add_(0, index, flat)
    counts = torch.bincount(index, minlength=PROFILE_BINS).double()
    profile = (sums / counts.clamp_min(1) / centre_value).clamp_min(0) ** (1 / exponent)
    return {
        "corner_falloff": round(corner_falloff, 5),
        "half_radius_falloff": round(half_radius_falloff, 5),
        "corner_falloff_per_frame": [round(value, 5) for value in per_frame],
        "deviation": round(max(abs(1 - corner_falloff), abs(1 - half_radius_falloff)), 5),
        "response_exponent": exponent,
        "frames": count,
        "profile_radius": [round(float(value), 4) for value in 0.5 * (bins[1:] + bins[:-1])],
        "profile": [round(float(value), 5) for value in profile],
    }
