"""Response-stage world effect: a camera's filmic tone curve instead of the sRGB encoding.

A camera does not write sRGB(E) of the linear exposure E: its image processor applies a tone
curve with a toe (shadows compressed), a shoulder (highlights rolled off) and its own encoding
gamma. The dataset's PNG writer encodes linear values with sRGB, so to make the stored code value
equal to the camera's curve(E), this effect replaces the linear image by srgb_to_linear(curve(E)):
a reader that decodes sRGB then sees the curve's distortion. The model side fits a gamma or a
monotone LUT; this curve is neither (a rational toe, a rational shoulder, then a power).
"""

from __future__ import annotations

import torch

from data_synth.effects.base import AppliedEffect, Capture
from data_synth.effects.world_effect import (
    ParameterSpec,
    WorldEffect,
    check_capture,
    round_float,
    sample_uniform,
    to_list,
)
from recon.camera import Cameras
from recon.io.images import linear_to_srgb, srgb_to_linear

# Samples of the realised curve table, and the range over which its effective exponent is fit.
TABLE_SAMPLES = 256
_FIT_RANGE = (0.05, 0.9)
MID_GREY = 0.18


class ResponseCurve(WorldEffect):
    """code(E) = clamp(shoulder(toe(E)), 0, 1)^(1 / gamma), stored as srgb_to_linear(code).

    toe(E) = (1 + t) E^2 / (E + t): quadratic (crushed) below E ~ t, linear above; toe(1) = 1.
    shoulder(x) = (1 + s) x / (1 + s x): slope 1 + s at black, 1 / (1 + s) at 1, shoulder(1) = 1.
    Both are monotone and map 0 to 0 and 1 to 1, so the curve is monotone with code(0) = 0 and
    code(1) = 1; exposures above 1 saturate. Realised: the parameters, a 256-sample table of
    observed linear (what an sRGB reader gets) against true linear on [0, 1], the mid-grey
    mapping and the effective exponent k of a fit observed ~ E^k over E in [0.05, 0.9].
    """

    name = "response_curve"
    stage = "response"
    PARAMETERS = {
        "toe": ParameterSpec(0.05, 0.0, 1.0, "toe knee t: exposures below ~t are crushed"),
        "shoulder": ParameterSpec(0.5, 0.0, 10.0, "shoulder s: highlight compression"),
        "gamma": ParameterSpec(2.2, 1.0, 4.0, "encoding gamma of the camera (code = x^(1/gamma))"),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """toe 0.01-0.08, shoulder 0.2-1.0, gamma 1.8-2.6: mid-grey lands within roughly
        code 0.35-0.6 (sRGB: 0.46), like camera JPEG engines."""
        return {
            "toe": round_float(sample_uniform(generator, 0.01, 0.08)),
            "shoulder": round_float(sample_uniform(generator, 0.2, 1.0)),
            "gamma": round_float(sample_uniform(generator, 1.8, 2.6)),
        }

    def code_value(self, exposure: torch.Tensor) -> torch.Tensor:
        """The camera's encoded value in [0, 1] for linear exposure [...] (any shape)."""
        toe = float(self.parameters["toe"])
        shoulder = float(self.parameters["shoulder"])
        gamma = float(self.parameters["gamma"])
        exposure = exposure.clamp(min=0.0)
        if toe > 0:
            # (1 + t) E^2 / (E + t), written as E * (1 + t) * E / (E + t) so E = 0 gives 0, not 0/0.
            toed = exposure * (1 + toe) * exposure / (exposure + toe)
        else:
            toed = exposure
        shouldered = (1 + shoulder) * toed / (1 + shoulder * toed)
        return shouldered.clamp(0.0, 1.0) ** (1.0 / gamma)

    def observed_linear(self, exposure: torch.Tensor) -> torch.Tensor:
        """What a reader decoding the stored sRGB PNG gets for linear exposure [...]."""
        return srgb_to_linear(self.code_value(exposure))

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] <- srgb_to_linear(code(images)); alpha and cameras unchanged.

        The curve acts on the pixel value (premultiplied radiance = what the photosite saw
        against a black background), as a camera's does.
        """
        check_capture(capture, self.name)
        capture.images = self.observed_linear(capture.images)
        true_linear = torch.linspace(0.0, 1.0, TABLE_SAMPLES, dtype=torch.float64)
        observed = self.observed_linear(true_linear)
        return AppliedEffect(
            self.name,
            {
                **self.parameters,
                "table": {
                    "true_linear": to_list(true_linear),
                    "observed_linear": to_list(observed),
                },
                "mid_grey": {
                    "true_linear": MID_GREY,
                    "observed_linear": round_float(
                        float(self.observed_linear(torch.tensor(MID_GREY, dtype=torch.float64)))
                    ),
                    "code_value": round_float(
                        float(self.code_value(torch.tensor(MID_GREY, dtype=torch.float64)))
                    ),
                    "srgb_code_value": round_float(
                        float(linear_to_srgb(torch.tensor(MID_GREY, dtype=torch.float64)))
                    ),
                },
                "effective_exponent": round_float(self.effective_exponent()),
            },
        )

    def effective_exponent(self) -> float:
        """k of the least-squares fit log(observed) = k log(E) over E in [0.05, 0.9]: what a
        pure-gamma model would recover (1 for an unaltered sRGB pipeline)."""
        exposure = torch.linspace(*_FIT_RANGE, 200, dtype=torch.float64)
        observed = self.observed_linear(exposure).clamp(min=1e-12)
        log_exposure, log_observed = torch.log(exposure), torch.log(observed)
        return float((log_exposure * log_observed).sum() / (log_exposure * log_exposure).sum())
