"""A lens distortion measured on a dataset's line-target frames (the plumb-line method).

A line-target frame is the capture camera looking at a card of straight stripes that fills the
frame (recon.config.run_config.LineTargetConfig; data_synth writes it as the dataset's
line_target split). A pinhole camera images a straight line as a straight line whatever the
card's pose, so the stripes' edges bend only by the lens. Brown's plumb-line method: find the
distortion whose inverse makes every edge straight again.

The measurement needs neither the card's pose nor its pattern: each frame's edges are found as
the sub-pixel crossings of the mid level between the local darkest and brightest values along
the image columns (stripes nearer horizontal) or rows (nearer vertical), linked into lines from
one column to the next. Exposure, white balance and a response curve change the levels, not
where an edge crosses their middle; a slow vignetting gradient moves the local mid level with it;
a symmetric blur widens an edge about its centre; a motion blur shifts a whole frame's edges
alike. None of them bends a line.

The undistortion that straightens the lines is fitted by least squares over all frames (the
Brown-Conrady polynomial on the distorted coordinates: radial q1, q2, tangential q3, q4); what
it moves the image corners by is the distortion's size. Its standard error comes from the run
itself: leaving each frame out in turn (a camera has one lens, so the frames must agree), or
the fit's own covariance with fewer than three frames, whichever is larger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.optimize import least_squares

from recon.diagnose.residuals import luminance_of
from recon.errors import ReconError

# Pixels at each image border where no edge crossing is kept (the local level filters reach
# past the frame there).
BORDER_PIXELS = 1
# A crossing is kept where the local contrast is at least this share of the frame's median:
# the stripes' edges, not noise on a flat patch.
MINIMUM_CONTRAST_SHARE = 0.5
# A crossing continues a line from the previous column when it moved by less than this many
# pixels (the stripes turn by tens of degrees at most: well under a pixel per column).
LINK_PIXELS = 1.0
# A line must span at least this share of the frame's columns to count (short runs are
# fragments near the corners, where a turn cannot be told from a bend).
MINIMUM_LINE_SHARE = 0.3
# Pixels from the nearest edge crossing beyond which a stripe's level is read (a blur of the
# blind check's sizes, 1 px defocus and 2 px motion paths at 48 px, leaves them).
PLATEAU_CLEARANCE = 2.0
# Largest second difference along the scan, as a share of the column's contrast, of a pixel
# whose level is read (noise of a few per cent of the contrast passes).
PLATEAU_FLATNESS = 0.05
# Fewest black (and white) plateau pixels a frame's level ratio is read from.
MINIMUM_PLATEAU_PIXELS = 20
# The undistortion's terms: radial q1, q2 and tangential q3, q4.
UNDISTORTION_TERMS = 4


@dataclass
class Line:
    """One edge line of one frame: pixel positions u, v [P] (pixel centres at i + 0.5)."""

    frame: int
    u: np.ndarray
    v: np.ndarray


def _half_period(luminance: np.ndarray) -> float:
    """The stripes' half period along axis 0 of luminance [H, W] (pixels), from how often each
    column crosses its median."""
    centred = luminance - np.median(luminance, axis=0, keepdims=True)
    crossings = (np.signbit(centred[1:]) != np.signbit(centred[:-1])).sum(axis=0)
    mean = float(crossings.mean())
    return luminance.shape[0] / mean if mean > 0 else float("inf")


def _column_crossings(luminance: np.ndarray) -> list[list[tuple[float, int]]]:
    """Per column of luminance [H, W] (stripes along axis 1): the sub-pixel rows (pixel centres
    at i + 0.5) where the profile crosses its local mid level, with the crossing's direction
    (+1 dark to bright going down, -1 the other way)."""
    height, width = luminance.shape
    half = _half_period(luminance)
    if not math.isfinite(half):
        return [[] for _ in range(width)]
    window = max(3, int(3 * half) | 1)
    high = maximum_filter1d(luminance, window, axis=0, mode="nearest")
    low = minimum_filter1d(luminance, window, axis=0, mode="nearest")
    middle, contrast = 0.5 * (high + low), high - low
    floor = MINIMUM_CONTRAST_SHARE * float(np.median(contrast))
    offset = luminance - middle
    first, second = offset[:-1], offset[1:]  # rows r and r + 1, [H - 1, W]
    rows = np.arange(height - 1)[:, None]
    crossing = (
        ((first < 0) != (second < 0))
        & (first != second)
        & (np.minimum(contrast[:-1], contrast[1:]) >= floor)
        & (rows >= BORDER_PIXELS)
        & (rows < height - 1 - BORDER_PIXELS)
    )
    found_rows, found_columns = np.nonzero(crossing)
    start, end = first[crossing], second[crossing]
    positions = found_rows + 0.5 + start / (start - end)
    directions = np.where(end > start, 1, -1)
    # np.nonzero runs row by row; each column's crossings in row order.
    order = np.lexsort((found_rows, found_columns))
    columns: list[list[tuple[float, int]]] = [[] for _ in range(width)]
    for index in order:
        columns[found_columns[index]].append((float(positions[index]), int(directions[index])))
    return columns


def _linked(columns: list[list[tuple[float, int]]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Crossings linked column to column into lines: (columns, rows) per line with at least
    MINIMUM_LINE_SHARE of the columns."""
    finished: list[list[tuple[int, float]]] = []
    active: list[tuple[int, list[tuple[int, float]]]] = []  # (direction, points)
    for column, found in enumerate(columns):
        continuing: list[tuple[int, list[tuple[int, float]]]] = []
        taken: set[int] = set()
        for position, direction in found:
            best, distance = None, LINK_PIXELS
            for index, (line_direction, points) in enumerate(active):
                if index in taken or line_direction != direction:
                    continue
                last_column, last_position = points[-1]
                if last_column == column - 1 and abs(last_position - position) < distance:
                    best, distance = index, abs(last_position - position)
            if best is None:
                continuing.append((direction, [(column, position)]))
            else:
                taken.add(best)
                active[best][1].append((column, position))
                continuing.append(active[best])
        finished += [points for index, (_, points) in enumerate(active) if index not in taken]
        active = continuing
    finished += [points for _, points in active]
    shortest = MINIMUM_LINE_SHARE * len(columns)
    return [
        (np.array([c for c, _ in points]) + 0.5, np.array([p for _, p in points]))
        for points in finished
        if len(points) >= shortest
    ]


