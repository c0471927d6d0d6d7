"""Sensor-stage world effects on linear radiance: exposure, white balance, noise.

Applied in that order (registry.APPLICATION_ORDER): the shutter/ISO scales the light reaching
the sensor, the illuminant colour mismatch tints it, and the photosites then count photons
(Poisson) and add read noise (Gaussian). The model side uses a per-view gain and per-view channel
gains; the world differs: log-normal shutter ratios with saturation at the full well, and
white-balance gains that move along the Planckian locus (plus a tint off it) instead of three
free gains.
"""

from __future__ import annotations

import math

import torch

from data_synth.effects.base import AppliedEffect, Capture
from data_synth.effects.world_effect import (
    ParameterSpec,
    WorldEffect,
    check_capture,
    round_float,
    sample_uniform,
    standard_normal,
    to_list,
)
from recon.camera import Cameras

# --------------------------------------------------------------------------------------------
# exposure
# --------------------------------------------------------------------------------------------


class Exposure(WorldEffect):
    """Per-view exposure as a camera in auto-exposure mode produces it.

    Each view's shutter time x ISO gain is off the nominal by a factor 2^(spread_stops * N(0, 1))
    (exposure errors are symmetric in stops, i.e. log-normal in linear light), then every
    channel saturates at full_well (a photosite cannot hold more charge; 1e9 = no clipping).
    Realised: per-view ratios and stops, and the fraction of clipped channel values.
    """

    name = "exposure"
    stage = "sensor"
    PARAMETERS = {
        "spread_stops": ParameterSpec(0.5, 0.0, 3.0, "std of the per-view exposure in stops"),
        "full_well": ParameterSpec(
            1.0e9, 1.0e-3, 1.0e9, "linear value at which channels saturate (1e9 = off)"
        ),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """spread 0.3-0.8 stops; no clipping: the 8-bit writer already saturates at 1, which is
        where a camera puts its full well, so an extra clip would be a second, confounded
        effect."""
        return {
            "spread_stops": round_float(sample_uniform(generator, 0.3, 0.8)),
            "full_well": 1.0e9,
        }

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] *= ratio[b], then min(., full_well); alpha and cameras unchanged."""
        count = check_capture(capture, self.name)[0]
        stops = self.parameters["spread_stops"] * standard_normal(
            (count,), generator, capture.images
        )
        ratios = torch.exp2(stops)
        exposed = capture.images * ratios[:, None, None, None]
        full_well = float(self.parameters["full_well"])
        clipped = exposed > full_well
        capture.images = exposed.clamp(min=0.0, max=full_well)
        return AppliedEffect(
            self.name,
            {
                "ratios": to_list(ratios),
                "stops": to_list(stops),
                "spread_stops": self.parameters["spread_stops"],
                "full_well": full_well,
                "clipped_fraction": round_float(float(clipped.double().mean())),
            },
        )


# --------------------------------------------------------------------------------------------
# white balance
# --------------------------------------------------------------------------------------------

# Planck's second radiation constant h c / k in metre kelvin.
_SECOND_RADIATION_CONSTANT = 1.4387769e-2
# CIE 1931 2-degree colour matching functions as the multi-lobe piecewise-Gaussian fit of
# Wyman, Sloan and Shirley (JCGT 2013): (weight, mean nm, sigma left, sigma right) per lobe.
_MATCHING_LOBES = {
    "x": ((1.056, 599.8, 37.9, 31.0), (0.362, 442.0, 16.0, 26.7), (-0.065, 501.1, 20.4, 26.2)),
    "y": ((0.821, 568.8, 46.9, 40.5), (0.286, 530.9, 16.3, 31.1)),
    "z": ((1.217, 437.0, 11.8, 36.0), (0.681, 459.0, 26.0, 13.8)),
}
# CIE XYZ -> linear sRGB (D65), IEC 61966-2-1.
_XYZ_TO_LINEAR_SRGB = (
    (3.2406, -1.5372, -0.4986),
    (-0.9689, 1.8758, 0.0415),
    (0.0557, -0.2040, 1.0570),
)
# Temperatures are kept where the blackbody colour stays inside the sRGB gamut's positive blue.
MINIMUM_KELVIN = 2500.0
MAXIMUM_KELVIN = 20000.0


def blackbody_rgb(kelvin: torch.Tensor) -> torch.Tensor:
    """Linear sRGB colour [..., 3] of blackbody radiators at temperatures kelvin [...], green = 1.

    Planck's law integrated against the CIE 1931 matching functions (380-780 nm, 5 nm steps),
    converted XYZ -> linear sRGB. The locus is curved in RGB, unlike three free channel gains.
    """
    wavelength_nm = torch.arange(380.0, 781.0, 5.0, dtype=torch.float64, device=kelvin.device)
    matching = []
    for lobes in _MATCHING_LOBES.values():
        curve = torch.zeros_like(wavelength_nm)
        for weight, mean, sigma_left, sigma_right in lobes:
            sigma = torch.where(wavelength_nm < mean, sigma_left, sigma_right)
            curve = curve + weight * torch.exp(-0.5 * ((wavelength_nm - mean) / sigma) ** 2)
        matching.append(curve)
    matching = torch.stack(matching, dim=-1)  # [L, 3]
    wavelength_m = wavelength_nm * 1e-9
    temperature = kelvin.double()[..., None]
    # Spectral radiance up to a constant: lambda^-5 / (exp(c2 / (lambda T)) - 1).
    radiance = wavelength_m**-5 / torch.expm1(
        _SECOND_RADIATION_CONSTANT / (wavelength_m * temperature)
    )
    xyz = radiance @ matching  # [..., 3]
    to_rgb = torch.tensor(_XYZ_TO_LINEAR_SRGB, dtype=torch.float64, device=kelvin.device)
    rgb = xyz @ to_rgb.T
    return rgb / rgb[..., 1:2]


class WhiteBalance(WorldEffect):
    """Per-view white-balance error: the camera is balanced for reference_kelvin but each view's
    illuminant (or auto-white-balance estimate) sits at reference + spread_kelvin * N(0, 1)
    kelvin on the Planckian locus, plus a green-magenta tint off the locus of std spread_tint.

    Gains per view = blackbody_rgb(T_view) / blackbody_rgb(T_reference), normalised so green = 1,
    with red and blue then multiplied by exp(-tint) (a positive tint is a green cast). They scale
    the linear RGB channels. Realised: per-view gains [B, 3], temperatures and tints.
    """

    name = "white_balance"
    stage = "sensor"
    PARAMETERS = {
        "spread_kelvin": ParameterSpec(
            500.0, 0.0, 5000.0, "std of the per-view colour temperature offset in kelvin"
        ),
        "reference_kelvin": ParameterSpec(
            6500.0, MINIMUM_KELVIN, 12000.0, "colour temperature the camera is balanced for"
        ),
        "spread_tint": ParameterSpec(
            0.0, 0.0, 0.3, "std of the per-view green-magenta tint (log gain of green vs red/blue)"
        ),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """spread 400-1200 K around 5000-7000 K (gains ~5-15 % per view), tint std 0-0.03."""
        return {
            "spread_kelvin": round_float(sample_uniform(generator, 400.0, 1200.0)),
            "reference_kelvin": round_float(sample_uniform(generator, 5000.0, 7000.0)),
            "spread_tint": round_float(sample_uniform(generator, 0.0, 0.03)),
        }

    def gains(self, kelvin: torch.Tensor, tint: torch.Tensor) -> torch.Tensor:
        """Channel gains [B, 3] (green 1) for view temperatures kelvin [B] and tints [B]."""
        reference = torch.tensor(float(self.parameters["reference_kelvin"]), dtype=torch.float64)
        gains = blackbody_rgb(kelvin) / blackbody_rgb(reference.to(kelvin.device))
        gains = gains / gains[:, 1:2]
        off_locus = torch.exp(-tint.double())
        return gains * torch.stack([off_locus, torch.ones_like(off_locus), off_locus], dim=-1)

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] *= gains[b, c]; alpha and cameras unchanged."""
        count = check_capture(capture, self.name)[0]
        draws = standard_normal((2, count), generator, capture.images.double())
        kelvin = self.parameters["reference_kelvin"] + self.parameters["spread_kelvin"] * draws[0]
        kelvin = kelvin.clamp(MINIMUM_KELVIN, MAXIMUM_KELVIN)
        tint = self.parameters["spread_tint"] * draws[1]
        gains = self.gains(kelvin, tint)
        capture.images = capture.images * gains.to(capture.images.dtype)[:, None, None, :]
        return AppliedEffect(
            self.name,
            {
                "gains": to_list(gains),
                "kelvin": to_list(kelvin),
                "tint": to_list(tint),
                "reference_kelvin": self.parameters["reference_kelvin"],
            },
        )


