"""Identifiability: whether the data can tell an effect apart at all, and which capture would.

Some effects cannot be separated from the fitted scene (or from each other) by any residual of
some data, whatever the diagnosis does: a tone curve under one light with no exposure change (a
texel is seen at one intensity, so the albedo absorbs the curve), a vignetting falloff where the
object never reaches the corners, a lens distortion where the object covers the centre only (it
then moves pixels like a per-view zoom and shift, which a pose correction also makes), a
motion blur in views whose edges all run one way (a blur along them looks like a defocus), a
defocus too small to clear its probe's allowance over the fit's own misfit (at 96 px of a real
photo a 1 px blur changes about 1 % of the held-out error), a
white balance whose change from view to view hides in the fit's per-view colour noise (and,
always, a cast common to every view: the albedo's colour absorbs it).
Saying so is part of the answer: "not identifiable from this data, because ...", and what
capture would settle it.

Producers return recon.diagnose.records.Evidence of kind "identifiability": passed means the
data can identify the effect; a failed one turns a miss or a wrong name into that sentence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from recon.config.run_config import IdentifiabilityConfig
from recon.diagnose.agreement import MINIMUM_VIEWS
from recon.diagnose.data import DiagnosisData
from recon.diagnose.pixel_table import (
    pixel_radius,
    surface_labels,
    table_pixels,
    view_directions,
)
from recon.diagnose.records import Evidence

KIND = "identifiability"


@dataclass(frozen=True)
class CaptureConditions:
    """What the capture holds besides the held-out views.

    relight: a relight split with its known light (the same object under a second light).
    exposure_gains: known per-view gains [B] (EXIF exposure) or None.
    flat_field: flat-field frames (a uniform target) are present.
    """

    relight: bool = False
    exposure_gains: torch.Tensor | None = None
    flat_field: bool = False


def response_curve_evidence(
    data: DiagnosisData, conditions: CaptureConditions, options: IdentifiabilityConfig
) -> Evidence:
    """A tone curve is identifiable when some texel is seen at two intensities whose ratio the
    fit does not learn: under a second, known light (relight split) or at known different
    exposures.

    A light that turns with the camera (a turntable) changes a texel's shading from view to
    view, but the fit learns that light: a power law of albedo x shading is albedo^g x
    shading^g, which the fitted albedo and the fitted light absorb whole (on the real capture
    the response curve's own signature removed 0.0-0.1 % of the held-out error with and
    without an injected curve). It does not make the curve identifiable."""
    ratio = 1.0
    if conditions.exposure_gains is not None and conditions.exposure_gains.numel():
        gains = conditions.exposure_gains.double()
        ratio = float(gains.max() / gains.min().clamp_min(1e-30))
    bracketed = ratio >= options.minimum_exposure_ratio
    camera_light = data.lighting.frame == "camera"
    passed = conditions.relight or bracketed
    if passed:
        sources = [
            text
            for text, present in (
                ("a relight split", conditions.relight),
                (f"known exposures spanning x{ratio:.2f}", bracketed),
            )
            if present
        ]
        reason = (
            "response_curve is identifiable: "
            + " and ".join(sources)
            + (" show the same surface at different intensities")
        )
    else:
        known = (
            "no known exposure change"
            if ratio == 1.0
            else f"known exposures spanning only x{ratio:.2f}"
        )
        light = (
            "one light, fitted with the scene, that turns with the camera: a power law of "
            "albedo x shading is the fitted albedo's and light's power law"
            if camera_light
            else "one fixed light"
        )
        reason = (
            "response_curve is not identifiable from this data, because every surface point "
            f"is seen at one known intensity only ({light}; no relight split, {known}): the "
            "albedo and the exposure absorb any tone curve; capture with bracketed exposures "
            "or a second light would settle it"
        )
    return Evidence(
        kind=KIND,
        candidate="response_curve",
        statistic=ratio,
        threshold=options.minimum_exposure_ratio,
        passed=passed,
        reason=reason,
        details={
            "relight": conditions.relight,
            "exposure_ratio": ratio,
            "camera_frame_light": camera_light,
            "confused_with": ["exposure", "albedo"],
        },
    )


def covered_radius(data: DiagnosisData) -> float:
    """The largest normalised radius (half image diagonal from the principal point = 1) of a
    pixel the observed object covers in any view."""
    batch, height, width, _ = data.observed.shape
    intrinsics = data.cameras.intrinsics.float()
    rows = torch.arange(height, dtype=torch.float32)[None, :, None] + 0.5
    columns = torch.arange(width, dtype=torch.float32)[None, None, :] + 0.5
    dx = columns - intrinsics[:, 0, 2, None, None]
    dy = rows - intrinsics[:, 1, 2, None, None]
    radius = torch.sqrt(dx * dx + dy * dy) / (0.5 * math.hypot(height, width))
    covered = data.observed_alpha[..., 0] > 0.5
    return float(radius[covered].max()) if bool(covered.any()) else 0.0


def radius_spread(data: DiagnosisData, options: IdentifiabilityConfig) -> float:
    """Median over surface regions of how far apart (normalised radius) the views see it."""
    # pixel_table's surface labels and radius values, without its other columns.
    keep = table_pixels(data)
    world, _ = view_directions(data)
    cells = surface_labels(world[keep], options.surface_cells)
    radius = pixel_radius(data)[keep].double()
    batch, height, width = keep.shape
    views = torch.arange(batch)[:, None, None].expand(batch, height, width)[keep]
    spreads = []
    for cell in torch.unique(cells):
        chosen = cells == cell
        if int(chosen.sum()) < 4:
            continue
        per_view = []
        for view in torch.unique(views[chosen]):
            per_view.append(float(radius[chosen & (views == view)].mean()))
        if len(per_view) > 1:
            spreads.append(max(per_view) - min(per_view))
    return float(torch.tensor(spreads).median()) if spreads else 0.0


def vignetting_evidence(
    data: DiagnosisData, conditions: CaptureConditions, options: IdentifiabilityConfig
) -> Evidence:
    """A falloff is measured where the object is: up to its covered radius, and told from the
    albedo only if the same surface is seen at different radii. Flat-field frames measure it
    everywhere."""
    radius = covered_radius(data)
    spread = radius_spread(data, options)
    details = {
        "covered_radius": radius,
        "radius_spread": spread,
        "flat_field": conditions.flat_field,
    }
    if conditions.flat_field:
        return Evidence(
            KIND,
            "vignetting",
            1.0,
            options.corner_radius,
            True,
            "vignetting is identifiable: flat-field frames measure the falloff over the whole "
            "image",
            details,
        )
    reasons = []
    if radius < options.corner_radius:
        reasons.append(
            f"the object covers radii up to {radius:.2f} of the half diagonal only (the "
            "corners are at 1.0), so the corner falloff is an extrapolation"
        )
    if spread < options.minimum_radius_spread:
        reasons.append(
            f"each surface region is seen at nearly one radius in every view (median spread "
            f"{spread:.2f}), so the albedo absorbs the falloff"
        )
    if not reasons:
        return Evidence(
            KIND,
            "vignetting",
            radius,
            options.corner_radius,
            True,
            f"vignetting is identifiable: the object reaches radius {radius:.2f} and each "
            f"surface region is seen at radii {spread:.2f} apart",
            details,
        )
    reason = (
        "vignetting is not identifiable from this data, because "
        + "; and ".join(reasons)
        + "; flat-field frames, or views with the object near the corners and moving "
        "across the image, would settle it"
    )
    return Evidence(KIND, "vignetting", radius, options.corner_radius, False, reason, details)


def _similarity_remainder(data: DiagnosisData, flow_of) -> tuple[float, float, int]:
    """The share of a flow over each view's covered pixels that a per-view shift, zoom and
    rotation reproduces (least squares), the RMS of the rest and the number of views with
    coverage. flow_of(view, x, y) -> (coordinates x, y [N] for the design, flow [2N]) from the
    covered pixels' offsets x, y [N] (pixels) from the view's principal point."""
    batch, height, width, _ = data.observed.shape
    intrinsics = data.cameras.intrinsics.double()
    rows = torch.arange(height, dtype=torch.float64)[:, None].expand(height, width) + 0.5
    columns = torch.arange(width, dtype=torch.float64)[None, :].expand(height, width) + 0.5
    total, residual, views, points = 0.0, 0.0, 0, 0
    for view in range(batch):
        covered = data.observed_alpha[view, ..., 0] > 0.5
        if int(covered.sum()) < 8:
            continue
        views += 1
        points += int(covered.sum())
        x, y, flow = flow_of(
            view, columns[covered] - intrinsics[view, 0, 2], rows[covered] - intrinsics[view, 1, 2]
        )
        ones, zeros = torch.ones_like(x), torch.zeros_like(x)
        design = torch.stack(
            [
                torch.cat([ones, zeros]),  # shift x
                torch.cat([zeros, ones]),  # shift y
                torch.cat([x, y]),  # zoom
                torch.cat([-y, x]),  # rotation
            ],
            dim=1,
        )
        solution = torch.linalg.lstsq(design, flow[:, None]).solution
        residual += float(((design @ solution)[:, 0] - flow).pow(2).sum())
        total += float(flow.pow(2).sum())
    share = 1 - residual / total if total > 0 else 1.0
    return share, math.sqrt(residual / max(points, 1)), views


def similarity_share(data: DiagnosisData) -> tuple[float, float, int]:
    """How a radial distortion's flow r^2 (x - c) (1 at the image corners) over each view's
    covered pixels compares with a per-view shift, zoom and rotation (least squares): the share
    of its energy they reproduce, the RMS of the rest (in corner displacements), and the number
    of views with coverage."""
    height, width = data.observed.shape[1:3]
    half_diagonal = 0.5 * math.hypot(height, width)

    def flow_of(view: int, x: torch.Tensor, y: torch.Tensor):
        x, y = x / half_diagonal, y / half_diagonal
        squared = x * x + y * y
        return x, y, torch.cat([squared * x, squared * y])

    return _similarity_remainder(data, flow_of)


def radial_flow_remainder(data: DiagnosisData, k1: float, k2: float) -> tuple[float, float, int]:
    """The same comparison as similarity_share for one radial distortion x_d = x (1 + k1 r^2 +
    k2 r^4) (normalised camera coordinates, the diagnosis' lens_distortion model), in pixels:
    the share of its flow over each view's covered pixels that a per-view shift, zoom and
    rotation reproduces, the RMS (pixels) of the rest, and the number of views with coverage.

    A recovered distortion is fitted where the object is; its displacement at the image corners
    is an extrapolation of its polynomial (a k1 and k2 of opposite signs can cancel there), so
    it is judged by its flow over the object, not by its corner shift."""
    intrinsics = data.cameras.intrinsics.double()

    def flow_of(view: int, x: torch.Tensor, y: torch.Tensor):
        fx, fy = intrinsics[view, 0, 0], intrinsics[view, 1, 1]
        squared = (x / fx) ** 2 + (y / fy) ** 2
        scale = k1 * squared + k2 * squared * squared
        return x, y, torch.cat([scale * x, scale * y])  # [2N] pixels

    return _similarity_remainder(data, flow_of)


def lens_distortion_evidence(
    data: DiagnosisData,
    options: IdentifiabilityConfig,
    corner_shift_pixels: float | None = None,
    radial: tuple[float, float] | None = None,
) -> Evidence:
    """A radial distortion is told from a pose error by the part of its flow that no per-view
    zoom, shift and rotation makes; where the object covers only the centre, that part is
    small and a pose correction explains the distortion as well.

    corner_shift_pixels: the distortion to judge, by its displacement at the image corners;
    default options.reference_corner_shift of the half diagonal (judged with the flow shape
    r^2 x). radial: a recovered distortion's (k1, k2), judged by its own flow over the object
    (radial_flow_remainder); corner_shift_pixels is then only reported."""
    explained, distinguishable, views = similarity_share(data)
    height, width = data.image_size
    if corner_shift_pixels is None:
        corner_shift_pixels = options.reference_corner_shift * 0.5 * math.hypot(height, width)
    pixels = distinguishable * abs(corner_shift_pixels)
    if radial is not None:
        explained, pixels, views = radial_flow_remainder(data, *radial)
    passed = pixels >= options.minimum_distinguishable_pixels
    radius = covered_radius(data)
    details = {
        "similarity_share": explained,
        "distinguishable_flow": distinguishable,
        "distinguishable_pixels": pixels,
        "corner_shift_pixels": corner_shift_pixels,
        "covered_radius": radius,
        "views": views,
        "confused_with": ["pose_error"],
        # The probe's own comparison with a pose correction (and the other confusers) measured
        # the answer this condition predicts from a reference distortion: where it decides, the
        # condition does not qualify it.
        "settled_by": ["beyond_confusers", "line_target"],
        # A prediction: the decision judges it by the run's pair records where the probe
        # measured a distortion (recon.diagnose.geometric_judgement.measured_condition).
        "measured_by": "pairs",
    }
    if radial is not None:
        details["judged"] = {"k1": radial[0], "k2": radial[1]}
        what = f"the recovered radial distortion (k1 {radial[0]:.3g}, k2 {radial[1]:.3g})"
    else:
        what = f"a radial distortion moving the corners by {corner_shift_pixels:.1f} px"
    if passed:
        reason = (
            f"lens_distortion is identifiable: {what} leaves {pixels:.2f} px (RMS) over the "
            f"object (radius up to {radius:.2f}) that no per-view zoom, shift or rotation makes"
        )
    else:
        reason = (
            "lens_distortion is not identifiable from pose_error on this data, because the "
            f"object covers radii up to {radius:.2f} only, where {what} is a per-view zoom and "
            f"shift but for {pixels:.2f} px (RMS, over {views} views): a pose correction "
            "explains it as well; views with the object off-centre or near "
            "the image edges, or a calibration target, would settle it"
        )
    return Evidence(
        KIND,
        "lens_distortion",
        pixels,
        options.minimum_distinguishable_pixels,
        passed,
        reason,
        details,
    )


def edge_coherence(data: DiagnosisData) -> float:
    """Median over views of the orientation coherence of the rendered image's edges:
    (l1 - l2) / (l1 + l2) of the summed gradient structure tensor (0 = edges of every
    orientation, 1 = all parallel)."""
    luminance = data.rendered.mean(dim=-1).double()
    dx = torch.zeros_like(luminance)
    dy = torch.zeros_like(luminance)
    dx[:, :, 1:-1] = (luminance[:, :, 2:] - luminance[:, :, :-2]) / 2
    dy[:, 1:-1] = (luminance[:, 2:] - luminance[:, :-2]) / 2
    xx, yy, xy = (dx * dx).sum((1, 2)), (dy * dy).sum((1, 2)), (dx * dy).sum((1, 2))
    trace = (xx + yy).clamp_min(1e-30)
    difference = torch.sqrt((xx - yy) ** 2 + 4 * xy * xy)
    return float((difference / trace).median())


def motion_blur_evidence(data: DiagnosisData, options: IdentifiabilityConfig) -> Evidence:
    """A motion blur is told from a defocus blur by edges across its direction: in views
    whose edges all run one way, the blur along them is invisible and across them it is any
    blur."""
    coherence = edge_coherence(data)
    passed = coherence <= options.maximum_edge_coherence
    # A prediction from the edges: where the probe measured a blur (its per-run null passed),
    # the decision judges it by what the probe keeps on top of the defocus and pose probes
    # (recon.diagnose.geometric_judgement.measured_condition).
    details = {
        "edge_coherence": coherence,
        "confused_with": ["defocus_blur"],
        "measured_by": "pairs",
    }
    if passed:
        reason = (
            f"motion_blur is identifiable: the views' edges run in many directions (coherence "
            f"{coherence:.2f})"
        )
    else:
        reason = (
            "motion_blur is not identifiable from defocus_blur on this data, because the "
            f"views' edges nearly all run one way (coherence {coherence:.2f}): a blur across "
            "them is any blur; views of a textured object with edges in several directions "
            "would settle it"
        )
    return Evidence(
        KIND, "motion_blur", coherence, options.maximum_edge_coherence, passed, reason, details
    )


def pillbox_kernel(radius: float, samples: int = 16) -> torch.Tensor:
    """A normalised disc kernel [K, K] of the given radius (pixels; K = 2 ceil(radius) + 1),
    each tap weighted by the share of its pixel inside the disc (samples^2 points per pixel)."""
    half = max(1, math.ceil(radius))
    offsets = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples - 0.5
    taps = torch.arange(-half, half + 1, dtype=torch.float64)
    x = (taps[:, None] + offsets[None, :]).reshape(-1)
    inside = (x[:, None] ** 2 + x[None, :] ** 2) <= radius**2
    size = 2 * half + 1
    weights = inside.double().view(size, samples, size, samples).mean(dim=(1, 3))
    return weights / weights.sum().clamp_min(1e-30)


def _blurred(images: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """[B, H, W, C] images convolved channel by channel with kernel [K, K] (zero padded)."""
    batch, height, width, channels = images.shape
    planes = images.permute(0, 3, 1, 2).reshape(batch * channels, 1, height, width).double()
    size = kernel.shape[0]
    out = torch.nn.functional.conv2d(planes, kernel.to(planes)[None, None], padding=size // 2)
    return out.reshape(batch, channels, height, width).permute(0, 2, 3, 1)


def blur_share(
    data: DiagnosisData, radius: float, explained: float = 0.0
) -> tuple[float, float, float]:
    """What a defocus of the given radius would add to this fit's held-out misfit, as a share
    of the error a probe recovering it exactly would remove: (share, outline share, outline
    pixels per view).

    The blur's change of the render, E (over the diagnosis region), against the fit's misfit R
    there: share = E / (E + R). The outline share counts only the render's coverage edge, the
    part no texture can absorb (the fit learns its texture from blurred views, so inside the
    object it absorbs part of the blur). explained: the share of R another candidate's probe
    removes (the blur's probe is then measured on top of it, recon.diagnose.which), left out
    of the misfit."""
    if radius <= 0:
        return 0.0, 0.0, 0.0
    kernel = pillbox_kernel(radius)
    region = data.region.double()
    alpha = data.rendered_alpha.double()
    outline = ((_blurred(alpha, kernel) - alpha).abs() > 1e-3).double() * region
    change = (_blurred(data.rendered, kernel) - data.rendered.double()) ** 2 * region
    misfit = float((data.residual.double() ** 2 * region).sum()) * (
        1 - min(max(explained, 0.0), 1.0)
    )
    energy, edge = float(change.sum()), float((change * outline).sum())
    return (
        energy / max(energy + misfit, 1e-30),
        edge / max(edge + misfit, 1e-30),
        float(outline.sum()) / max(data.view_count, 1),
    )


def defocus_blur_evidence(
    data: DiagnosisData, options: IdentifiabilityConfig, allowance: float, explained: float = 0.0
) -> Evidence:
    """A defocus blur is identifiable when a blur of options.reference_blur_radius would
    remove more of this fit's held-out error than the probe's allowance (``allowance``):
    otherwise the fit's own misfit hides a blur that size, whatever the probe does (explained:
    the share of the misfit the strongest other candidate's probe removes, blur_share). The
    estimate (blur_share, scaled by options.blur_estimate_factor, what the probe removed over
    it on synthetic blurs) is judged again with each calibration's allowance
    (recon.diagnose.decision, ``details["judged_against"]``)."""
    radius = options.reference_blur_radius
    estimate, outline_share, outline = blur_share(data, radius, explained)
    details = {
        "explained_by_others": explained,
        "expected_share": min(1.0, options.blur_estimate_factor * estimate),
        "estimated_share": estimate,
        "outline_share": outline_share,
        "reference_radius_px": radius,
        "outline_pixels": outline,
        "judged_against": "probe",
        "capture": (
            "a few views in focus (or at another aperture), a higher resolution, or a "
            "sharper fit (more views, a finer texture)"
        ),
    }
    return judge_expected_share("defocus_blur", details["expected_share"], allowance, details)


def judge_expected_share(name: str, share: float, allowance: float, details: dict) -> Evidence:
    """The identifiability Evidence of an effect judged by the share of the held-out error its
    reference strength would remove (details["expected_share"]) against its probe's allowance;
    the reason is built from details (recon.diagnose.decision judges it again with another
    calibration's allowance)."""
    passed = share > allowance
    radius = details.get("reference_radius_px", 0.0)
    what = (
        f"a defocus of radius {radius:g} px would remove about {100 * share:.1f} % of this "
        f"fit's held-out error (its outline, which no texture absorbs, "
        f"{100 * details.get('outline_share', 0.0):.1f} %)"
    )
    if passed:
        reason = f"{name} is identifiable: {what}, above the allowance {100 * allowance:.1f} %"
    else:
        reason = (
            f"{what}, short of the allowance {100 * allowance:.1f} % its probe must clear: "
            "the fit's own misfit hides a blur this size"
        )
    return Evidence(KIND, name, share, allowance, passed, reason, dict(details))


def white_balance_evidence(
    detectable: float,
    noise: float,
    views: int,
    options: IdentifiabilityConfig,
    found: float | None = None,
) -> Evidence:
    """A white balance is identified by how the views' colours change from view to view (the
    agreement of separate halves of each view, recon.diagnose.agreement); a colour cast common
    to every view is the albedo's colour to a fit without a reference of known colour, whatever
    the data. Whether a per-view change is identifiable depends on the fit's own per-view colour
    noise (how far the halves of a view disagree; a white balance cancels in it): detectable is
    the smallest RMS change the agreement's test names on this data, judged against
    options.white_balance_reference_spread. Not on the change the views show: a capture with no
    white-balance change identifies one as well as a capture with one. The one exception is a
    change the agreement found (found, its RMS log gain, given only when its test named it): at
    or above detectable, this data identified that change, whatever the reference would say
    about a smaller one."""
    reference = options.white_balance_reference_spread
    details = {
        "detectable_spread": detectable,
        "noise": noise,
        "reference_spread": reference,
        "views": views,
        "confused_with": ["albedo"],
    }
    common = (
        "a colour cast common to every view is absorbed by the albedo's colour (a grey card "
        "or another target of known colour would settle that part)"
    )
    if views < MINIMUM_VIEWS:
        reason = (
            "white_balance is not identifiable from this data, because a change from view to "
            f"view needs at least {MINIMUM_VIEWS} held-out views to compare, got {views}, and "
            f"{common}; more held-out views would settle the change from view to view"
        )
        return Evidence(KIND, "white_balance", detectable, reference, False, reason, details)
    if found is not None and found >= detectable:
        reason = (
            f"white_balance is identifiable as a change from view to view: the one found "
            f"({100 * found:.1f} %, RMS log gain) stands out of this fit's per-view colour "
            f"noise ({100 * noise:.1f} %, separate halves of each view, {views} views; a change "
            f"below {100 * detectable:.1f} % would hide in it); {common}"
        )
        details["found_spread"] = found
        return Evidence(KIND, "white_balance", detectable, reference, True, reason, details)
    if detectable <= reference:
        reason = (
            f"white_balance is identifiable as a change from view to view: one of "
            f"{100 * detectable:.1f} % (RMS log gain) or more stands out of this fit's "
            f"per-view colour noise ({100 * noise:.1f} %, separate halves of each view, "
            f"{views} views); {common}"
        )
        return Evidence(KIND, "white_balance", detectable, reference, True, reason, details)
    reason = (
        "white_balance is not identifiable from this data, because the fit's per-view colour "
        f"noise ({100 * noise:.1f} %: separate halves of each view disagree by that much over "
        f"{views} views) hides a change from view to view below {100 * detectable:.1f} % "
        f"(RMS log gain; reference {100 * reference:.1f} %), and {common}; more held-out "
        "views, a closer fit of the texture, or a grey card in the views would settle it"
    )
    return Evidence(KIND, "white_balance", detectable, reference, False, reason, details)


def identifiability_evidence(
    data: DiagnosisData,
    conditions: CaptureConditions | None = None,
    options: IdentifiabilityConfig | None = None,
    corner_shift_pixels: float | None = None,
) -> list[Evidence]:
    """Identifiability Evidence of the effects whose identifiability depends on the capture:
    response_curve, vignetting, lens_distortion (against pose_error; corner_shift_pixels: the
    recovered distortion's displacement at the corners, when known) and motion_blur (against
    defocus_blur)."""
    conditions = conditions or CaptureConditions()
    options = options or IdentifiabilityConfig()
    return [
        response_curve_evidence(data, conditions, options),
        vignetting_evidence(data, conditions, options),
        lens_distortion_evidence(data, options, corner_shift_pixels),
        motion_blur_evidence(data, options),
    ]