def _stripes_across_columns(image: np.ndarray) -> bool:
    """Whether the stripes of luminance [H, W] are nearer horizontal (they change down the
    columns more than along the rows)."""
    vertical = float(np.abs(np.diff(image, axis=0)).mean())
    horizontal = float(np.abs(np.diff(image, axis=1)).mean())
    return vertical >= horizontal


def _plateau_ratio(image: np.ndarray) -> float:
    """The black stripes' luminance over the white ones' in luminance [H, W] (stripes along
    axis 1), on the pixels at least PLATEAU_CLEARANCE_PIXELS from every edge crossing of their
    column (a blur of the edges leaves them), the white level a quadratic over the frame (a
    falloff scales both levels alike, so the ratio is taken against the white level there).
    NaN where a frame has too few such pixels."""
    height, width = image.shape
    centres = np.arange(height) + 0.5
    # A plateau is flat: a blur as wide as the stripes rounds their middles (curvature) even
    # where the slope is zero, and their levels there are no longer the card's.
    curvature = np.full_like(image, np.inf)
    curvature[1:-1] = np.abs(image[:-2] - 2 * image[1:-1] + image[2:])
    high = maximum_filter1d(image, height, axis=0, mode="nearest")
    low = minimum_filter1d(image, height, axis=0, mode="nearest")
    flat = curvature <= PLATEAU_FLATNESS * (high - low)
    dark = np.zeros((height, width), dtype=bool)
    bright = np.zeros((height, width), dtype=bool)
    for column, found in enumerate(_column_crossings(image)):
        if len(found) < 2:
            continue
        positions = np.array([position for position, _ in found])
        clear = np.abs(centres[:, None] - positions[None, :]).min(axis=1) >= PLATEAU_CLEARANCE
        # Between the first and last crossing: the stripes there are whole.
        clear &= (centres > positions.min()) & (centres < positions.max()) & flat[:, column]
        # A pixel is in a black stripe when the next crossing below it rises (dark to bright
        # going down), in a white one when it falls.
        below = np.searchsorted(positions, centres)
        rising = np.array([direction for _, direction in found] + [0])[below]
        dark[:, column] = clear & (rising > 0)
        bright[:, column] = clear & (rising < 0)
    if dark.sum() < MINIMUM_PLATEAU_PIXELS or bright.sum() < MINIMUM_PLATEAU_PIXELS:
        return float("nan")
    rows, columns = np.mgrid[0:height, 0:width] + 0.5

    def design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = u / width - 0.5, v / height - 0.5
        return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)

    white = np.linalg.lstsq(design(columns[bright], rows[bright]), image[bright], rcond=None)[0]
    return float((image[dark] / (design(columns[dark], rows[dark]) @ white)).mean())


def card_exponent_allowance(dark_share: float, contrast_tolerance: float) -> float:
    """How far from 1 a linear camera's exponent over the card's two levels can read when the
    card's true contrast is dark_share within a relative contrast_tolerance: a black level of
    dark_share (1 + e) reads k = 1 + ln(1 + e) / ln(dark_share), largest for e = -tolerance."""
    if contrast_tolerance <= 0.0:
        return 0.0
    return -math.log1p(-contrast_tolerance) / -math.log(dark_share)


