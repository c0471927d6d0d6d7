"""The stages: the only modules that read or write a run folder (recon.io.run_folder.RunPaths).

A stage is a function `stage(config, paths, device, **options) -> dict` (a summary). recon's own
stages are the table below, imported only when one runs (so `recon --help` stays fast). Stages
of other packages register in the ``recon.stages`` entry-point group (pyproject.toml): the synth
stage belongs to data_synth, which recon must not import, so it is found by name.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module
from importlib.metadata import entry_points

from recon.errors import ReconError

Stage = Callable[..., dict]

# name -> "module:function".
STAGES = {
    "fit": "recon.stages.fit:fit_stage",
    "evaluate": "recon.stages.evaluate:evaluate_stage",
    "report": "recon.stages.report:report_stage",
    "diagnose": "recon.stages.diagnose:diagnose_stage",
}
ENTRY_POINT_GROUP = "recon.stages"


def find_stage(name: str) -> Stage:
    """recon's own stage of that name, else the one registered under it in the entry-point
    group; ReconError naming the known stages when there is none."""
    if name in STAGES:
        module, function = STAGES[name].split(":")
        return getattr(import_module(module), function)
    found = {entry.name: entry for entry in entry_points(group=ENTRY_POINT_GROUP)}
    if name not in found:
        known = sorted(set(STAGES) | set(found))
        raise ReconError(
            f"stage {name!r}: not installed (known: {', '.join(known)}); the synth stage "
            "comes with data_synth: install the project with 'pip install -e .'"
        )
    return found[name].load()
