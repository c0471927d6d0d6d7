"""Pictures of where the sim-to-real gap lies, one PNG per domain plus the worst views.

Every figure is drawn from a DiagnosisData and where_analysis's output, with matplotlib's Agg
backend, and written atomically (recon.io.atomic.atomic_path), so a reader never sees half a PNG.
Residual maps use a diverging colour map centred at zero (red: observed brighter than rendered,
blue: darker), with symmetric limits at the 99th percentile of |residual| so one outlier does not
wash the map out.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch

from recon.diagnose.data import DiagnosisData
from recon.diagnose.gap import gap_summary
from recon.diagnose.residuals import luminance_of
from recon.io.atomic import atomic_path
from recon.io.images import linear_to_srgb

# No display: figures only go to files (as in recon.report).
matplotlib.use("Agg")

CHANNEL_COLORS = ("tab:red", "tab:green", "tab:blue")
CHANNEL_NAMES = ("R", "G", "B")
DIVERGING = "RdBu_r"
DPI = 100


def _save(figure: plt.Figure, path: Path) -> Path:
    """Write figure to path atomically and close it."""
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=DPI, bbox_inches="tight", format="png")
    plt.close(figure)
    return path


def _array(values) -> np.ndarray:
    """Summary lists as a float array: None (an empty bin, or an empty bin's whole row of
    channels) becomes NaN."""
    if isinstance(values, np.ndarray):
        return values.astype(float)
    if values is None or len(values) == 0:
        return np.zeros(0)
    rows = [value for value in values if isinstance(value, (list, tuple))]
    if rows:
        width = max(len(row) for row in rows)
        return np.array(
            [
                [np.nan] * width
                if value is None
                else [np.nan if item is None else item for item in value]
                for value in values
            ],
            dtype=float,
        )
    return np.array([np.nan if value is None else value for value in values], dtype=float)


def _symmetric_limit(values: np.ndarray) -> float:
    finite = np.abs(values[np.isfinite(values)])
    if finite.size == 0:
        return 1.0
    limit = float(np.percentile(finite, 99))
    return limit if limit > 0 else max(float(finite.max()), 1e-6)


def _title(analysis: dict, domain: str) -> str:
    entry = analysis.get(domain, {})
    return (
        f"{domain}: score {entry.get('score', 0.0):.2f} "
        f"(in sample {entry.get('score_in_sample', 0.0):.2f})"
    )


def _channel_curves(
    axis, x, curves, label_prefix: str = "", marker: str = "o", linestyle: str = "-"
) -> None:
    """Plot [C][K] curves against x ([K] shared or [C][K] per channel)."""
    x = _array(x)
    curves = _array(curves)
    for channel in range(curves.shape[0]):
        positions = x[channel] if x.ndim == 2 else x
        axis.plot(
            positions,
            curves[channel],
            marker=marker,
            markersize=3,
            linestyle=linestyle,
            color=CHANNEL_COLORS[channel],
            label=f"{label_prefix}{CHANNEL_NAMES[channel]}",
        )


def _beyond_response(axis, x, curves) -> None:
    """Dashed: the residual the score sees (what the shared response curve leaves)."""
    if curves:
        _channel_curves(axis, x, _array(curves).T, "beyond response ", "", "--")


def image_position_figure(data: DiagnosisData, analysis: dict, path: Path) -> Path:
    """Mean over views of the residual luminance per pixel (where in the region), and the
    radial gain profile observed / rendered."""
    residual = luminance_of(data.residual.double())  # [B, H, W]
    region = data.region[..., 0] > 0.5
    count = region.sum(0)
    mean = torch.where(
        count > 0, (residual * region).sum(0) / count.clamp_min(1), torch.nan
    ).numpy()
    figure, (heat_axis, radial_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    limit = _symmetric_limit(mean)
    image = heat_axis.imshow(mean, cmap=DIVERGING, vmin=-limit, vmax=limit)
    heat_axis.set_title("mean residual luminance over views")
    heat_axis.set_xlabel("x (pixels)")
    heat_axis.set_ylabel("y (pixels)")
    figure.colorbar(image, ax=heat_axis, shrink=0.8)
    summary = analysis.get("image_position", {}).get("summary", {})
    edges = np.array(summary.get("radial_edges", [0.0, 1.0]), dtype=float)
    centres = (edges[:-1] + edges[1:]) / 2
    ratio = summary.get("radial_ratio")
    if ratio:
        _channel_curves(radial_axis, centres, _array(ratio).T)
    radial_axis.axhline(1.0, color="gray", linewidth=0.8, linestyle="--")
    radial_axis.set_xlabel("radius / farthest corner")
    radial_axis.set_ylabel("observed / rendered")
    radial_axis.set_title("radial gain (vignetting)")
    radial_axis.legend(fontsize=8)
    figure.suptitle(_title(analysis, "image_position"))
    return _save(figure, path)


def surface_figure(analysis: dict, path: Path) -> Path:
    """The unwrapped residual on the fitted UV atlas (texel cells) and its across-view spread."""
    summary = analysis.get("surface", {}).get("summary", {})
    figure, (mean_axis, spread_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    if summary.get("mean_luminance"):
        mean = _array(summary["mean_luminance"])
        spread = _array(summary["across_view_std"])
        limit = _symmetric_limit(mean)
        image = mean_axis.imshow(mean, cmap=DIVERGING, vmin=-limit, vmax=limit, extent=(0, 1, 1, 0))
        figure.colorbar(image, ax=mean_axis, shrink=0.8)
        image = spread_axis.imshow(spread, cmap="magma", vmin=0, extent=(0, 1, 1, 0))
        figure.colorbar(image, ax=spread_axis, shrink=0.8)
    else:
        for axis in (mean_axis, spread_axis):
            axis.text(0.5, 0.5, "no texel coordinates", ha="center", va="center")
    mean_axis.set_title("mean residual luminance per texel cell")
    spread_axis.set_title(
        f"across-view std (view-dependent score {summary.get('view_dependent_score', 0.0):.2f})"
    )
    for axis in (mean_axis, spread_axis):
        axis.set_xlabel("u")
        axis.set_ylabel("v")
    figure.suptitle(_title(analysis, "surface"))
    return _save(figure, path)


def view_figure(analysis: dict, path: Path) -> Path:
    """Per-view bars per channel: mean residual and gain observed / rendered."""
    summary = analysis.get("view", {}).get("summary", {})
    names = summary.get("names", [])
    mean = _array(summary.get("mean_residual", [])).reshape(len(names), -1)
    gain = _array(summary.get("gain", [])).reshape(len(names), -1)
    figure, (mean_axis, gain_axis) = plt.subplots(
        2, 1, figsize=(max(6, 0.5 * len(names) + 2), 6), sharex=True
    )
    positions = np.arange(len(names))
    width = 0.27
    for channel in range(min(3, mean.shape[1] if mean.ndim == 2 else 0)):
        offset = (channel - 1) * width
        mean_axis.bar(positions + offset, mean[:, channel], width, color=CHANNEL_COLORS[channel])
        gain_axis.bar(
            positions + offset,
            gain[:, channel] - 1.0,
            width,
            bottom=1.0,
            color=CHANNEL_COLORS[channel],
            label=CHANNEL_NAMES[channel],
        )
    mean_axis.axhline(0.0, color="gray", linewidth=0.8)
    mean_axis.set_ylabel("mean residual")
    gain_axis.axhline(1.0, color="gray", linewidth=0.8)
    gain_axis.set_ylabel("observed / rendered")
    gain_axis.set_xticks(positions, names, rotation=60, fontsize=7)
    gain_axis.legend(fontsize=8)
    figure.suptitle(_title(analysis, "view"))
    return _save(figure, path)


def intensity_figure(analysis: dict, path: Path) -> Path:
    """Observed against rendered per channel (bin means) with the identity line: the response."""
    summary = analysis.get("intensity", {}).get("summary", {})
    figure, (curve_axis, ratio_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    if summary.get("mean_rendered"):
        rendered = _array(summary["mean_rendered"])
        _channel_curves(curve_axis, rendered, summary["mean_observed"])
        _channel_curves(ratio_axis, rendered, summary["ratio"])
        top = np.nanmax(
            np.concatenate([rendered.ravel(), _array(summary["mean_observed"]).ravel()])
        )
        top = float(top) if np.isfinite(top) and top > 0 else 1.0
        curve_axis.plot([0, top], [0, top], color="gray", linestyle="--", label="identity")
    ratio_axis.axhline(1.0, color="gray", linewidth=0.8, linestyle="--")
    gamma = summary.get("gamma") or []
    gamma_text = ", ".join("-" if value is None else f"{value:.2f}" for value in gamma)
    curve_axis.set_title(f"response (log-log slope per channel: {gamma_text})")
    curve_axis.set_xlabel("rendered (linear)")
    curve_axis.set_ylabel("observed (linear)")
    curve_axis.legend(fontsize=8)
    ratio_axis.set_xlabel("rendered (linear)")
    ratio_axis.set_ylabel("observed / rendered")
    ratio_axis.set_title("gain per intensity bin")
    figure.suptitle(_title(analysis, "intensity"))
    return _save(figure, path)


def light_geometry_figure(analysis: dict, path: Path) -> Path:
    """Mean residual per channel against n.l and against the angle between n and h."""
    summary = analysis.get("light_geometry", {}).get("summary", {})
    figure, (cosine_axis, angle_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    if summary.get("cosine_mean_residual"):
        edges = np.array(summary["cosine_edges"], dtype=float)
        centres = (edges[:-1] + edges[1:]) / 2
        _channel_curves(cosine_axis, centres, _array(summary["cosine_mean_residual"]).T)
        _beyond_response(cosine_axis, centres, summary.get("cosine_mean_beyond_response"))
        angle_edges = np.array(summary["half_angle_edges"], dtype=float)
        angle_edges[-1] = min(angle_edges[-1], 180.0)
        angle_centres = (angle_edges[:-1] + angle_edges[1:]) / 2
        _channel_curves(angle_axis, angle_centres, _array(summary["half_angle_mean_residual"]).T)
        _beyond_response(angle_axis, angle_centres, summary.get("half_angle_mean_beyond_response"))
    for axis in (cosine_axis, angle_axis):
        axis.axhline(0.0, color="gray", linewidth=0.8)
        axis.set_ylabel("mean residual")
        axis.legend(fontsize=7, ncol=2)
    cosine_axis.set_xlabel("n . l (dominant light)")
    cosine_axis.set_title(f"n.l (score {summary.get('cosine_score', 0.0):.2f})")
    angle_axis.set_xlabel("angle between n and h (degrees)")
    angle_axis.set_title(f"n.h (score {summary.get('half_angle_score', 0.0):.2f})")
    figure.suptitle(_title(analysis, "light_geometry"))
    return _save(figure, path)


def edges_figure(analysis: dict, path: Path) -> Path:
    """Residual against the signed distance to the silhouette, and RMS against the gradient."""
    summary = analysis.get("edges", {}).get("summary", {})
    figure, (distance_axis, gradient_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    if summary.get("distance_bins"):
        distances = np.array(summary["distance_bins"], dtype=float)
        _channel_curves(distance_axis, distances, _array(summary["distance_mean_residual"]).T)
        _beyond_response(distance_axis, distances, summary.get("distance_mean_beyond_response"))
        distance_axis.plot(
            distances,
            _array(summary["distance_rms_residual"]),
            color="black",
            linestyle=":",
            label="RMS (luminance)",
        )
        gradient_axis.plot(
            _array(summary["gradient_magnitude"]),
            _array(summary["gradient_rms_residual"]),
            marker="o",
            color="black",
            label="RMS residual",
        )
        gradient_axis.plot(
            _array(summary["gradient_magnitude"]),
            _array(summary["gradient_mean_residual"]),
            marker="s",
            color="gray",
            label="mean residual",
        )
    distance_axis.axvline(0.0, color="gray", linewidth=0.8)
    distance_axis.axhline(0.0, color="gray", linewidth=0.8)
    distance_axis.set_xlabel("signed distance to the rendered silhouette (pixels, + outside)")
    distance_axis.set_ylabel("residual")
    sigma = summary.get("blur_sigma_pixels") or []
    sigma_text = ", ".join(f"{value:.2f}" for value in sigma)
    distance_axis.set_title(f"silhouette profile (blur sigma px: {sigma_text})")
    distance_axis.legend(fontsize=8)
    gradient_axis.set_xlabel("rendered luminance gradient magnitude (per pixel)")
    gradient_axis.set_ylabel("residual luminance")
    gradient_axis.set_title(f"texture edges (shift score {summary.get('shift_score', 0.0):.2f})")
    gradient_axis.legend(fontsize=8)
    figure.suptitle(_title(analysis, "edges"))
    return _save(figure, path)


def frequency_figure(analysis: dict, path: Path) -> Path:
    """Normalised radial power spectrum of the residual (white noise = 1) and autocorrelation."""
    summary = analysis.get("frequency", {}).get("summary", {})
    figure, (spectrum_axis, correlation_axis) = plt.subplots(1, 2, figsize=(10, 4.2))
    power = _array(summary.get("power", []))
    if power.size and np.isfinite(power).any():
        spectrum_axis.semilogy(_array(summary["frequencies"]), power, marker="o", color="black")
    spectrum_axis.axhline(1.0, color="gray", linestyle="--", label="white noise")
    spectrum_axis.set_xlabel("frequency (cycles per pixel)")
    spectrum_axis.set_ylabel("power / mean power")
    spectrum_axis.set_title("residual power spectrum")
    spectrum_axis.legend(fontsize=8)
    correlation = summary.get("autocorrelation", {})
    lags = [int(lag) for lag in correlation]
    values = [np.nan if value is None else value for value in correlation.values()]
    correlation_axis.bar([str(lag) for lag in lags], values, color="tab:purple")
    correlation_axis.axhline(0.0, color="gray", linewidth=0.8)
    correlation_axis.set_ylim(-1, 1)
    correlation_axis.set_xlabel("lag (pixels)")
    correlation_axis.set_ylabel("autocorrelation")
    correlation_axis.set_title("spatial autocorrelation (0 for white noise)")
    figure.suptitle(_title(analysis, "frequency"))
    return _save(figure, path)


def worst_views_figure(data: DiagnosisData, path: Path, count: int = 3) -> Path:
    """observed | rendered | residual (luminance, diverging) for the count views with the
    largest residual RMSE over the region, worst first."""
    gap = gap_summary(data)
    rmse = [-1.0 if value is None else value for value in gap["per_view_rmse"]]
    order = sorted(range(len(rmse)), key=lambda index: -rmse[index])[: max(1, count)]
    residual = luminance_of(data.residual.double()) * (data.region[..., 0] > 0.5)
    limit = _symmetric_limit(residual[order].numpy())
    figure, axes = plt.subplots(len(order), 3, figsize=(9, 3 * len(order)), squeeze=False)
    for row, view in enumerate(order):
        observed = linear_to_srgb(data.observed[view].clamp(0, 1)).numpy()
        rendered = linear_to_srgb(data.rendered[view].clamp(0, 1)).numpy()
        axes[row, 0].imshow(observed)
        axes[row, 1].imshow(rendered)
        image = axes[row, 2].imshow(residual[view].numpy(), cmap=DIVERGING, vmin=-limit, vmax=limit)
        figure.colorbar(image, ax=axes[row, 2], shrink=0.8)
        name = data.names[view] if view < len(data.names) else str(view)
        axes[row, 0].set_ylabel(f"{name}\nRMSE {rmse[view]:.4f}")
        for column, title in enumerate(("observed", "rendered", "residual (luminance)")):
            axes[row, column].set_xticks([])
            axes[row, column].set_yticks([])
            if row == 0:
                axes[row, column].set_title(title)
    figure.suptitle("worst views")
    return _save(figure, path)


def where_figures(data: DiagnosisData, analysis: dict, folder: str | Path) -> dict[str, Path]:
    """All figures into folder: {domain (and "worst_views"): path of its PNG}."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return {
        "image_position": image_position_figure(
            data, analysis, folder / "where_image_position.png"
        ),
        "surface": surface_figure(analysis, folder / "where_surface.png"),
        "view": view_figure(analysis, folder / "where_view.png"),
        "intensity": intensity_figure(analysis, folder / "where_intensity.png"),
        "light_geometry": light_geometry_figure(analysis, folder / "where_light_geometry.png"),
        "edges": edges_figure(analysis, folder / "where_edges.png"),
        "frequency": frequency_figure(analysis, folder / "where_frequency.png"),
        "worst_views": worst_views_figure(data, folder / "where_worst_views.png"),
    }


