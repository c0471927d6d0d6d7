"""The diagnosis' cost against the fit's, measured back to back in one process.

For each benchmark case folder (a run with synthesised data, e.g. from
``recon-bench diagnose --fits-only``): copy its config and dataset to OUT, run the fit
stage, then the diagnose stage with the top-effect refit, and print JSON with the three times and
their ratios. Measuring both in the same process, one after the other, keeps the ratio free of
the machine's drift between a benchmark's fit and its diagnosis.

    recon-bench time-diagnosis RUN [RUN ...] [--out /tmp/time_diagnosis] [--threads 2]

The README's table: one case of every kind from a benchmark folder B (nothing else running):

    recon-bench time-diagnosis B/default/exposure_seed1 B/default/lens_distortion_seed0 \
        B/default/vignetting_seed1 B/spot/none_seed100 B/default/white_balance_seed1 \
        B/default/pose_error_seed1 B/default/motion_blur_seed2 B/spot/defocus_blur_seed0 \
        B/spot/response_curve_seed2 B/default/shadows_seed1 B/spot/specular_seed0 \
        B/default/interreflection_seed0
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    import torch

    from recon.config import load_config
    from recon.config.run_config import RunConfig
    from recon.io.run_folder import RunPaths, open_run_folder
    from recon.pipeline import run_stages
    from recon.stages.diagnose import run_diagnosis

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", help="run folders with a synthesised dataset")
    parser.add_argument("--out", default="/tmp/time_diagnosis")
    parser.add_argument("--threads", type=int, default=2)
    arguments = parser.parse_args(argv)
    torch.set_num_threads(arguments.threads)
    results = []
    for run in arguments.runs:
        source = Path(run)
        target = Path(arguments.out) / source.parent.name / source.name
        if target.exists():
            shutil.rmtree(target)
        target.mkdir(parents=True)
        source_paths, target_paths = RunPaths(source), RunPaths(target)
        shutil.copytree(source_paths.dataset, target_paths.dataset)
        shutil.copy2(source_paths.resolved_config, target_paths.resolved_config)
        if source_paths.environment.exists():
            shutil.copy2(source_paths.environment, target_paths.environment)
        if source_paths.ground_truth.is_dir():
            shutil.copytree(source_paths.ground_truth, target_paths.ground_truth)
        paths = open_run_folder(target)
        config = load_config(paths.resolved_config, RunConfig)
        started = time.perf_counter()
        run_stages(config, paths, torch.device("cpu"), ["fit"], None)
        fit_seconds = time.perf_counter() - started
        started = time.perf_counter()
        diagnosis = run_diagnosis(paths, config, torch.device("cpu"), refit="top")
        wall_seconds = time.perf_counter() - started
        timings = diagnosis.timings
        results.append(
            {
                "run": str(source),
                "fit_seconds": round(fit_seconds, 1),
                "diagnose_seconds": timings["diagnose_seconds"],
                "refit_seconds": timings.get("refit_seconds"),
                "diagnosis_share_of_fit": round(timings["diagnose_seconds"] / fit_seconds, 3),
                "refit_share_of_fit": round(timings.get("refit_seconds", 0.0) / fit_seconds, 3),
                # The rest of the stage: the geometry errors against the reference mesh
                # (synthetic data only), the figures and diagnosis.json.
                "outside_seconds": round(
                    wall_seconds - timings["diagnose_seconds"] - timings.get("refit_seconds", 0.0),
                    2,
                ),
                "verdict": diagnosis.verdict,
            }
        )
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
