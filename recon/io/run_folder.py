"""The run folder layout, defined once. Stages talk to each other only through these files."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from recon.errors import ReconError


@dataclass(frozen=True)
class RunPaths:
    """Paths inside one run folder."""

    root: Path
    # A dataset outside the run folder (config key 'data'); None = the run's own dataset/.
    external_dataset: Path | None = None

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
    def ground_truth(self) -> Path:
        """Beside the dataset, never inside it: reference mesh, light, injected effects."""
        return self.root / "ground_truth"

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
    def mesh_folder(self) -> Path:
        """The fitted mesh: model.obj (+ .mtl, texture PNG) and model.glb."""
        return self.root / "mesh"

    @property
    def fitted_mesh(self) -> Path:
        return self.mesh_folder / "model.obj"

    @property
    def light_folder(self) -> Path:
        """light.json (SH coefficients, directional lights) and environment.exr."""
        return self.root / "light"

    @property
    def fitted_light(self) -> Path:
        return self.light_folder / "light.json"

    @property
    def renders(self) -> Path:
        """Held-out views: target, render, error."""
        return self.root / "renders"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

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

    @property
    def reference_mesh(self) -> Path:
        return self.ground_truth / "reference.obj"


def open_run_folder(root: str | Path, external_dataset: str | Path | None = None) -> RunPaths:
    """An existing run folder (for --resume and the single-stage commands)."""
    root = Path(root)
    if not (root / "config.resolved.yaml").exists():
        raise ReconError(
            f"run folder {root}: no config.resolved.yaml here; is this a recon run folder?"
        )
    return RunPaths(root, None if external_dataset is None else Path(external_dataset))


def prepare_run_folder(root: str | Path, force: bool = False) -> RunPaths:
    """Create the run folder; refuse to reuse a non-empty one unless force (then it is emptied).

    Raises ReconError naming the folder, so a previous run is never overwritten by accident.
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise ReconError(f"run folder {root}: exists and is not a folder")
    if root.exists() and any(root.iterdir()):
        if not force:
            raise ReconError(
                f"run folder {root}: already exists and is not empty; pass --force to replace "
                "it or --out to choose another folder"
            )
        shutil.rmtree(root)
    root.mkdir(parents=True, exist_ok=True)
    return RunPaths(root)
