"""Validation helpers for schema ``__post_init__`` methods.

A schema raises ConfigFieldError (usually through check_range) with the field's key relative to
the dataclass; the loader catches it and re-raises a ConfigError that adds the file, the line
and the full dotted key path. Built directly in Python, the schema still raises a ConfigError.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from recon.errors import ConfigError


class ConfigFieldError(ConfigError):
    """One field of a schema dataclass is invalid.

    key: the field's key relative to the dataclass (``"lr"``, ``"fov_deg[1]"``).
    reason: what is wrong, including the actual value (``"must be > 0, got -1.0"``).
    """

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(f"{key}: {reason}")
        self.key = key
        self.reason = reason

    def __reduce__(self) -> tuple:
        # The default pickling would call __init__ with the one formatted message.
        return (type(self), (self.key, self.reason))


def describe_bounds(
    low: float | None, high: float | None, low_inclusive: bool, high_inclusive: bool
) -> str:
    """``in [0, 1)``, ``>= 0`` or ``< 1``: the accepted range in words."""
    if low is not None and high is not None:
        opening = "[" if low_inclusive else "("
        closing = "]" if high_inclusive else ")"
        return f"in {opening}{low}, {high}{closing}"
    if low is not None:
        return f">= {low}" if low_inclusive else f"> {low}"
    if high is not None:
        return f"<= {high}" if high_inclusive else f"< {high}"
    return "a number"


def check_range(
    value: float | Sequence[float] | None,
    key: str,
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> None:
    """Raise ConfigFieldError unless value lies within the bounds (inclusive by default).

    value may be a number, a list/tuple of numbers (each is checked; the key names the index)
    or None (skipped, so Optional fields can be checked without a guard). NaN is always
    rejected, because every comparison with NaN is false and it would slip through.
    """
    if value is None:
        return
    if isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            check_range(
                item,
                f"{key}[{index}]",
                low,
                high,
                low_inclusive=low_inclusive,
                high_inclusive=high_inclusive,
            )
        return
    bounds = describe_bounds(low, high, low_inclusive, high_inclusive)
    if math.isnan(value):
        raise ConfigFieldError(key, f"must be {bounds}, got nan")
    too_low = low is not None and (value < low if low_inclusive else value <= low)
    too_high = high is not None and (value > high if high_inclusive else value >= high)
    if too_low or too_high:
        raise ConfigFieldError(key, f"must be {bounds}, got {value!r}")