def level_exponents(frames: torch.Tensor, dark_share: float) -> list[float]:
    """Per frame of frames [N, H, W, 3] (linear): the exponent k of the camera's response over
    the card's two levels, observed black / white = dark_share^k (1: linear; a frame whose
    levels could not be read is left out)."""
    luminance = luminance_of(frames.double()).cpu().numpy()
    exponents = []
    for image in luminance:
        ratio = _plateau_ratio(image if _stripes_across_columns(image) else image.T)
        if math.isfinite(ratio) and ratio > 0:
            exponents.append(math.log(ratio) / math.log(dark_share))
    return exponents


def edge_lines(frames: torch.Tensor) -> list[Line]:
    """The stripes' edge lines in frames [N, H, W, 3] (linear): per frame, scanned along the
    columns where the stripes are nearer horizontal (the vertical gradient is the larger), else
    along the rows."""
    luminance = luminance_of(frames.double()).cpu().numpy()
    lines = []
    for index, image in enumerate(luminance):
        if _stripes_across_columns(image):
            for columns, rows in _linked(_column_crossings(image)):
                lines.append(Line(index, columns, rows))
        else:
            for rows, columns in _linked(_column_crossings(image.T)):
                lines.append(Line(index, columns, rows))
    return lines


def undistorted(x: np.ndarray, y: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Brown-Conrady polynomial on normalised coordinates (x, y) with radial q[0], q[1] and
    tangential q[2], q[3] (OpenCV's p1, p2)."""
    squared = x * x + y * y
    radial = 1 + squared * (q[0] + squared * q[1])
    new_x = x * radial + 2 * q[2] * x * y + q[3] * (squared + 2 * x * x)
    new_y = y * radial + q[2] * (squared + 2 * y * y) + 2 * q[3] * x * y
    return new_x, new_y


def _straightness(lines: list[Line], intrinsics: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Each point's distance (pixels) from its line's total-least-squares fit once undistorted."""
    residuals = []
    for line in lines:
        fx, fy, cx, cy = intrinsics[line.frame]
        x, y = undistorted((line.u - cx) / fx, (line.v - cy) / fy, q)
        points = np.stack([fx * x, fy * y], axis=1)
        centred = points - points.mean(axis=0)
        # The normal is the direction of least spread.
        _, _, directions = np.linalg.svd(centred, full_matrices=False)
        residuals.append(centred @ directions[-1])
    return np.concatenate(residuals)


def _fit(lines: list[Line], intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The undistortion q [4] that straightens the lines, its covariance [4, 4] and the
    residuals [P] (pixels)."""
    result = least_squares(
        lambda q: _straightness(lines, intrinsics, q), np.zeros(UNDISTORTION_TERMS), method="lm"
    )
    residuals = result.fun
    freedom = max(1, residuals.size - UNDISTORTION_TERMS - 2 * len(lines))
    variance = float(residuals @ residuals) / freedom
    covariance = np.linalg.pinv(result.jac.T @ result.jac) * variance
    return result.x, covariance, residuals


def corner_shift(q: np.ndarray, intrinsics: np.ndarray, image_size: tuple[int, int]) -> float:
    """Mean displacement (pixels) of the four image corners under the undistortion q."""
    height, width = image_size
    fx, fy, cx, cy = intrinsics
    u = np.array([0.0, width, 0.0, width])
    v = np.array([0.0, 0.0, height, height])
    x, y = (u - cx) / fx, (v - cy) / fy
    new_x, new_y = undistorted(x, y, q)
    return float(np.hypot(fx * (new_x - x), fy * (new_y - y)).mean())


def forward_coefficients(q: np.ndarray, intrinsics: np.ndarray, image_size) -> dict[str, float]:
    """The distortion (k1, k2, p1, p2; recon's and OpenCV's forward model) whose inverse is the
    undistortion q, by least squares over the frame: distorted = forward(undistorted)."""
    height, width = image_size
    fx, fy, cx, cy = intrinsics
    rows, columns = np.meshgrid(np.linspace(0, height, 9), np.linspace(0, width, 9), indexing="ij")
    x_distorted, y_distorted = (columns.ravel() - cx) / fx, (rows.ravel() - cy) / fy
    x, y = undistorted(x_distorted, y_distorted, q)
    squared = x * x + y * y
    # x_d - x = x (k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2), and y alike: linear in k, p.
    design = np.concatenate(
        [
            np.stack([x * squared, x * squared**2, 2 * x * y, squared + 2 * x * x], axis=1),
            np.stack([y * squared, y * squared**2, squared + 2 * y * y, 2 * x * y], axis=1),
        ]
    )
    target = np.concatenate([x_distorted - x, y_distorted - y])
    solution = np.linalg.lstsq(design, target, rcond=None)[0]
    return {
        key: round(float(value), 6)
        for key, value in zip(("k1", "k2", "p1", "p2"), solution, strict=True)
    }


def measure_line_target(
    frames: torch.Tensor, intrinsics: torch.Tensor, dark_share: float | None = None
) -> dict:
    """The lens distortion that the stripes' edges in frames [N, H, W, 3] (linear) show, seen
    through cameras with intrinsics [N, 3, 3].

    Returns corner_shift_pixels (the distortion's mean displacement of the image corners),
    standard_error (pixels: leave-one-frame-out with three frames or more, else the fit's own,
    whichever is larger), the fitted forward coefficients (parameters: k1, k2, p1, p2), the
    lines' RMS distance from straight before and after (pixels), and the lines, points and
    frames it rests on. With dark_share (the card's black stripes' radiance over its white
    ones'), also levels: the response's exponent over the card's two levels (level_exponents),
    their mean, its standard error over the frames (None with fewer than two) and the
    per-frame values. ReconError where the frames show too few lines to fit."""
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise ReconError(
            f"line_target.frames: expected shape [N >= 1, H, W, 3], got {tuple(frames.shape)}"
        )
    if intrinsics.shape != (frames.shape[0], 3, 3):
        raise ReconError(
            f"line_target.intrinsics: expected shape [{frames.shape[0]}, 3, 3], "
            f"got {tuple(intrinsics.shape)}"
        )
    if not bool(torch.isfinite(frames).all()):
        raise ReconError("line_target.frames: non-finite values (NaN or infinity)")
    count, height, width = frames.shape[:3]
    matrices = intrinsics.double().cpu().numpy()
    parameters = np.stack(
        [matrices[:, 0, 0], matrices[:, 1, 1], matrices[:, 0, 2], matrices[:, 1, 2]], axis=1
    )
    lines = edge_lines(frames)
    points = sum(line.u.size for line in lines)
    if len(lines) < 3 or points < 4 * (UNDISTORTION_TERMS + 2 * len(lines)) // 3:
        raise ReconError(
            f"line_target.frames: {len(lines)} straight edges found in {count} frames "
            "(at least 3 expected): the frames should show a card of black and white stripes "
            "filling the frame"
        )
    q, covariance, residuals = _fit(lines, parameters)
    size = (height, width)
    shift = corner_shift(q, parameters[0], size)
    # The delta method: the shift's gradient in q (central differences).
    gradient = np.zeros(UNDISTORTION_TERMS)
    for term in range(UNDISTORTION_TERMS):
        step = np.zeros(UNDISTORTION_TERMS)
        step[term] = 1e-6
        gradient[term] = (
            corner_shift(q + step, parameters[0], size)
            - corner_shift(q - step, parameters[0], size)
        ) / 2e-6
    formal = math.sqrt(max(0.0, float(gradient @ covariance @ gradient)))
    framed = sorted({line.frame for line in lines})
    jackknife = float("nan")
    if len(framed) >= 3:
        left_out = []
        for frame in framed:
            kept = [line for line in lines if line.frame != frame]
            left_out.append(corner_shift(_fit(kept, parameters)[0], parameters[0], size))
        values = np.array(left_out)
        jackknife = math.sqrt(
            (values.size - 1) / values.size * float(((values - values.mean()) ** 2).sum())
        )
    error = max(formal, jackknife) if math.isfinite(jackknife) else formal
    before = _straightness(lines, parameters, np.zeros(UNDISTORTION_TERMS))
    levels = None
    if dark_share is not None:
        exponents = np.array(level_exponents(frames, dark_share))
        spread = (
            round(float(exponents.std(ddof=1)) / math.sqrt(exponents.size), 5)
            if exponents.size >= 2
            else None
        )
        levels = {
            "exponent": round(float(exponents.mean()), 5) if exponents.size else None,
            "standard_error": spread,
            "per_frame": [round(float(value), 5) for value in exponents],
            "dark_share": dark_share,
        }
    return {
        "levels": levels,
        "corner_shift_pixels": round(shift, 4),
        "standard_error": round(error, 4),
        "standard_error_formal": round(formal, 4),
        "standard_error_jackknife": round(jackknife, 4) if math.isfinite(jackknife) else None,
        "parameters": forward_coefficients(q, parameters[0], size),
        "undistortion": [round(float(value), 6) for value in q],
        "straightness_before_pixels": round(float(np.sqrt((before**2).mean())), 4),
        "straightness_after_pixels": round(float(np.sqrt((residuals**2).mean())), 4),
        "lines": len(lines),
        "points": int(points),
        "frames": count,
        "frames_with_lines": len(framed),
        # What the figure needs to draw the field: fx, fy, cx, cy and (H, W).
        "intrinsics": [round(float(value), 4) for value in parameters[0]],
        "image_size": [height, width],
    }
