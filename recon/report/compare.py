"""Compare a run's metrics with a baseline: what users put in their CI for regression tests.

Baseline file (YAML or JSON): dotted metric names from metrics.json with bounds, e.g.

    image.psnr: {min: 32.0}
    geometry.chamfer_l1: {max: 0.002}
    geometry.f1@1%: {value: 0.99, tolerance: 0.01, better: higher}

min/max are hard bounds; value + tolerance + better says how far the metric may move in the
bad direction from a recorded value.
"""

from __future__ import annotations

import difflib
import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from recon.errors import ReconError
from recon.io.atomic import atomic_write_text

# Which way is better for the metrics recon writes (used by write_baseline).
HIGHER_IS_BETTER = ("psnr", "ssim", "f1", "precision", "recall", "normal_consistency")


@dataclass
class Comparison:
    metric: str
    value: float | None
    bound: str
    passed: bool


def metric_value(metrics: dict, dotted: str) -> float | None:
    """metrics['image']['psnr'] for 'image.psnr' (keys may contain '@' and '%')."""
    group, _, key = dotted.partition(".")
    values = metrics.get(group)
    value = values.get(key) if key and isinstance(values, dict) else None if key else values
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value)


BOUND_KEYS = ("min", "max", "value", "tolerance", "better")


def _check_bounds(path: Path, metric: str, bounds: object) -> None:
    """One metric's bounds: known keys, numbers where numbers go, better in higher/lower."""
    if not isinstance(bounds, dict) or not set(bounds) <= set(BOUND_KEYS) or not bounds:
        raise ReconError(
            f"baseline {path}: {metric}: expected keys among {', '.join(BOUND_KEYS)}; "
            f"got {bounds!r}"
        )
    for key in ("min", "max", "value", "tolerance"):
        if key not in bounds:
            continue
        value = bounds[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            raise ReconError(f"baseline {path}: {metric}.{key}: expected a number, got {value!r}")
    if "tolerance" in bounds and bounds["tolerance"] < 0:
        raise ReconError(
            f"baseline {path}: {metric}.tolerance: expected >= 0, got {bounds['tolerance']}"
        )
    if bounds.get("better", "higher") not in ("higher", "lower"):
        raise ReconError(
            f"baseline {path}: {metric}.better: expected 'higher' or 'lower', got "
            f"{bounds['better']!r}"
        )
    if ("tolerance" in bounds or "better" in bounds) and "value" not in bounds:
        raise ReconError(f"baseline {path}: {metric}: 'tolerance' and 'better' need a 'value'")


def load_baseline(path: str | Path) -> dict:
    """Read and check a baseline file (ReconError naming the file, metric and key)."""
    path = Path(path)
    if not path.is_file():
        raise ReconError(f"baseline {path}: file not found")
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError, UnicodeDecodeError) as error:
        raise ReconError(
            f"baseline {path}: not valid {path.suffix[1:] or 'YAML'}: {error}"
        ) from error
    if not isinstance(data, dict) or not data:
        raise ReconError(f"baseline {path}: expected a mapping of metric -> bounds, got {data!r}")
    for metric, bounds in data.items():
        _check_bounds(path, str(metric), bounds)
    return data


def _known_metrics(metrics: dict) -> list[str]:
    return [
        f"{group}.{key}"
        for group, values in metrics.items()
        if isinstance(values, dict)
        for key, value in values.items()
        if isinstance(value, (int, float)) and not isinstance(value, bool)
    ]


def compare(metrics: dict, baseline: dict, source: str | Path = "metrics.json") -> list[Comparison]:
    """Each bound of the baseline checked against the run's metrics.

    A metric the baseline names but the run does not have is an error (a misspelt name must not
    read as a regression): ReconError naming it, with the closest known names.
    """
    known = _known_metrics(metrics)
    for metric in baseline:
        if metric_value(metrics, metric) is None:
            close = difflib.get_close_matches(metric, known, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ReconError(
                f"baseline metric {metric!r}: not in {source} (it has {len(known)} numeric "
                f"metrics){hint}"
            )
    results = []
    for metric, bounds in baseline.items():
        value = metric_value(metrics, metric)
        checks = []
        if "min" in bounds:
            checks.append((f">= {bounds['min']}", value >= bounds["min"]))
        if "max" in bounds:
            checks.append((f"<= {bounds['max']}", value <= bounds["max"]))
        if "value" in bounds:
            tolerance = float(bounds.get("tolerance", 0.0))
            if bounds.get("better", "higher") == "higher":
                limit = bounds["value"] - tolerance
                checks.append((f">= {limit:.6g}", value >= limit))
            else:
                limit = bounds["value"] + tolerance
                checks.append((f"<= {limit:.6g}", value <= limit))
        for text, passed in checks:
            results.append(Comparison(metric, value, text, passed))
    return results


def write_baseline(
    metrics: dict, path: str | Path, relative_tolerance: float = 0.05, force: bool = False
) -> None:
    """A baseline from a run's metrics: every numeric image/geometry metric with a tolerance.

    An existing file is refused unless force (ReconError naming it); the write is atomic.
    """
    path = Path(path)
    if path.exists() and not force:
        raise ReconError(
            f"baseline {path}: already exists; pass --force to replace it, or choose another path"
        )
    if path.is_dir():
        raise ReconError(f"baseline {path}: is a folder; expected a file path")
    baseline = {}
    for group in ("image", "geometry"):
        for key, value in metrics.get(group, {}).items():
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                continue
            better = "higher" if any(word in key for word in HIGHER_IS_BETTER) else "lower"
            baseline[f"{group}.{key}"] = {
                "value": float(value),
                "tolerance": abs(float(value)) * relative_tolerance,
                "better": better,
            }
    if not baseline:
        raise ReconError(
            "compare --write: the run's metrics.json has no numeric image/geometry metric"
        )
    atomic_write_text(path, yaml.safe_dump(baseline, sort_keys=False))


def format_table(results: list[Comparison]) -> str:
    lines = [f"{'metric':36} {'value':>12}  {'bound':>14}  result"]
    for item in results:
        value = "missing" if item.value is None else f"{item.value:.6g}"
        lines.append(
            f"{item.metric:36} {value:>12}  {item.bound:>14}  {'ok' if item.passed else 'REGRESSION'}"
        )
    return "\n".join(lines)
