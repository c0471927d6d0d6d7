"""Shared machinery of the world-side image effects: validated strength parameters and checks.

Every world effect is a WorldEffect subclass that declares its strength parameters as
ParameterSpec entries (default, inclusive range, kind). Construction validates a dict of
parameters against them; per-view quantities (exposure ratios, colour temperatures, pose
perturbations, noise) are drawn in apply() from the generator passed in, while per-lens quantities
(distortion coefficients, vignetting centre, blur radius) are parameters, so that every split of
one dataset sees the same lens.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar, Literal

import torch

from data_synth.effects.base import AppliedEffect, Capture, Stage
from recon.camera import Cameras
from recon.errors import ReconError

ParameterKind = Literal["float", "int", "bool"]

# The nominal capture sample_strength assumes when it is given no cameras: the benchmark's
# 128-pixel square images with a 40 degree horizontal field of view.
NOMINAL_IMAGE_SIZE = (128, 128)
NOMINAL_FOV_X_DEG = 40.0


@dataclass(frozen=True)
class ParameterSpec:
    """One strength parameter: its default, inclusive range [minimum, maximum] and kind.

    kind "bool" accepts True/False or the numbers 0/1 (run configs hold floats only).
    """

    default: float | int | bool
    minimum: float
    maximum: float
    description: str
    kind: ParameterKind = "float"


class WorldEffect:
    """Base class of the world effects (implements data_synth.effects.base.ImageEffect).

    Subclasses set name, stage and PARAMETERS and implement apply(); they may override
    sample_strength() to draw plausible strengths for blind (withheld) datasets.
    """

    name: ClassVar[str] = ""
    stage: ClassVar[Stage] = "sensor"
    supersampled: ClassVar[bool] = False
    PARAMETERS: ClassVar[dict[str, ParameterSpec]] = {}

    def __init__(self, parameters: Mapping[str, object] | None = None) -> None:
        self.parameters: dict[str, float | int | bool] = self.validate(parameters or {})

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.parameters})"

    @classmethod
    def default_parameters(cls) -> dict[str, float | int | bool]:
        """The strength parameters used where a config gives none."""
        return {key: spec.default for key, spec in cls.PARAMETERS.items()}

    @classmethod
    def validate(cls, parameters: Mapping[str, object]) -> dict[str, float | int | bool]:
        """Defaults overridden by parameters, each checked against its ParameterSpec.

        Raises ReconError naming the effect and the parameter (with the closest known name for
        an unknown one).
        """
        if not isinstance(parameters, Mapping):
            raise ReconError(
                f"effect {cls.name}: parameters must be a mapping of name -> value, "
                f"got {type(parameters).__name__}"
            )
        values = cls.default_parameters()
        for key, value in parameters.items():
            if key not in cls.PARAMETERS:
                close = difflib.get_close_matches(str(key), list(cls.PARAMETERS), n=1)
                hint = f"; did you mean '{close[0]}'?" if close else ""
                raise ReconError(
                    f"effect {cls.name}: unknown parameter '{key}'{hint} "
                    f"(known: {', '.join(sorted(cls.PARAMETERS))})"
                )
            values[key] = _check_value(cls.name, key, value, cls.PARAMETERS[key])
        return values

    @classmethod
    def sample_strength(
        cls, generator: torch.Generator, cameras: Cameras | None = None
    ) -> dict[str, float | int | bool]:
        """Random but plausible strengths (a valid parameter dict) for blind datasets.

        cameras, when given, adapts pixel-scale quantities to their image size and field of
        view; otherwise a 128 x 128 image with a 40 degree field of view is assumed.
        """
        return cls.default_parameters()

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        raise NotImplementedError


def _check_value(effect: str, key: str, value: object, spec: ParameterSpec) -> float | int | bool:
    """value converted to spec.kind, or ReconError naming effect and parameter."""
    where = f"effect {effect}: parameter '{key}'"
    if spec.kind == "bool":
        if isinstance(value, bool):
            return value
        if isinstance(value, (int, float)) and value in (0, 1):
            return bool(value)
        raise ReconError(f"{where}: expected true/false (or 0/1), got {value!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ReconError(f"{where}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise ReconError(f"{where}: expected a finite number, got {value!r}")
    if spec.kind == "int":
        if float(value) != int(value):
            raise ReconError(f"{where}: expected an integer, got {value!r}")
        value = int(value)
    else:
        value = float(value)
    if not spec.minimum <= value <= spec.maximum:
        raise ReconError(
            f"{where}: expected a value in [{spec.minimum:g}, {spec.maximum:g}], got {value:g}"
        )
    return value


# --------------------------------------------------------------------------------------------
# Helpers shared by the effects
# --------------------------------------------------------------------------------------------


def check_capture(capture: Capture, effect: str) -> tuple[int, int, int]:
    """(B, H, W) of a capture, or ReconError when images, alpha and cameras disagree."""
    images, alpha = capture.images, capture.alpha
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ReconError(
            f"effect {effect}: capture.images: expected shape [B, H, W, 3], got {tuple(images.shape)}"
        )
    count, height, width = images.shape[:3]
    if tuple(alpha.shape) != (count, height, width, 1):
        raise ReconError(
            f"effect {effect}: capture.alpha: expected shape {[count, height, width, 1]}, "
            f"got {list(alpha.shape)}"
        )
    if len(capture.cameras) != count:
        raise ReconError(
            f"effect {effect}: capture.cameras: expected {count} cameras, got {len(capture.cameras)}"
        )
    if tuple(capture.cameras.image_size) != (height, width):
        raise ReconError(
            f"effect {effect}: capture.cameras.image_size {capture.cameras.image_size} does not "
            f"match the images ({height}, {width})"
        )
    return count, height, width


def standard_normal(
    shape: tuple[int, ...], generator: torch.Generator, like: torch.Tensor
) -> torch.Tensor:
    """N(0, 1) draws of shape, made on the generator's device (so the stream does not depend on
    where the images live) and moved to like's device and float dtype."""
    draws = torch.randn(shape, generator=generator, device=generator.device, dtype=torch.float64)
    return draws.to(device=like.device, dtype=like.dtype)


