"""The run folder layout, defined once. Stages talk to each other only through these files.

Every path inside a run folder is a `RunPaths` property: no other module joins a file name to
a run folder (tests/test_architecture.py holds the rule; only recon/stages/, the pipeline and
the CLI use RunPaths). What the dataset holds is asked of its `DatasetLayout`.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from recon.errors import ReconError
from recon.io.atomic import atomic_write_text
from recon.io.dataset_layout import DatasetLayout

# Written when recon creates a run folder: --force replaces only folders that hold it.
RUN_MARKER = ".recon-run"


@dataclass(frozen=True)
class RunPaths:
    """Paths inside one run folder."""

    root: Path
    # A dataset outside the run folder (config key 'data'); None = the run's own dataset/.
    external_dataset: Path | None = None

    @property
    def marker(self) -> Path:
        """Written at creation: the folder is recon's own and --force may replace it."""
        return self.root / RUN_MARKER

    @property
    def stage_overrides(self) -> Path:
        """One JSON record per later-stage run with --set overrides (the fit's record stays)."""
        return self.root / "stage_overrides.jsonl"

    @property
    def synth_progress(self) -> Path:
        """The synth stage's progress (finished splits, random states) while it runs."""
        return self.root / "synth_progress.pt"

    @property
    def diagnosis(self) -> Path:
        return self.root / "diagnosis.json"

    @property
    def diagnosis_folder(self) -> Path:
        """The diagnosis's figures (diagnosis.json links them relative to the root)."""
        return self.root / "diagnosis"

    @property
    def diagnosis_refit(self) -> Path:
        """Scratch space of the diagnosis's refits (their checkpoints and history)."""
        return self.diagnosis_folder / "refit"

    @property
    def resolved_config(self) -> Path:
        return self.root / "config.resolved.yaml"

    @property
    def environment(self) -> Path:
        return self.root / "env.json"

    @property
    def dataset(self) -> Path:
        """The captures (NeRF-synthetic or LLFF layout) that a fit reads."""
        return self.external_dataset if self.external_dataset is not None else self.root / "dataset"

    @property
    def dataset_layout(self) -> DatasetLayout:
        """What the dataset holds (its kind, splits, relight light, flat-field frames)."""
        return DatasetLayout(self.dataset)

    @property
    def ground_truth(self) -> Path:
        """Beside the dataset, never inside it: reference mesh, light, injected effects."""
        return self.root / "ground_truth"

    @property
    def reference_mesh(self) -> Path:
        return self.ground_truth / "reference.obj"

    @property
    def truth_lighting(self) -> Path:
        """The synthesised world's light (data_synth's lighting JSON)."""
        return self.ground_truth / "lighting.json"

    @property
    def truth_environment(self) -> Path:
        """The synthesised world's environment map, when it has one."""
        return self.ground_truth / "environment.exr"

    @property
    def truth_effects(self) -> Path:
        """The effects put into the captures (withheld ones only in --truth-out)."""
        return self.ground_truth / "effects.json"

    @property
    def contact_sheet(self) -> Path:
        return self.root / "captures_contact_sheet.png"

    @property
    def history(self) -> Path:
        """One JSON record per logged optimisation step."""
        return self.root / "history.jsonl"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def geometry_checkpoint(self) -> Path:
        """The fit's geometry stage (remeshing), for --resume."""
        return self.checkpoints / "geometry.pt"

    @property
    def texture_checkpoint(self) -> Path:
        """The fit's texture (or pbr material) stage, for --resume."""
        return self.checkpoints / "texture.pt"

    @property
    def mesh_folder(self) -> Path:
        """The fitted mesh: model.obj (+ .mtl, texture PNG) and model.glb."""
        return self.root / "mesh"

    @property
    def fitted_mesh(self) -> Path:
        return self.mesh_folder / "model.obj"

    @property
    def fitted_glb(self) -> Path:
        """The fitted mesh and its material as one GLB."""
        return self.mesh_folder / "model.glb"

    @property
    def normalized_mesh(self) -> Path:
        """The fitted mesh in the fit's normalised frame (dataset.normalize), beside model.obj."""
        return self.mesh_folder / "normalized" / "model.obj"

    @property
    def normalized_light(self) -> Path:
        """The fitted light in the fit's normalised frame (dataset.normalize), beside light.json."""
        return self.light_folder / "normalized" / "light.json"

    @property
    def light_folder(self) -> Path:
        """light.json (SH coefficients, directional lights) and environment.exr."""
        return self.root / "light"

    @property
    def fitted_light(self) -> Path:
        return self.light_folder / "light.json"

    @property
    def fitted_effects(self) -> Path:
        """The fit's effect modules (fit.effects), when it had any: evaluate renders with them."""
        return self.root / "effects.json"

    @property
    def fitted_environment(self) -> Path:
        """The fitted light as an equirectangular map (the pbr fit's own environment)."""
        return self.light_folder / "environment.exr"

    @property
    def fitted_environment_with_suns(self) -> Path:
        """The pbr fit's environment with its suns (fit.pbr.sun_lights) added as texels, for
        renderers that take one map; written only when the fit has suns."""
        return self.light_folder / "environment_with_suns.exr"

    @property
    def renders(self) -> Path:
        """Held-out views: target, render, error."""
        return self.root / "renders"

    def render_panel(self, split: str, view: str) -> Path:
        """One held-out view's panel (target | render | error); view names may hold '/'."""
        return self.renders / f"{split}_{view.replace('/', '_')}.png"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    def figure(self, name: str) -> Path:
        """A report figure, figures/NAME.png (loss, turntable, material, geometry_error)."""
        return self.figures / f"{name}.png"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    @property
    def report_markdown(self) -> Path:
        return self.root / "report.md"

    @property
    def normalization(self) -> Path:
        """The similarity transform from the dataset's frame to the fit's normalised frame."""
        return self.root / "normalization.json"


