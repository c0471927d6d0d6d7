"""Withheld mode: pick effects at random (seeded) with random plausible strengths.

What is picked goes only to the truth file named on the command line (--truth-out), never into
the dataset or the run folder's ground_truth/: the diagnosis is checked blind.
"""

from __future__ import annotations

import torch

from data_synth.effects.base import ADDABLE
from data_synth.effects.light_transport import LIGHT_TRANSPORT_EFFECTS
from data_synth.effects.registry import WORLD_EFFECTS
from recon.camera import Cameras
from recon.config.run_config import EffectConfig
from recon.errors import ReconError

# Withheld draws use their own stream, offset from the run seed, so switching --withhold on
# leaves the camera rig and every configured effect exactly as they were.
_WITHHOLD_SEED_OFFSET = 7919


def effect_class(name: str) -> type:
    if name in WORLD_EFFECTS:
        return WORLD_EFFECTS[name]
    if name in LIGHT_TRANSPORT_EFFECTS:
        return LIGHT_TRANSPORT_EFFECTS[name]
    raise ReconError(f"effect {name!r}: not in the catalogue")


def choose_withheld_effects(
    count: int,
    seed: int,
    exclude: list[str] | None = None,
    candidates: tuple[str, ...] = ADDABLE,
    cameras: Cameras | None = None,
) -> list[EffectConfig]:
    """count distinct effects from candidates (minus exclude), each with sampled strengths."""
    available = [name for name in candidates if name not in set(exclude or [])]
    if count > len(available):
        raise ReconError(
            f"--withhold: asked for {count} effects but only {len(available)} are available "
            f"({', '.join(available)})"
        )
    generator = torch.Generator().manual_seed(seed + _WITHHOLD_SEED_OFFSET)
    order = torch.randperm(len(available), generator=generator)[:count].tolist()
    return sample_effects([available[index] for index in sorted(order)], generator, cameras)


def sample_effects(
    names: list[str], generator: torch.Generator, cameras: Cameras | None = None
) -> list[EffectConfig]:
    """The named effects, each with random plausible strengths drawn from generator."""
    chosen = []
    for name in names:
        parameters = effect_class(name).sample_strength(generator, cameras)
        chosen.append(
            EffectConfig(name=name, parameters={k: float(v) for k, v in parameters.items()})
        )
    return chosen
