"""The sweep file: a strict YAML schema read with recon's config loader.

Relative paths (base configs, out) are taken as written, i.e. relative to the current folder,
like every other path in recon's configs.

Example:
    base: configs/quickstart.yaml
    set: [capture.cameras.resolution=[32,32]]
    grid:
      fit.geometry.steps: [2, 4]
    seeds: [0, 1]
    metrics: [fit.loss, metrics.image.psnr]
    out: sweeps/steps
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from recon.config import load_config
from recon.config.checks import ConfigFieldError, check_range
from recon.errors import ConfigError

# A grid value: what a --set value may be (a scalar or a flat list such as a resolution).
Scalar = bool | int | float | str
GridValue = bool | int | float | str | list[Scalar]

# Where a metric is read from in a trial: metrics.json (the evaluate stage), the fit's last
# history record, or the blind diagnosis's score (diagnosis sweeps).
METRIC_SOURCES = ("metrics", "fit", "score")


@dataclass
class DiagnoseSpec:
    """Diagnosis sweeps: each trial is fitted without effects, diagnosed blind, then scored
    against the withheld truth (recon.sweep.scoring)."""

    refit: Literal["none", "top", "greedy"] = "top"
    # Candidate effects of the diagnosis: empty = all registered.
    candidates: list[str] = field(default_factory=list)


@dataclass
class SweepSpec:
    """One sweep: base config(s) x grid x cases x withheld-effect sets x seeds."""

    # One run config, or several (e.g. one per scene): each is one value of the 'base' axis.
    base: str | list[str]
    # The metrics to collect, 'SOURCE.KEY.PATH' with SOURCE one of METRIC_SOURCES.
    metrics: list[str]
    # The sweep's folder: trials/<id>/ (one run folder each), results.*, summary.html.
    out: str
    # --set overrides applied to every trial.
    set: list[str] = field(default_factory=list)
    # Config key -> values; every combination is a trial.
    grid: dict[str, list[GridValue]] | None = None
    # Listed override sets (each a list of --set strings); crossed with the grid.
    cases: list[list[str]] | None = None
    # Effect sets withheld from the synthetic captures ([] = clean); the truth goes beside the
    # trial's run folder, never into it.
    withhold: list[list[str]] | None = None
    # Seeds: each trial runs once per seed (the config's 'seed').
    seeds: list[int] = field(default_factory=lambda: [0])
    # 'diagnosis': diagnose each fitted trial blind and score it against the withheld truth.
    kind: Literal["fit", "diagnosis"] = "fit"
    diagnose: DiagnoseSpec = field(default_factory=DiagnoseSpec)
    # torch threads in each trial (both backends, so results match) and Ray's CPU request.
    cpus_per_trial: int = 1
    # GPUs per trial (Ray's request); 0 runs trials on the CPU, > 0 on CUDA.
    gpus_per_trial: float = 0.0
    # At most this many trials at once on Ray (None: as many as the resources allow).
    max_concurrent: int | None = None

    def __post_init__(self) -> None:
        bases = self.base_configs
        if not bases:
            raise ConfigFieldError("base", "expected a config path or a non-empty list of them")
        if not self.metrics:
            raise ConfigFieldError("metrics", "expected at least one metric, got an empty list")
        for index, name in enumerate(self.metrics):
            source, _, key = name.partition(".")
            if source not in METRIC_SOURCES or not key:
                raise ConfigFieldError(
                    f"metrics[{index}]",
                    f"expected 'SOURCE.KEY' with SOURCE one of {', '.join(METRIC_SOURCES)}, "
                    f"got {name!r}",
                )
            if source == "score" and self.kind != "diagnosis":
                raise ConfigFieldError(
                    f"metrics[{index}]", f"{name!r} needs kind: diagnosis (a scored diagnosis)"
                )
        if self.grid is not None:
            if not self.grid:
                raise ConfigFieldError(
                    "grid", "empty grid: give at least one key with values, or leave grid out"
                )
            for key, values in self.grid.items():
                if not values:
                    raise ConfigFieldError(
                        f"grid.{key}", "empty list of values: give at least one value"
                    )
        for name in ("cases", "withhold"):
            if getattr(self, name) is not None and not getattr(self, name):
                raise ConfigFieldError(
                    name, f"empty list: give at least one entry, or leave {name} out"
                )
        for index, case in enumerate(self.cases or []):
            for position, text in enumerate(case):
                if "=" not in text:
                    raise ConfigFieldError(
                        f"cases[{index}][{position}]", f"expected KEY=VALUE, got {text!r}"
                    )
        for index, text in enumerate(self.set):
            if "=" not in text:
                raise ConfigFieldError(f"set[{index}]", f"expected KEY=VALUE, got {text!r}")
        if not self.seeds:
            raise ConfigFieldError("seeds", "expected at least one seed, got an empty list")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigFieldError("seeds", f"seeds repeat: {self.seeds}")
        if self.kind == "diagnosis" and self.withhold is None:
            raise ConfigFieldError(
                "withhold", "kind: diagnosis needs withhold (effect sets, [] for a clean case)"
            )
        check_range(self.cpus_per_trial, "cpus_per_trial", low=1)
        check_range(self.gpus_per_trial, "gpus_per_trial", low=0.0)
        check_range(self.max_concurrent, "max_concurrent", low=1)

    @property
    def base_configs(self) -> list[str]:
        return [self.base] if isinstance(self.base, str) else list(self.base)

    @property
    def device(self) -> str:
        """Trials run where their resources are: CUDA with GPUs per trial, else the CPU (so a
        local and a Ray sweep of the same file compute the same thing)."""
        return "cuda" if self.gpus_per_trial > 0 else "cpu"


def load_sweep(path: str | Path, overrides: list[str] = ()) -> SweepSpec:
    """Read and check a sweep file; every problem is a ConfigError naming the file and key."""
    spec = load_config(path, SweepSpec, overrides=overrides)
    for base in spec.base_configs:
        if not Path(base).is_file():
            raise ConfigError(f"{path}: base: config file {base} not found")
    return spec
