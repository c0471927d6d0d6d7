"""Add flat-field (or line-target) frames to synthetic run folders made before the config asked
for them.

    python scripts/add_flat_field.py RUN [RUN ...] [--views 2] [--split flat_field|line_target]
        [--truth-dir DIR] [--force]

This is data_synth's (the world's) side, not the diagnosis': for each RUN it reads
RUN/config.resolved.yaml, sets capture.SPLIT.views, and renders the frames through the
run's effects (the config's, plus the withheld ones from the truth file TRUTH_DIR/RUN_NAME.json,
by default RUN/../truth as recon-bench diagnose-blind lays it out) with data_synth.flat_field (or
data_synth.line_target), the function the synth stage calls: the frames draw from their own
seeded streams, so they are the frames a fresh synth with the new config writes
(tests/data_synth/test_flat_field.py checks this). It then writes RUN/dataset/SPLIT, adds the
realised parameters to the truth file (withheld effects) or ground_truth/effects.json (the
others), rewrites config.resolved.yaml, and updates a blind benchmark case's bench_fit.json to
the new config's hash: the fit never reads these splits, so the stored fit is the one the new
config makes.

How the README's benchmark figures with flat fields were made (fits from before the frames):

    python scripts/add_flat_field.py runs/bench_diagnose/*/*_seed*
    recon-bench diagnose --reuse-fits --clean 6
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_flat_field(
    run: Path, views: int, truth_dir: Path | None, force: bool, split: str = "flat_field"
) -> dict:
    """split's frames into run (data_synth.calibration_splits), its withheld effects read from
    TRUTH_DIR/RUN_NAME.json (by default RUN/../truth)."""
    from data_synth.calibration_splits import add_calibration_split

    truth_file = (truth_dir or run.parent / "truth") / f"{run.name}.json"
    return add_calibration_split(run, split, views, truth_file, force)


def main(argv: list[str] | None = None) -> int:
    from recon.errors import ReconError

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--split", choices=("flat_field", "line_target"), default="flat_field")
    parser.add_argument("--truth-dir", type=Path, default=None)
    parser.add_argument("--force", action="store_true", help="replace an existing split")
    arguments = parser.parse_args(argv)
    if arguments.views < 1:
        parser.error(f"--views: expected >= 1, got {arguments.views}")
    try:
        for run in arguments.runs:
            print(
                json.dumps(
                    add_flat_field(
                        run, arguments.views, arguments.truth_dir, arguments.force, arguments.split
                    )
                )
            )
    except ReconError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
