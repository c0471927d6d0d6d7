"""Tests for data_synth.reference: docs/effect_parameters.md matches the world effects."""

from __future__ import annotations

from pathlib import Path

from data_synth.reference import (
    REGENERATE_COMMAND,
    effect_parameters_markdown,
    world_effect_classes,
)
from recon.config.run_config import EFFECT_NAMES

REPO_ROOT = Path(__file__).resolve().parents[2]
PAGE = REPO_ROOT / "docs" / "effect_parameters.md"


def test_docs_effect_parameters_md_is_current():
    actual = PAGE.read_text(encoding="utf-8") if PAGE.exists() else ""
    assert actual == effect_parameters_markdown(), (
        f"{PAGE} is stale (a world effect's PARAMETERS changed); regenerate it: "
        f"{REGENERATE_COMMAND}"
    )


def test_every_catalogue_effect_has_a_section_with_every_parameter():
    assert list(world_effect_classes()) == list(EFFECT_NAMES)
    text = effect_parameters_markdown()
    for name, effect in world_effect_classes().items():
        section = text.split(f"\n## {name}\n", 1)[1].split("\n## ", 1)[0]
        assert effect.PARAMETERS, name
        for key, spec in effect.PARAMETERS.items():
            assert f"| `{key}` | {spec.kind} |" in section
            assert spec.description in section
