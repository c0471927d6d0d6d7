"""Blind diagnosis benchmark at 128² on the default scene and spot (../shared/meshes), several
seeds per effect, clean datasets and pairs; prints one JSON object per scene with top-1 accuracy,
both-found rate, false-positive rate, gap closed and the cost of diagnosis relative to the fit.

    recon-bench diagnose [--scenes default spot] [--seeds 0,1,2] [--out runs/bench_diagnose]

Each scene's folder also gets bench.md and confusion.png (recon-bench diagnose-blind writes them);
with both scenes the pooled cases go to OUT/bench.md, OUT/bench.json and OUT/confusion.png.

How the README's figures were made (clean seeds 103-105 calibrate, 100-102 are scored):

    recon-bench diagnose --fits-only --clean 6           # synthesise and fit
    recon-bench calibrate OUT/*/none_seed10[345]
    # -> the allowances of the config section diagnose.decision (--write a fragment),
    #    before any scored case is diagnosed
    recon-bench diagnose --reuse-fits --clean 6          # diagnose every case
    recon-bench diagnose --reuse-fits --rescore --clean 3  # pooled, 100-102 scored

The fits of the current figures predate the flat-field frames; they were added to every case
with scripts/add_flat_field.py (the fit never reads them) before the --reuse-fits run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
SPOT_OVERRIDES = [
    "scene.shape.procedural=null",
    "scene.shape.mesh_path=../shared/meshes/spot_triangulated.obj",
    "scene.shape.texture_path=../shared/meshes/spot_texture.png",
    "scene.material.albedo=file",
]


def main(argv: list[str] | None = None) -> int:
    import torch

    from benchmarks.diagnose_blind import diagnose_blind, summarise, write_outputs

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["default", "spot"])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--clean", type=int, default=3)
    parser.add_argument("--out", default="runs/bench_diagnose")
    parser.add_argument("--refit", choices=["none", "top", "greedy"], default="top")
    parser.add_argument("--reuse-fits", action="store_true", help="rediagnose finished fits")
    parser.add_argument("--fits-only", action="store_true", help="synthesise and fit, then stop")
    parser.add_argument(
        "--rescore", action="store_true", help="re-decide stored diagnoses (with --reuse-fits)"
    )
    arguments = parser.parse_args(argv)
    results = {}
    for scene in arguments.scenes:
        if scene == "spot" and not (REPO_ROOT.parent / "shared" / "meshes").is_dir():
            results[scene] = {"skipped": "../shared/meshes is absent"}
            continue
        results[scene] = diagnose_blind(
            REPO_ROOT / "configs" / "bench" / "diagnose.yaml",
            Path(arguments.out) / scene,
            torch.device("cpu"),
            seeds=[int(seed) for seed in arguments.seeds.split(",")],
            clean=arguments.clean,
            overrides=SPOT_OVERRIDES if scene == "spot" else [],
            refit=arguments.refit,
            reuse_fits=arguments.reuse_fits,
            fits_only=arguments.fits_only,
            rescore=arguments.rescore,
        )
    scored = [
        Path(arguments.out) / scene / "bench.json"
        for scene in arguments.scenes
        if "skipped" not in results[scene]
    ]
    if len(scored) > 1:
        # Every scored case of every scene together (each scene's confusion.png stays its own).
        records = [case for path in scored for case in json.loads(path.read_text())["cases"]]
        results["pooled"] = summarise(records)
        write_outputs(records, Path(arguments.out))
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
