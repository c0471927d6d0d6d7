"""Capture metadata from a photo's EXIF: exposure time, f-number, ISO, white-balance mode and
camera model.

Read with Pillow (only the header is parsed; the pixels are not decoded). A photo without EXIF,
or a tag that is missing or unreadable, gives None for that value.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

from PIL import Image

# EXIF tag numbers (EXIF 2.3): the main IFD's Model and the Exif sub-IFD's exposure tags.
_MAKE, _MODEL = 0x010F, 0x0110
_EXIF_IFD = 0x8769
_EXPOSURE_TIME, _F_NUMBER = 0x829A, 0x829D
_ISO, _ISO_OLD = 0x8827, 0x8833  # PhotographicSensitivity (ISOSpeedRatings) / StandardOutputSens.
_WHITE_BALANCE = 0xA403  # 0: auto, 1: manual (EXIF 2.3)
WHITE_BALANCE_MODES = {0: "auto", 1: "manual"}

EXIF_KEYS = ("exposure_time", "f_number", "iso", "white_balance", "camera_model")


def _positive_number(value: Any) -> float | None:
    """A finite positive float from an EXIF rational, integer or a tuple of them."""
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def read_exif(path: str | os.PathLike) -> dict[str, float | str | None]:
    """{exposure_time (s), f_number, iso, white_balance ("auto" or "manual"), camera_model} of
    one image file (None where absent).

    Files Pillow cannot open (EXR) or without EXIF give all None.
    """
    result: dict[str, float | str | None] = dict.fromkeys(EXIF_KEYS)
    if Path(path).suffix.lower() == ".exr":
        return result
    try:
        with Image.open(path) as image:
            exif = image.getexif()
            sub = exif.get_ifd(_EXIF_IFD)
    except (OSError, ValueError, SyntaxError):
        return result
    result["exposure_time"] = _positive_number(sub.get(_EXPOSURE_TIME, exif.get(_EXPOSURE_TIME)))
    result["f_number"] = _positive_number(sub.get(_F_NUMBER, exif.get(_F_NUMBER)))
    result["iso"] = _positive_number(
        sub.get(_ISO, sub.get(_ISO_OLD, exif.get(_ISO, exif.get(_ISO_OLD))))
    )
    mode = sub.get(_WHITE_BALANCE, exif.get(_WHITE_BALANCE))
    result["white_balance"] = WHITE_BALANCE_MODES.get(mode) if isinstance(mode, int) else None
    model = exif.get(_MODEL)
    if isinstance(model, bytes):
        model = model.decode("ascii", "replace")
    if isinstance(model, str):
        make = exif.get(_MAKE)
        model = model.strip("\x00 ").strip()
        result["camera_model"] = model or None
        if isinstance(make, str) and make.strip() and result["camera_model"] is None:
            result["camera_model"] = make.strip()
    return result


def exposure_value(metadata: dict[str, Any]) -> float | None:
    """Relative sensor exposure time x ISO / f_number^2 (None when a value is missing): the
    factor by which the recorded linear signal scales for a fixed scene radiance."""
    time, aperture, iso = (metadata.get(key) for key in ("exposure_time", "f_number", "iso"))
    if time is None or aperture is None or iso is None:
        return None
    return float(time) * float(iso) / float(aperture) ** 2