def open_run_folder(root: str | Path, external_dataset: str | Path | None = None) -> RunPaths:
    """An existing run folder (for --resume and the single-stage commands)."""
    root = Path(root)
    if not RunPaths(root).resolved_config.exists():
        raise ReconError(
            f"run folder {root}: no config.resolved.yaml here; is this a recon run folder?"
        )
    return RunPaths(root, None if external_dataset is None else Path(external_dataset))


def is_recon_run_folder(root: str | Path) -> bool:
    """Whether recon created this folder (it holds the marker written at creation)."""
    return RunPaths(Path(root)).marker.is_file()


def _refuse_replacing(root: Path, inputs: Sequence[Path]) -> None:
    """Raise ReconError unless `root` (an existing, non-empty folder) may be replaced by --force.

    Only a folder recon created (RUN_MARKER inside) may be replaced, and never the working
    directory or one of its ancestors, nor a folder that holds one of this run's inputs.
    """
    if root.is_symlink():
        raise ReconError(
            f"run folder {root}: is a symbolic link to {root.resolve()}; --force replaces only "
            "a real folder that recon created"
        )
    absolute = root.resolve()
    working = Path.cwd().resolve()
    if absolute == working or absolute in working.parents:
        raise ReconError(
            f"run folder {root}: is the working directory or one of its ancestors; --force "
            "never replaces it (choose another --out)"
        )
    for item in inputs:
        item_absolute = Path(item).resolve()
        if item_absolute == absolute or absolute in item_absolute.parents:
            raise ReconError(
                f"run folder {root}: holds this run's input {item}; --force never replaces a "
                "folder with an input in it (choose another --out)"
            )
    if not is_recon_run_folder(root):
        raise ReconError(
            f"run folder {root}: exists, is not empty and was not created by recon (no "
            f"{RUN_MARKER} marker); --force replaces only recon's own run folders: choose "
            "another --out or remove it yourself"
        )


@dataclass
class NewRunFolder:
    """A run folder being started; the folder it replaces (if any) waits aside until commit().

    paths: the new run's paths. created: recon made the folder (it did not exist before).
    replaced: where the old run (--force) was moved, a hidden sibling; None when nothing was
    replaced.
    """

    paths: RunPaths
    created: bool
    replaced: Path | None = None

    def commit(self) -> None:
        """The new run has started cleanly: delete the old run it replaces."""
        if self.replaced is not None and self.replaced.exists():
            shutil.rmtree(self.replaced)
        self.replaced = None

    def abandon(self) -> None:
        """The new run failed its checks: remove what this start created, put the old run back."""
        root = self.paths.root
        if self.created:
            shutil.rmtree(root, ignore_errors=True)
        elif root.is_dir():
            # An existing empty folder was used: empty it again, keep the folder itself.
            for child in root.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child, ignore_errors=True)
                else:
                    child.unlink(missing_ok=True)
        if self.replaced is not None and self.replaced.exists():
            os.replace(self.replaced, root)
        self.replaced = None


def start_run_folder(
    root: str | Path, force: bool = False, inputs: Sequence[str | Path] = ()
) -> NewRunFolder:
    """Create a new run folder with recon's marker in it.

    A missing or empty folder is used as it is. A non-empty one is refused unless force is given
    and the folder may be replaced (see _refuse_replacing); it is then moved aside, not deleted,
    until the caller commits (the new run started cleanly) or abandons (a check failed).
    inputs: files and folders this run reads (config, dataset, meshes): never inside a replaced
    folder.
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise ReconError(f"run folder {root}: exists and is not a folder")
    replaced = None
    created = not root.exists()
    if root.is_dir() and any(root.iterdir()):
        if not force:
            raise ReconError(
                f"run folder {root}: already exists and is not empty; pass --force to replace "
                "it or --out to choose another folder"
            )
        _refuse_replacing(root, [Path(item) for item in inputs])
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
        replaced = root.parent / f".{root.name}.replaced-{stamp}-{os.getpid()}"
        os.replace(root, replaced)
        created = True
    try:
        root.mkdir(parents=True, exist_ok=True)
        atomic_write_text(
            RunPaths(root).marker,
            json.dumps({"created": datetime.now(timezone.utc).isoformat(timespec="seconds")})
            + "\n",
        )
    except BaseException:
        if created:
            shutil.rmtree(root, ignore_errors=True)
        if replaced is not None:
            os.replace(replaced, root)
        raise
    return NewRunFolder(RunPaths(root), created, replaced)


def prepare_run_folder(
    root: str | Path, force: bool = False, inputs: Sequence[str | Path] = ()
) -> RunPaths:
    """start_run_folder, committed at once (for callers with no checks of their own to run)."""
    started = start_run_folder(root, force=force, inputs=inputs)
    started.commit()
    return started.paths
