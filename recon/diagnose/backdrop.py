"""The backdrop check: a camera gain scales the whole frame, the object's reflectance does not.

An exposure or a white balance is a gain the camera applies to every pixel of a view. Where the
photos share a static backdrop (a turntable capture: the camera, the room and its light stay,
the object turns), the backdrop's change from view to view is the camera's gain, measured on
pixels that no fitted model has to explain. A per-view gain the diagnosis recovers on the object
must then show in the backdrop too; a change of the object's own (reflections of the
surroundings on a glossy surface, which a diffuse model cannot render) does not.

The reading: backdrop pixels are the ones outside every view's object mask (dilated by a
margin), neither dark nor clipped, and static: their log colour, once each view's gain is
removed, stays near its median over the views. A view's log gain is the median over those
pixels of its log colour less the per-pixel median, iterated a few times so that a large
exposure change does not hide the static pixels. Its noise is half the difference of the top
and bottom halves' readings. A rendered capture (RGBA, nothing behind the object) or a moving
camera has no such pixels, and the check does not apply.

The evidence (kind "backdrop", a veto in recon.diagnose.decision): the share of the object's
log-gain change over the views that the backdrop shows, 1 - RMS(object - backdrop) /
RMS(object), both centred over the views (a common scale or cast is the albedo's). Exposure is
compared on the mean of the three channels' log gains, white balance on log(red / green) and
log(blue / green). Below diagnose.backdrop.minimum_explained, the gain is not the camera's;
at or above it, the backdrop's gains are what the candidate reports (a direct measurement,
the turntable's grey card).
Where the backdrop itself changes beyond its noise, the camera (or the room's light) did change
the frames, but by less than the object's own change, which hides it: the candidate is then not
identifiable from this data (an identifiability condition beside the veto).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from recon.config.run_config import BackdropConfig
from recon.diagnose.data import box_dilate
from recon.diagnose.records import Evidence

KIND = "backdrop"
# The candidates whose parameters are per-view camera gains, and the backdrop's reading of them.
GAIN_CANDIDATES = ("exposure", "white_balance")
# The per-view log gains each candidate is compared on (gain_components).
COMPONENTS = {
    "exposure": ("log gain",),
    "white_balance": ("log red / green", "log blue / green"),
}
REFINEMENTS = 3


@dataclass(frozen=True)
class BackdropReading:
    """The camera's per-view log gains read off a static backdrop.

    log_gains: [B, 3] per view and channel, centred over the views.
    noise: [B, 3] half the difference of the top and bottom halves' readings.
    pixels: the static backdrop pixels the reading used.
    """

    log_gains: torch.Tensor
    noise: torch.Tensor
    pixels: int


def read_backdrop(
    frames: torch.Tensor, masks: torch.Tensor, settings: BackdropConfig
) -> BackdropReading | None:
    """The per-view gains of the backdrop of frames [B, H, W, 3] (linear, straight colour)
    outside masks [B, H, W, 1] (object coverage); None where fewer than settings.minimum_pixels
    static pixels or fewer than settings.minimum_views views are there."""
    if frames.shape[0] < settings.minimum_views:
        return None
    coverage = (masks > 0.02).to(frames.dtype).permute(0, 3, 1, 2)
    near_object = box_dilate(coverage, settings.object_margin_pixels)[:, 0] > 0
    usable = (
        ~near_object & (frames.amin(-1) > settings.darkest) & (frames.amax(-1) < settings.brightest)
    ).all(0)
    if int(usable.sum()) < settings.minimum_pixels:
        return None
    # Only the usable pixels in double precision: large photos stay in their float32.
    logs = torch.log(frames[:, usable].double())  # [B, P, 3]
    gains = (logs - logs.median(0).values).median(1).values
    static = torch.ones(logs.shape[1], dtype=torch.bool)
    for _ in range(REFINEMENTS):
        steady = logs - gains[:, None, :]
        deviation = (steady - steady.median(0).values).abs().median(0).values.amax(-1)
        static = deviation < settings.static_tolerance
        if int(static.sum()) < settings.minimum_pixels:
            return None
        reference = steady[:, static].median(0).values
        gains = (logs[:, static] - reference).median(1).values
    rows = torch.nonzero(usable)[:, 0][static]
    top = rows < rows.double().median()
    if int(top.sum()) == 0 or int((~top).sum()) == 0:
        return None
    reference = (logs[:, static] - gains[:, None, :]).median(0).values
    upper = (logs[:, static][:, top] - reference[top]).median(1).values
    lower = (logs[:, static][:, ~top] - reference[~top]).median(1).values
    noise = (upper - upper.mean(0)) - (lower - lower.mean(0))
    return BackdropReading(gains - gains.mean(0), noise.abs() / 2, int(static.sum()))


def gain_components(candidate: str, log_gains: torch.Tensor) -> torch.Tensor:
    """The components of per-view log gains [B, 3] (red, green, blue) a candidate's parameters
    are compared on: [B, 1] the channels' mean (exposure), [B, 2] log red / green and blue /
    green (white balance); centred over the views."""
    if candidate == "exposure":
        components = log_gains.mean(-1, keepdim=True)
    elif candidate == "white_balance":
        components = log_gains[:, [0, 2]] - log_gains[:, [1]]
    else:
        raise ValueError(f"backdrop: no gain components for {candidate!r}")
    return components - components.mean(0)


def object_log_gains(candidate: str, parameters: dict) -> torch.Tensor | None:
    """A candidate's recovered per-view gains as log gains [B, 3] (None without them):
    exposure's ratios on every channel, white balance's per-channel gains."""
    if candidate == "exposure" and parameters.get("ratios"):
        ratios = torch.tensor(parameters["ratios"], dtype=torch.float64)
        return torch.log(ratios.clamp_min(1e-12))[:, None].expand(-1, 3)
    if candidate == "white_balance" and parameters.get("gains"):
        gains = torch.tensor(parameters["gains"], dtype=torch.float64)
        return torch.log(gains.clamp_min(1e-12))
    return None


def backdrop_parameters(candidate: str, reading: BackdropReading) -> dict:
    """The backdrop's per-view gains in the candidate's parameters: exposure ratios and stops
    (the channels' mean log gain, geometric mean 1 over the views), or white-balance gains per
    view [red, 1, blue] (over green)."""
    if candidate == "exposure":
        log_ratios = reading.log_gains.mean(-1)
        return {
            "ratios": torch.exp(log_ratios).tolist(),
            "stops": (log_ratios / math.log(2.0)).tolist(),
            "estimator": KIND,
        }
    gains = torch.exp(reading.log_gains - reading.log_gains[:, 1:2])
    return {"gains": gains.tolist(), "channels": ["red", "green", "blue"], "estimator": KIND}


def _rms(values: torch.Tensor) -> float:
    return float(values.pow(2).mean().sqrt())


def backdrop_evidence(
    candidate: str, recovered: torch.Tensor, reading: BackdropReading, settings: BackdropConfig
) -> Evidence | None:
    """Evidence of kind "backdrop" on a per-view gain candidate: recovered [B, 3] its log gains
    on the object, reading the backdrop's of the same views. None where the backdrop could not
    see the change the object shows (its noise hides it): no evidence either way."""
    if recovered.shape != reading.log_gains.shape:
        return None
    found = gain_components(candidate, recovered)
    frame = gain_components(candidate, reading.log_gains)
    noise = _rms(gain_components(candidate, reading.noise))
    spread = _rms(found)
    if spread <= settings.detectable_factor * noise or spread == 0.0:
        return None
    explained = 1.0 - _rms(found - frame) / spread
    shown = _rms(frame)
    details = {
        "views": int(found.shape[0]),
        "pixels": reading.pixels,
        "object_spread": spread,
        "backdrop_spread": shown,
        "backdrop_noise": noise,
        "correlation": _correlation(found, frame),
        "backdrop_log_gains": reading.log_gains.tolist(),
        # What was compared, per view (the figure's curves): centred log gains.
        "components": list(COMPONENTS[candidate]),
        "object_components": found.tolist(),
        "backdrop_components": frame.tolist(),
    }
    passed = explained >= settings.minimum_explained
    if passed:
        # The camera's gain, measured on pixels no model has to explain: what the candidate
        # reports (recon.diagnose.decision reads these parameters first).
        details["parameters"] = backdrop_parameters(candidate, reading)
    what = "log gain" if candidate == "exposure" else "log colour gain"
    measured = (
        f"{candidate}: the static backdrop in the same frames ({reading.pixels} pixels, "
        f"{found.shape[0]} views) changes by {100 * shown:.1f} % RMS {what} where the object's "
        f"gains change by {100 * spread:.1f} %; it shows {100 * explained:.0f} % of that change"
    )
    if passed:
        reason = f"{measured}: the camera's gain, which scales the whole frame"
    else:
        reason = (
            f"{measured} (at least {100 * settings.minimum_explained:.0f} % needed): the rest is "
            "the object's own change from view to view (its view-dependent reflectance), not "
            "the camera's, which would scale the backdrop as well"
        )
    return Evidence(KIND, candidate, explained, settings.minimum_explained, passed, reason, details)


CAPTURE = {
    "exposure": "a grey card that turns with the object in every view, or the photos' EXIF "
    "exposure",
    "white_balance": "a grey card or colour chart that turns with the object in every view, or "
    "a manual white balance",
}


def backdrop_condition(
    veto: Evidence, reading: BackdropReading, settings: BackdropConfig
) -> Evidence | None:
    """Where the backdrop vetoed a gain (veto, failed) yet changes itself beyond its reading
    noise, the camera's gain is there but cannot be read on the object: an identifiability
    Evidence (failed) saying so and what capture would settle it; None where the backdrop
    shows no change of its own (the veto is the whole answer)."""
    if veto.passed:
        return None
    candidate = veto.candidate
    shown = float(veto.details["backdrop_spread"])
    noise = float(veto.details["backdrop_noise"])
    if shown <= settings.detectable_factor * noise:
        return None
    spread = float(veto.details["object_spread"])
    reason = (
        f"the static backdrop shows the frames changing by {100 * shown:.1f} % from view to "
        f"view (its reading noise {100 * noise:.1f} %), but the object's own change "
        f"({100 * spread:.1f} %, which does not follow the backdrop) hides that gain on the object"
    )
    details = {
        "backdrop_spread": shown,
        "backdrop_noise": noise,
        "object_spread": spread,
        "capture": CAPTURE[candidate],
        "source": KIND,
    }
    return Evidence(
        "identifiability",
        candidate,
        shown,
        settings.detectable_factor * noise,
        False,
        reason,
        details,
    )


def _correlation(one: torch.Tensor, other: torch.Tensor) -> float:
    """Pearson correlation of two centred [B, K] readings over all their entries (0 when
    either is constant)."""
    norm = float(one.norm() * other.norm())
    return float((one * other).sum()) / norm if norm > 0 else 0.0