def uniform(shape: tuple[int, ...], generator: torch.Generator, like: torch.Tensor) -> torch.Tensor:
    """U[0, 1) draws of shape on the generator's device, moved to like's device and dtype."""
    draws = torch.rand(shape, generator=generator, device=generator.device, dtype=torch.float64)
    return draws.to(device=like.device, dtype=like.dtype)


def sample_uniform(generator: torch.Generator, low: float, high: float) -> float:
    """One U[low, high) draw as a Python float (for sample_strength)."""
    return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))


def sample_sign(generator: torch.Generator) -> float:
    """+1 or -1 with equal probability."""
    return 1.0 if float(torch.rand((), generator=generator, dtype=torch.float64)) < 0.5 else -1.0


def nominal_geometry(cameras: Cameras | None) -> tuple[tuple[int, int], float]:
    """(image_size, mean focal length in pixels) of cameras, or of the nominal capture."""
    if cameras is None:
        height, width = NOMINAL_IMAGE_SIZE
        focal = 0.5 * width / math.tan(math.radians(NOMINAL_FOV_X_DEG) / 2)
        return (height, width), focal
    focal = float(cameras.intrinsics[:, [0, 1], [0, 1]].double().mean())
    return tuple(cameras.image_size), focal


def corner_radius_normalised(cameras: Cameras | None) -> float:
    """Mean tan(field angle) of the image corner, sqrt((W/2/fx)^2 + (H/2/fy)^2)."""
    (height, width), focal = nominal_geometry(cameras)
    return math.hypot(0.5 * width / focal, 0.5 * height / focal)


def pixel_grid(height: int, width: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates (column u [H, W], row v [H, W]) with centres at i + 0.5."""
    rows = torch.arange(height, device=like.device, dtype=like.dtype) + 0.5
    columns = torch.arange(width, device=like.device, dtype=like.dtype) + 0.5
    v, u = torch.meshgrid(rows, columns, indexing="ij")
    return u, v


def to_list(values: torch.Tensor, digits: int = 6) -> list:
    """A tensor as nested Python lists of floats rounded to digits significant digits (JSON)."""
    return _round_nested(values.detach().double().cpu().tolist(), digits)


def _round_nested(values, digits: int):
    if isinstance(values, list):
        return [_round_nested(value, digits) for value in values]
    return float(f"{values:.{digits}g}")


def round_float(value: float, digits: int = 6) -> float:
    """value rounded to digits significant digits (JSON)."""
    return float(f"{float(value):.{digits}g}")
