"""Where a diagnosis' time goes, piece by piece, on fitted runs (JSON on stdout).

For each run folder: the seconds of every candidate's probe (the second of two passes, so the
one-time sky visibility is not in them) with its Jacobian column count, and the seconds of the
sky visibility's 64 depth maps (median of three, cache cleared). With --lens-control also the
lens absorption evidence measured two ways: against the control refit (what the diagnosis
does) and against the fit itself (half the refits), with the control's own change over the
fit; the README's "tried and not kept" figures come from

    recon-bench diagnosis-costs B/*/lens_distortion_seed* --lens-control

over the benchmark folder B (recon-bench diagnose).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path


def _interval(pair: tuple[float, tuple[float, float]]) -> dict:
    reduction, (low, high) = pair
    return {"reduction": round(reduction, 4), "interval": [round(low, 4), round(high, 4)]}


def lens_control(paths, config, data) -> dict:
    """The lens refit against the control refit and against the fit (bootstrap over views)."""
    import torch

    from recon.diagnose.absorption import heldout_errors
    from recon.diagnose.refit import RefitSettings, refit_with
    from recon.diagnose.which import bootstrap_reduction, heldout_modules
    from recon.stages.diagnose import diagnosis_inputs

    settings = config.diagnose
    inputs = diagnosis_inputs(paths, config, torch.device("cpu"))
    fit_errors = heldout_errors(data, [], settings)[0]
    errors = {}
    refit = RefitSettings(steps=settings.geometry_steps, resolution=settings.geometry_resolution)
    for names in ([], ["lens_distortion"]):
        refitted, fitted = refit_with(
            names,
            inputs.training,
            inputs.model,
            config,
            torch.device("cpu"),
            paths.diagnosis_refit,
            refit,
        )
        modules = heldout_modules(names, fitted.modules, data.view_count, "cpu")
        refitted = refitted.to("cpu")
        refitted = replace(data, mesh=refitted.mesh, lighting=refitted.lighting, model=refitted)
        errors[bool(names)] = heldout_errors(refitted, modules, settings)[0]
    samples = settings.bootstrap_samples
    return {
        "against_control": _interval(bootstrap_reduction(errors[False], errors[True], samples)),
        "against_fit": _interval(bootstrap_reduction(fit_errors, errors[True], samples)),
        "control_against_fit": _interval(bootstrap_reduction(fit_errors, errors[False], samples)),
    }


def main(argv: list[str] | None = None) -> int:
    import torch

    from recon.config import load_config
    from recon.config.run_config import RunConfig
    from recon.diagnose.gauss_newton import _columns
    from recon.diagnose.which import EffectProbe, probe_candidate, probe_effect
    from recon.effects import light_transport
    from recon.effects.registry import MODEL_EFFECTS
    from recon.io.run_folder import open_run_folder
    from recon.stages.diagnose import load_diagnosis_data

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", help="fitted run folders")
    parser.add_argument("--lens-control", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    arguments = parser.parse_args(argv)
    torch.set_num_threads(arguments.threads)
    results = []
    for run in arguments.runs:
        paths = open_run_folder(Path(run))
        config = load_config(paths.resolved_config, RunConfig)
        data = load_diagnosis_data(paths, "test", config, torch.device("cpu"))
        probe = EffectProbe(data, config.diagnose)
        names = sorted(MODEL_EFFECTS)
        probes = {}
        for _ in range(2):  # the second pass is kept (the first pays the one-time work)
            for name in names:
                started = time.perf_counter()
                result = probe_candidate(name, probe)
                columns = len(
                    _columns([probe_effect(name, data.view_count, "cpu")], data.view_count)
                )
                probes[name] = {
                    "seconds": round(time.perf_counter() - started, 3),
                    "columns": columns,
                    "heldout_reduction": round(result.evidence_of("probe").details["reduction"], 4),
                }
        sky = []
        for _ in range(3):
            light_transport._SKY_CACHE.clear()
            started = time.perf_counter()
            light_transport.sky_visibility(data.mesh.verts, data.mesh.faces)
            sky.append(time.perf_counter() - started)
        record = {
            "run": str(run),
            "probes": probes,
            "probes_seconds": round(sum(item["seconds"] for item in probes.values()), 3),
            "sky_visibility_seconds": round(statistics.median(sky), 3),
        }
        if arguments.lens_control:
            record["lens_control"] = lens_control(paths, config, data)
        results.append(record)
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