def flat_field_figure(measurement: dict, model: dict | None, path: Path) -> Path:
    """The flat-field frames' radial profile (relative to the centre) beside the fitted
    vignetting polynomial 1 + a r^2 + b r^4 (model: a vignetting parameter set with a, b and
    covered_radius; None without one), with the radius the object's pixels reach: what a fit to
    the object alone extrapolates beyond."""
    figure, axis = plt.subplots(figsize=(5.5, 3.5))
    radius = np.asarray(measurement["profile_radius"])
    axis.plot(radius, measurement["profile"], "o-", color="k", label="flat field (measured)")
    if model and "a" in model and "b" in model:
        grid = np.linspace(0.0, 1.0, 101)
        polynomial = 1 + model["a"] * grid**2 + model["b"] * grid**4
        axis.plot(grid, polynomial, color="tab:orange", label="fitted polynomial")
    covered = (model or {}).get("object_radius")
    if covered:
        axis.axvline(covered, color="tab:blue", linestyle=":", label="object reaches")
    axis.axhline(
        measurement["corner_falloff"],
        color="tab:red",
        linestyle="--",
        linewidth=0.8,
        label="corner (mean of the four corner pixels)",
    )
    axis.set_xlabel("radius (half image diagonal)")
    axis.set_ylabel("relative gain")
    axis.set_title(
        f"flat field: corner {measurement['corner_falloff']:.3f}, "
        f"half-way {measurement['half_radius_falloff']:.3f}"
    )
    axis.legend(fontsize=8)
    return _save(figure, path)


