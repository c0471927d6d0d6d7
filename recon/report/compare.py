"""Compare a run's metrics with a baseline: what users put in their CI for regression tests.

Baseline file (YAML or JSON): dotted metric names from metrics.json with bounds, e.g.

    image.psnr: {min: 32.0}
    geometry.chamfer_l1: {max: 0.002}
    geometry.f1@1%: {value: 0.99, tolerance: 0.01, better: higher}

min/max are hard bounds; value + tolerance + better says how far the metric may move in the
bad direction from a recorded value.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from recon.errors import ReconError

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
    value = metrics.get(group, {}).get(key) if key else metrics.get(group)
    return None if value is None else float(value)


def load_baseline(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise ReconError(f"baseline {path}: file not found")
    text = path.read_text()
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as error:
        raise ReconError(
            f"baseline {path}: not valid {path.suffix[1:] or 'YAML'}: {error}"
        ) from error
    if not isinstance(data, dict):
        raise ReconError(f"baseline {path}: expected a mapping of metric -> bounds")
    for metric, bounds in data.items():
        if not isinstance(bounds, dict) or not set(bounds) <= {
            "min",
            "max",
            "value",
            "tolerance",
            "better",
        }:
            raise ReconError(
                f"baseline {path}: {metric}: expected keys among min, max, value, tolerance, "
                f"better; got {bounds!r}"
            )
    return data


def compare(metrics: dict, baseline: dict) -> list[Comparison]:
    results = []
    for metric, bounds in baseline.items():
        value = metric_value(metrics, metric)
        checks = []
        if "min" in bounds:
            checks.append((f">= {bounds['min']}", value is not None and value >= bounds["min"]))
        if "max" in bounds:
            checks.append((f"<= {bounds['max']}", value is not None and value <= bounds["max"]))
        if "value" in bounds:
            tolerance = float(bounds.get("tolerance", 0.0))
            if bounds.get("better", "higher") == "higher":
                limit = bounds["value"] - tolerance
                checks.append((f">= {limit:.6g}", value is not None and value >= limit))
            else:
                limit = bounds["value"] + tolerance
                checks.append((f"<= {limit:.6g}", value is not None and value <= limit))
        for text, passed in checks:
            results.append(Comparison(metric, value, text, passed))
    return results


def write_baseline(metrics: dict, path: str | Path, relative_tolerance: float = 0.05) -> None:
    """A baseline from a run's metrics: every numeric image/geometry metric with a tolerance."""
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
    Path(path).write_text(yaml.safe_dump(baseline, sort_keys=False))


def format_table(results: list[Comparison]) -> str:
    lines = [f"{'metric':36} {'value':>12}  {'bound':>14}  result"]
    for item in results:
        value = "missing" if item.value is None else f"{item.value:.6g}"
        lines.append(
            f"{item.metric:36} {value:>12}  {item.bound:>14}  {'ok' if item.passed else 'REGRESSION'}"
        )
    return "\n".join(lines)
