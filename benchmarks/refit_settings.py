"""The how-far refit under other settings, for one diagnosed run: how much of the gap it closes
on the held-out views and on the relight split with the vertices' step size and the response
curve's exponent (held at the relight probe's estimate, or free from 1) chosen here rather than
by recon.diagnose.diagnose. Prints one JSON record per setting.

    recon-bench refit-settings RUN EFFECT [--position-rates 0.002,0.01]
        [--response-exponent relight|free]

For example, on the benchmark's fits (recon-bench diagnose):

    recon-bench refit-settings OUT/default/lens_distortion_seed2 lens_distortion
    recon-bench refit-settings OUT/default/vignetting_seed0 vignetting
    recon-bench refit-settings OUT/default/response_curve_seed0 response_curve \\
        --position-rates 0.002 --response-exponent free
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv: list[str] | None = None) -> int:
    import torch

    from recon.config import load_config
    from recon.config.run_config import RunConfig
    from recon.diagnose.decision import redecide
    from recon.diagnose.diagnose import heldout_views, relight_views
    from recon.diagnose.gap import noise_floor
    from recon.diagnose.how_far import RefitBaseline, RefitInputs, measure_refit, relight_exponent
    from recon.diagnose.refit import RefitSettings
    from recon.io.run_folder import open_run_folder
    from recon.stages.diagnose import diagnosis_inputs

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("run", help="a fitted run folder with diagnosis.json (for the exponent)")
    parser.add_argument("effect")
    parser.add_argument("--position-rates", default="0.002,0.01")
    parser.add_argument("--response-exponent", choices=["relight", "free"], default="relight")
    parser.add_argument("--threads", type=int, default=2)
    arguments = parser.parse_args(argv)
    torch.set_num_threads(arguments.threads)
    device = torch.device("cpu")
    paths = open_run_folder(arguments.run)
    config = load_config(paths.resolved_config, RunConfig)
    inputs = diagnosis_inputs(paths, config, device)
    data, _ = heldout_views(inputs)
    floor = (noise_floor(data).get("floor_rmse") or 0.0) ** 2
    _, relight = relight_views(inputs)
    baseline = RefitBaseline.measure(data, floor, relight and relight[0], config.diagnose)
    refit_inputs = RefitInputs(inputs.training, inputs.model, config, device, paths.diagnosis_refit)
    exponent = None
    if arguments.effect == "response_curve" and arguments.response_exponent == "relight":
        stored = redecide(json.loads(paths.diagnosis.read_text()))
        exponent = relight_exponent(stored.candidates)
    for rate in (float(value) for value in arguments.position_rates.split(",")):
        settings = RefitSettings(
            steps=config.diagnose.refit_steps,
            position_learning_rate=rate,
            response_exponent=exponent,
        )
        record, _ = measure_refit([arguments.effect], baseline, refit_inputs, settings)
        keys = ("before", "after", "closed_fraction", "relight_after", "relight_closed_fraction")
        summary = {key: record.get(key) for key in keys}
        fitted = record["parameters"][arguments.effect]
        summary["parameters"] = {key: value for key, value in fitted.items() if key != "table"}
        print(json.dumps({"position_rate": rate, "response_exponent": exponent, **summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
