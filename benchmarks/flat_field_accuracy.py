"""How closely the diagnosis' flat-field measurement reads a vignetting's corner and half-way
falloff, with and without sensor noise, on frames data_synth renders; prints JSON.

    recon-bench flat-field-accuracy [--draws 8] [--views 2] [--config configs/bench/diagnose.yaml]

Each draw samples a vignetting (data_synth's plausible strengths for the config's camera),
exposure and white balance, and renders the config's flat-field frames through them, once
noise-free and once with the sensor-noise effect at its default strength (the benchmark's
datasets have no noise; this says what noise costs). The error is relative to the realised
falloff that data_synth records.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import replace
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    import torch

    from data_synth.flat_field import flat_field_capture
    from data_synth.rigs import make_cameras
    from data_synth.withhold import sample_effects
    from recon.config import load_config
    from recon.config.run_config import EffectConfig, RunConfig
    from recon.diagnose.flat_field import measure_flat_field

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--config", default=str(REPO_ROOT / "configs" / "bench" / "diagnose.yaml"))
    arguments = parser.parse_args(argv)
    config = load_config(arguments.config, RunConfig)
    capture = replace(
        config.capture, flat_field=replace(config.capture.flat_field, views=arguments.views)
    )
    camera = make_cameras(capture.cameras, 1, torch.Generator().manual_seed(0))
    results: dict[str, list[dict]] = {"noise_free": [], "noisy": []}
    for draw in range(arguments.draws):
        effects = sample_effects(
            ["vignetting", "exposure", "white_balance"], torch.Generator().manual_seed(draw), camera
        )
        for key, extra in (("noise_free", []), ("noisy", [EffectConfig("noise", {})])):
            frames, realised = flat_field_capture(capture, effects + extra, seed=draw)
            truth = next(item for item in realised if item["name"] == "vignetting")["parameters"]
            measured = measure_flat_field(frames.images)
            record = {"draw": draw}
            for name in ("corner_falloff", "half_radius_falloff"):
                true_value = statistics.fmean(truth[name])
                record[name] = round(true_value, 4)
                record[f"{name}_relative_error"] = abs(measured[name] - true_value) / true_value
            results[key].append(record)
    summary = {
        key: {
            "corner_relative_error_median": statistics.median(
                r["corner_falloff_relative_error"] for r in records
            ),
            "corner_relative_error_max": max(r["corner_falloff_relative_error"] for r in records),
            "half_radius_relative_error_max": max(
                r["half_radius_falloff_relative_error"] for r in records
            ),
            "draws": records,
        }
        for key, records in results.items()
    }
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
