"""Expand a sweep into trials, each with a stable id (a digest of what makes it different).

The id depends only on the trial's own settings (base config path, overrides, withheld effects,
seed), not on its position, so adding a value to the grid keeps every existing trial's id and
folder: a resumed sweep finds them again.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from dataclasses import asdict, dataclass, field

from recon.errors import ConfigError
from recon.sweep.spec import SweepSpec


@dataclass(frozen=True)
class Trial:
    """One run of the sweep.

    parameters: axis name -> value, for the tables and plots ('base', grid keys, 'case',
    'withhold', 'seed').
    overrides: --set strings applied to the base config, in order (sweep 'set', grid, case,
    then seed).
    withhold: effects withheld from the synthetic captures (None: none asked for; [] clean).
    """

    trial_id: str
    base: str
    overrides: tuple[str, ...]
    seed: int
    parameters: dict = field(hash=False, compare=False)
    withhold: tuple[str, ...] | None = None

    def to_dict(self) -> dict:
        record = asdict(self)
        record["overrides"] = list(self.overrides)
        record["withhold"] = None if self.withhold is None else list(self.withhold)
        return record


def format_value(value) -> str:
    """A grid value as --set text: strings as written, everything else as JSON (valid YAML)."""
    return value if isinstance(value, str) else json.dumps(value)


def trial_id(base: str, overrides: tuple[str, ...], withhold, seed: int) -> str:
    canonical = json.dumps(
        {"base": base, "overrides": list(overrides), "withhold": withhold, "seed": seed},
        sort_keys=True,
    )
    return "trial-" + hashlib.sha1(canonical.encode()).hexdigest()[:10]


def expand(spec: SweepSpec) -> list[Trial]:
    """Every combination of base x grid x cases x withhold x seeds, in file order."""
    grid_keys = list(spec.grid or {})
    grid_points = list(itertools.product(*(spec.grid[key] for key in grid_keys))) or [()]
    cases = spec.cases if spec.cases is not None else [None]
    withheld_sets = spec.withhold if spec.withhold is not None else [None]
    bases = spec.base_configs
    trials = []
    for base, point, case, withhold, seed in itertools.product(
        bases, grid_points, cases, withheld_sets, spec.seeds
    ):
        overrides = list(spec.set)
        overrides += [
            f"{key}={format_value(value)}" for key, value in zip(grid_keys, point, strict=True)
        ]
        overrides += list(case or [])
        overrides.append(f"seed={seed}")
        parameters = {}
        if len(bases) > 1:
            parameters["base"] = base
        parameters.update(dict(zip(grid_keys, point, strict=True)))
        if case is not None:
            parameters["case"] = " ".join(case) or "(none)"
        if withhold is not None:
            parameters["withhold"] = "+".join(withhold) or "none"
        parameters["seed"] = seed
        withheld = None if withhold is None else tuple(withhold)
        trials.append(
            Trial(
                trial_id(base, tuple(overrides), withhold, seed),
                base,
                tuple(overrides),
                seed,
                parameters,
                withheld,
            )
        )
    seen = {}
    for trial in trials:
        if trial.trial_id in seen:
            raise ConfigError(
                f"sweep: two trials are the same run ({trial.parameters} and "
                f"{seen[trial.trial_id].parameters}); remove the repeated value"
            )
        seen[trial.trial_id] = trial
    return trials