def line_target_figure(measurement: dict, path: Path) -> Path:
    """The lens distortion the line-target frames measured (recon.diagnose.line_target): the
    displacement field over the frame (arrows, scaled to be seen) and its size against the
    radius, up to the corners."""
    from recon.diagnose.line_target import undistorted

    height, width = measurement["image_size"]
    fx, fy, cx, cy = measurement["intrinsics"]
    q = np.asarray(measurement["undistortion"])
    rows, columns = np.meshgrid(np.linspace(0, height, 9), np.linspace(0, width, 9), indexing="ij")
    x, y = (columns - cx) / fx, (rows - cy) / fy
    new_x, new_y = undistorted(x, y, q)
    # The lens moves the ideal image point (undistorted) to where it is seen (the grid).
    du, dv = fx * (x - new_x), fy * (y - new_y)
    figure, (field, profile) = plt.subplots(1, 2, figsize=(9.0, 3.8))
    largest = float(np.hypot(du, dv).max()) or 1.0
    scale = 0.08 * max(height, width) / largest
    field.quiver(columns, rows, du * scale, dv * scale, angles="xy", scale_units="xy", scale=1)
    # A margin round the frame (drawn), so that the arrows at its edges and corners show.
    field.add_patch(plt.Rectangle((0, 0), width, height, fill=False, linewidth=0.8))
    field.set_xlim(-0.15 * width, 1.15 * width)
    field.set_ylim(1.15 * height, -0.15 * height)
    field.set_aspect("equal")
    field.set_title(f"lens displacement (arrows x{scale:.1f})", fontsize=9)
    radius = np.linspace(0.0, 1.0, 50)
    corner = np.hypot(width - cx, height - cy)
    angle = math.atan2(height - cy, width - cx)
    u = cx + radius * corner * math.cos(angle)
    v = cy + radius * corner * math.sin(angle)
    x, y = (u - cx) / fx, (v - cy) / fy
    new_x, new_y = undistorted(x, y, q)
    profile.plot(radius, np.hypot(fx * (new_x - x), fy * (new_y - y)), color="k")
    profile.axhline(
        measurement["allowance"], color="tab:red", linestyle="--", linewidth=0.8, label="allowance"
    )
    profile.set_xlabel("radius along the diagonal (half diagonal)")
    profile.set_ylabel("displacement (px)")
    profile.set_title(
        f"corners moved {measurement['corner_shift_pixels']:.2f} px "
        f"(standard error {measurement['standard_error']:.2f})",
        fontsize=9,
    )
    profile.legend(fontsize=8)
    return _save(figure, path)


