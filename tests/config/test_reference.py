"""Tests for recon.config.reference: every key documented, docs/config.md current, ranges true."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from recon.config import ConfigError, from_dict
from recon.config.reference import (
    REGENERATE_COMMAND,
    checked_ranges,
    config_keys,
    format_keys,
    reference_markdown,
)
from recon.config.run_config import CameraRigConfig, GeometryStageConfig, RunConfig
from recon.config.schema import setting

REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIG_MD = REPO_ROOT / "docs" / "config.md"


def test_every_config_field_has_a_doc():
    undocumented = [item.key for item in config_keys(RunConfig) if not item.doc]
    assert not undocumented, (
        f"config fields without a doc: {undocumented}; declare them with "
        "setting(default, 'what it does') in recon/config/run_config.py"
    )


def test_docs_config_md_is_current():
    expected = reference_markdown(RunConfig)
    actual = CONFIG_MD.read_text(encoding="utf-8") if CONFIG_MD.exists() else ""
    assert actual == expected, (
        f"{CONFIG_MD} is stale (the schema changed); regenerate it: {REGENERATE_COMMAND}"
    )


def test_reference_lists_every_key_with_type_default_and_allowed_values():
    keys = {item.key: item for item in config_keys(RunConfig)}
    fov = keys["capture.cameras.fov_deg"]
    assert (fov.type, fov.default, fov.allowed) == ("float", "40.0", "in [1.0, 170.0]")
    assert keys["device"].allowed == "'auto', 'cpu', 'cuda'"
    assert keys["scene.lighting.suns"].type == "list[SunConfig]"
    assert keys["scene.lighting.suns[].irradiance"].allowed == ">= 0.0"
    assert keys["capture.effects[].name"].allowed.startswith("'exposure', 'white_balance'")
    assert keys["data"].type == "str | null" and keys["data"].default == "null"
    # Every leaf field of every section appears once, under its dotted path.
    assert len(keys) == len(config_keys(RunConfig))
    markdown = reference_markdown(RunConfig)
    for section in ("## `capture.cameras` (CameraRigConfig)", "## `fit.geometry`"):
        assert section in markdown
    text = format_keys(config_keys(RunConfig))
    assert "capture.cameras.fov_deg  float = 40.0  (in [1.0, 170.0])" in text


def test_ranges_are_read_from_the_validation_including_loops():
    geometry = checked_ranges(GeometryStageConfig)
    # The learning rates are checked in a loop over their names.
    assert geometry["albedo_learning_rate"] == ">= 0.0"
    assert geometry["edge_length_end"] == "> 0.0"
    assert checked_ranges(CameraRigConfig)["distance"] == "> 0.0"


def _scalar_range_cases():
    """(key path, a value just outside the documented range) for scalar numeric keys."""
    cases = []
    for item in config_keys(RunConfig):
        match = re.fullmatch(r"in \[(\S+), (\S+)\]|>= (\S+)|> (\S+)", item.allowed)
        if match is None or item.type not in ("int", "float") or "[]" in item.key:
            continue
        low = float(match[1] or match[3] or match[4])
        step = 1 if item.type == "int" else 1e-3
        below = low - step if match[4] is None else low
        cases.append((item.key, int(below) if item.type == "int" else below))
        if match[2] is not None:
            high = float(match[2])
            above = high + step
            cases.append((item.key, int(above) if item.type == "int" else above))
    return cases


@pytest.mark.parametrize(("key", "value"), _scalar_range_cases())
def test_documented_ranges_are_what_the_loader_rejects(key, value):
    with pytest.raises(ConfigError, match=re.escape(key)):
        from_dict({}, RunConfig, overrides=[f"{key}={value}"])


def test_setting_needs_a_doc_and_keeps_defaults():
    with pytest.raises(TypeError, match="doc"):
        setting(1)

    @dataclasses.dataclass
    class Example:
        count: int = setting(3, "how many")
        names: list[str] = setting(factory=lambda: ["a"], doc="which")

    first, second = Example(), Example()
    assert (first.count, first.names) == (3, ["a"])
    assert first.names is not second.names  # the factory builds a fresh list per instance
    built = from_dict({"count": 5}, Example)
    assert (built.count, built.names) == (5, ["a"])