# --------------------------------------------------------------------------------------------
# noise
# --------------------------------------------------------------------------------------------

# A typical interchangeable-lens sensor: about 20 000 photo-electrons at saturation at ISO 100;
# raising the ISO by a factor k maps k times fewer electrons to the same output value.
_BASE_ISO = 100.0
_BASE_FULL_WELL_ELECTRONS = 20000.0


class Noise(WorldEffect):
    """Poisson-Gaussian sensor noise: photon shot noise plus Gaussian read noise.

    A linear value I is I * full_well_photons expected photo-electrons; the sensor counts a
    Poisson number of them, divides back, and adds N(0, read_noise^2). The variance is therefore
    a * I + b with a = 1 / full_well_photons and b = read_noise^2. Negative results (read noise
    below black) are clipped at 0, as the output encoding does. 8-bit quantisation happens when
    the PNG is written, not here. Realised: a, b (and the two parameters).
    """

    name = "noise"
    stage = "sensor"
    PARAMETERS = {
        "full_well_photons": ParameterSpec(
            2000.0,
            1.0,
            1.0e8,
            "photo-electrons collected at linear value 1 (shot noise a = 1/this)",
        ),
        "read_noise": ParameterSpec(
            0.002, 0.0, 0.2, "std of the Gaussian read noise in linear units (b = this^2)"
        ),
    }

    @classmethod
    def sample_strength(cls, generator: torch.Generator, cameras: Cameras | None = None) -> dict:
        """A camera at ISO 400-1600 (log-uniform): 5000-1250 electrons at white, 1.5-4
        electrons of read noise."""
        iso = math.exp(sample_uniform(generator, math.log(400.0), math.log(1600.0)))
        electrons = _BASE_FULL_WELL_ELECTRONS * _BASE_ISO / iso
        read_electrons = sample_uniform(generator, 1.5, 4.0)
        return {
            "full_well_photons": round_float(electrons),
            "read_noise": round_float(read_electrons / electrons),
        }

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        """images [B, H, W, 3] <- max(Poisson(I n) / n + N(0, read_noise^2), 0), n the full well."""
        check_capture(capture, self.name)
        images = capture.images
        photons = float(self.parameters["full_well_photons"])
        read_noise = float(self.parameters["read_noise"])
        # Drawn on the generator's device so the noise does not depend on where images live;
        # float32 counts: exact up to 2^24 photons, and rounded by 6e-8 relative above that,
        # far below the shot noise.
        rate = (images.detach().clamp(min=0.0) * photons).to(generator.device, torch.float32)
        counts = torch.poisson(rate, generator=generator)
        read = torch.randn(
            rate.shape, generator=generator, device=generator.device, dtype=torch.float32
        )
        noisy = counts / photons + read_noise * read
        capture.images = noisy.clamp(min=0.0).to(device=images.device, dtype=images.dtype)
        return AppliedEffect(
            self.name,
            {
                "a": round_float(1.0 / photons),
                "b": round_float(read_noise**2),
                "full_well_photons": photons,
                "read_noise": read_noise,
            },
        )