def backdrop_figure(evidence: list[dict], path: Path) -> Path:
    """The backdrop check (recon.diagnose.backdrop), one panel per checked candidate: the
    per-view log gains recovered on the object beside the ones the static backdrop shows in
    the same frames (centred over the views), a curve per compared component. evidence: the
    backdrop Evidence records as JSON (candidate, statistic, passed, details)."""
    figure, axes = plt.subplots(1, len(evidence), figsize=(5.0 * len(evidence), 3.3), squeeze=False)
    colours = ("tab:red", "tab:blue")
    for axis, record in zip(axes[0], evidence, strict=True):
        details = record["details"]
        found = _array(details["object_components"])
        shown = _array(details["backdrop_components"])
        views = np.arange(len(found))
        for index, name in enumerate(details["components"]):
            colour = "k" if len(details["components"]) == 1 else colours[index % 2]
            axis.plot(views, found[:, index], "o-", color=colour, label=f"object: {name}")
            axis.plot(
                views, shown[:, index], "s--", color=colour, alpha=0.6, label=f"backdrop: {name}"
            )
        verdict = "the camera's" if record["passed"] else "not the camera's"
        axis.set_title(
            f"{record['candidate']}: backdrop shows {100 * record['statistic']:.0f} % ({verdict})",
            fontsize=9,
        )
        axis.axhline(0.0, color="grey", linewidth=0.6)
        axis.set_xlabel("held-out view")
        axis.set_ylabel("log gain (centred)")
        axis.legend(fontsize=7)
    return _save(figure, path)


def waterfall_figure(refits: list[dict], floor_rmse: float, path: Path) -> Path:
    """Held-out RMSE of the fitted scene and after each refit, against the noise floor."""
    labels = ["fitted"] + ["+ " + " + ".join(r["effects"]) for r in refits]
    values = [refits[0]["before_rmse"]] + [r["after_rmse"] for r in refits] if refits else []
    figure, axis = plt.subplots(figsize=(6, 3.5))
    axis.bar(range(len(values)), values, color=["#888"] + ["#3a7"] * (len(values) - 1))
    axis.axhline(floor_rmse, color="#c33", linestyle="--", label="noise floor")
    axis.set_xticks(range(len(values)), labels, rotation=20, ha="right")
    axis.set_ylabel("held-out residual RMSE (linear)")
    axis.legend()
    return _save(figure, path)
