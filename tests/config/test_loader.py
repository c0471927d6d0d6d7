"""Tests for recon.config: strict loading, error messages, overrides, dump and hash."""

# String annotations on purpose: the loader must resolve them (schemas in the project use them).
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import pytest

from recon.config import (
    ConfigError,
    ConfigFieldError,
    check_range,
    config_hash,
    dump_resolved,
    from_dict,
    load_config,
    to_dict,
)

# --------------------------------------------------------------------------- example schema


@dataclass
class Geometry:
    """Nested two levels down, with range validation."""

    learning_rate: float = 0.01
    steps: int = 100

    def __post_init__(self) -> None:
        check_range(self.learning_rate, "learning_rate", low=0.0, low_inclusive=False)
        check_range(self.steps, "steps", low=1)


@dataclass
class Fit:
    geometry: Geometry = field(default_factory=Geometry)
    steps: int = 500
    weights: dict[str, float] = field(default_factory=lambda: {"rgb": 1.0})


@dataclass
class Light:
    kind: Literal["point", "sun"]
    power: float = 1.0
    position: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass
class Cameras:
    count: int = 8
    fov_deg: list[float] = field(default_factory=lambda: [45.0])
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        check_range(self.fov_deg, "fov_deg", 1.0, 179.0)


@dataclass
class Scene:
    shape: Literal["sphere", "torus", "cube"]
    # typing.Optional (a typing.Union) and X | None (a types.UnionType) are both supported.
    seed: Optional[int] = None  # noqa: UP045
    scale: float | None = 1.0


@dataclass
class Experiment:
    name: str
    scene: Scene
    fit: Fit = field(default_factory=Fit)
    cameras: Cameras = field(default_factory=Cameras)
    lights: list[Light] = field(default_factory=list)
    resolution: tuple[int, int] = (64, 64)
    verbose: bool = False
    tag: int | str = 0


@dataclass
class AllDefaults:
    steps: int = 3
    rate: float = 0.5


MINIMAL = "name: demo\nscene:\n  shape: sphere\n"

FULL = """\
name: full
scene:
  shape: torus
  seed: 7
  scale: 2
fit:
  geometry:
    learning_rate: 1e-3
    steps: 20
  steps: 50
  weights:
    rgb: 1
    normal: 0.25
cameras:
  count: 4
  fov_deg: [40, 50.5]
  names: [front, back]
lights:
  - kind: point
    power: 3
    position: [1, 2, 3]
  - kind: sun
resolution: [32, 16]
verbose: true
tag: run-a
"""


def write(tmp_path: Path, text: str, name: str = "experiment.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def load_error(tmp_path: Path, text: str, overrides: list[str] = ()) -> str:
    """The message of the ConfigError that loading text raises."""
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as caught:
        load_config(path, Experiment, overrides)
    return str(caught.value)


# --------------------------------------------------------------------------- valid loads


def test_full_config_loads_with_schema_types(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, FULL), Experiment)
    assert config.name == "full"
    assert config.scene == Scene(shape="torus", seed=7, scale=2.0)
    assert isinstance(config.scene.scale, float)  # int accepted for float, stored as float
    assert config.fit.geometry == Geometry(learning_rate=0.001, steps=20)
    assert config.fit.steps == 50
    assert config.fit.weights == {"rgb": 1.0, "normal": 0.25}
    assert config.cameras == Cameras(count=4, fov_deg=[40.0, 50.5], names=["front", "back"])
    assert config.lights == [
        Light(kind="point", power=3.0, position=(1.0, 2.0, 3.0)),
        Light(kind="sun"),
    ]
    assert isinstance(config.lights[0].position, tuple)
    assert config.resolution == (32, 16)
    assert config.verbose is True
    assert config.tag == "run-a"


def test_defaults_fill_missing_keys(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL), Experiment)
    assert config == Experiment(name="demo", scene=Scene(shape="sphere"))
    assert config.fit.geometry.learning_rate == 0.01
    assert config.lights == []
    assert config.scene.seed is None


def test_default_factories_are_not_shared(tmp_path: Path) -> None:
    first = load_config(write(tmp_path, MINIMAL), Experiment)
    second = load_config(write(tmp_path, MINIMAL), Experiment)
    first.fit.weights["extra"] = 2.0
    assert "extra" not in second.fit.weights


def test_empty_file_means_all_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, ""), AllDefaults) == AllDefaults()
    assert load_config(write(tmp_path, "# only a comment\n"), AllDefaults) == AllDefaults()


def test_null_allowed_for_optional(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL + "  seed: null\n  scale: ~\n"), Experiment)
    assert config.scene.seed is None
    assert config.scene.scale is None


def test_union_tries_each_member(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, MINIMAL + "tag: 5\n"), Experiment).tag == 5
    message = load_error(tmp_path, MINIMAL + "tag: [1]\n")
    assert "tag: expected int or str, got list [1]" in message


def test_from_dict_names_source_and_does_not_modify_data() -> None:
    data = {"name": "x", "scene": {"shape": "cube"}}
    config = from_dict(data, Experiment, source="inline", overrides=["scene.shape=torus"])
    assert config.scene.shape == "torus"
    assert data == {"name": "x", "scene": {"shape": "cube"}}
    with pytest.raises(ConfigError, match=r"^inline: scene\.shape: expected one of"):
        from_dict({"name": "x", "scene": {"shape": "cone"}}, Experiment, source="inline")


def test_exponent_without_dot_is_a_float(tmp_path: Path) -> None:
    # YAML 1.1 would read 1e-3 as a string; the loader reads it as a number.
    text = MINIMAL + "fit:\n  geometry:\n    learning_rate: 5e-4\n"
    assert load_config(write(tmp_path, text), Experiment).fit.geometry.learning_rate == 5e-4


# --------------------------------------------------------------------------- unknown keys


def test_unknown_nested_key_names_file_line_path_and_suggestion(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit:\n  geometry:\n    lr: 0.1\n")
    assert "experiment.yaml:6" in message
    assert "fit.geometry.lr" in message
    assert "did you mean 'learning_rate'?" in message
    assert "learning_rate, steps" in message  # the valid keys are listed


def test_unknown_key_typo_suggestion(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "camras:\n  count: 2\n")
    assert "experiment.yaml:4: camras: unknown key (did you mean 'cameras'?)" in message


def test_unknown_key_inside_list_item(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "lights:\n  - kind: sun\n    powr: 2\n")
    assert "experiment.yaml:6: lights[0].powr: unknown key (did you mean 'power'?)" in message


def test_unknown_key_without_close_match_lists_valid_keys(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "zzz: 1\n")
    assert "zzz: unknown key; valid keys here: name, scene, fit" in message
    assert "did you mean" not in message


def test_non_string_key_rejected(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "1: x\n")
    assert "experiment.yaml" in message
    assert "keys must be strings, got int 1" in message


# --------------------------------------------------------------------------- wrong types


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ("fit:\n  steps: ten\n", "fit.steps: expected int, got str 'ten'"),
        ("fit:\n  steps: '100'\n", "(write the number without quotes)"),
        ("fit:\n  steps: true\n", "fit.steps: expected int, got bool True"),
        ("fit:\n  steps: 2.5\n", "fit.steps: expected int, got float 2.5"),
        ("fit:\n  steps: 2*50\n", "fit.steps: expected int, got str '2*50'"),  # no arithmetic
        ("verbose: 1\n", "verbose: expected bool, got int 1"),
    ],
)
def test_wrong_scalar_type_names_key_expected_and_actual(
    tmp_path: Path, extra: str, expected: str
) -> None:
    message = load_error(tmp_path, MINIMAL + extra)
    assert "experiment.yaml:" in message
    assert expected in message


def test_bool_rejected_for_float(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "  scale: false\n")
    assert "scene.scale: expected float, got bool False" in message


def test_string_rejected_for_str_list_item_types(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "cameras:\n  fov_deg: [40, wide]\n")
    assert "experiment.yaml:5: cameras.fov_deg[1]: expected float, got str 'wide'" in message


def test_number_rejected_for_str(tmp_path: Path) -> None:
    message = load_error(tmp_path, "name: 12\nscene:\n  shape: cube\n")
    assert "experiment.yaml:1: name: expected str, got int 12" in message


def test_tuple_length_checked(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "resolution: [1, 2, 3]\n")
    assert "resolution: expected a list of 2 items [int, int], got a list of 3 items" in message


def test_section_must_be_a_mapping(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit: 3\n")
    assert "experiment.yaml:4: fit: expected a mapping (Fit), got int 3" in message


def test_list_must_be_a_list(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "lights: sun\n")
    assert "lights: expected a list of Light mappings, got str 'sun'" in message


def test_list_item_must_be_a_mapping(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "lights: [sun]\n")
    assert "experiment.yaml:4: lights[0]: expected a mapping (Light), got str 'sun'" in message


def test_dict_values_checked(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit:\n  weights:\n    rgb: high\n")
    assert "fit.weights.rgb: expected float, got str 'high'" in message


def test_literal_mismatch_lists_allowed_values(tmp_path: Path) -> None:
    message = load_error(tmp_path, "name: demo\nscene:\n  shape: tours\n")
    assert "experiment.yaml:3: scene.shape" in message
    assert "expected one of 'sphere', 'torus', 'cube', got str 'tours'" in message
    assert "did you mean 'torus'?" in message


def test_null_rejected_for_required_type(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit:\n  steps: null\n")
    assert "fit.steps: expected int, got null" in message


# --------------------------------------------------------------------------- missing keys, files


def test_missing_required_key(tmp_path: Path) -> None:
    message = load_error(tmp_path, "scene:\n  shape: cube\n")
    assert "experiment.yaml: name: missing required key" in message


def test_missing_required_keys_all_named(tmp_path: Path) -> None:
    message = load_error(tmp_path, "fit: {}\n")
    assert "experiment.yaml: name: missing required key (also missing: scene)" in message


def test_missing_required_nested_key_names_section_line(tmp_path: Path) -> None:
    message = load_error(tmp_path, "name: demo\nscene: {}\n")
    assert "experiment.yaml:2: scene.shape: missing required key" in message


def test_missing_required_key_in_list_item(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "lights:\n  - power: 2\n")
    assert "experiment.yaml:5: lights[0].kind: missing required key" in message


def test_missing_file_names_path(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(ConfigError, match="nowhere.yaml: config file not found"):
        load_config(path, Experiment)


def test_folder_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(tmp_path, Experiment)


def test_yaml_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    message = load_error(tmp_path, "name: demo\nscene:\n  shape: [sphere\nfit: {}\n")
    assert "experiment.yaml:4:" in message
    assert "invalid YAML" in message


def test_bad_indentation_names_line(tmp_path: Path) -> None:
    message = load_error(tmp_path, "name: demo\nscene:\n  shape: cube\n bad: 1\n")
    assert "experiment.yaml:4:" in message


def test_duplicate_key_rejected_with_both_lines(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "name: again\n")
    assert "experiment.yaml:4:" in message
    assert "duplicate key 'name' (first set on line 1)" in message


@pytest.mark.parametrize("text", ["- a\n- b\n", "just text\n", "42\n"])
def test_top_level_must_be_a_mapping(tmp_path: Path, text: str) -> None:
    message = load_error(tmp_path, text)
    assert "experiment.yaml: the top level must be a mapping" in message


def test_non_dataclass_schema_is_a_type_error(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="dataclass"):
        load_config(write(tmp_path, MINIMAL), dict)


@dataclass
class Unsupported:
    values: set[int] = field(default_factory=set)


def test_unsupported_hint_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="unsupported type hint"):
        from_dict({"values": [1]}, Unsupported)


# --------------------------------------------------------------------------- __post_init__ checks


def test_post_init_range_error_names_full_key_path(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit:\n  geometry:\n    learning_rate: -0.5\n")
    assert "experiment.yaml:6: fit.geometry.learning_rate: must be > 0.0, got -0.5" in message


def test_post_init_sequence_range_names_index(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "cameras:\n  fov_deg: [45, 190]\n")
    assert "experiment.yaml:5: cameras.fov_deg[1]: must be in [1.0, 179.0], got 190.0" in message


def test_post_init_error_from_override_names_override(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["fit.geometry.steps=0"])
    assert "experiment.yaml (--set fit.geometry.steps=0): fit.geometry.steps" in message
    assert "must be >= 1, got 0" in message


def test_direct_construction_still_raises_config_error() -> None:
    with pytest.raises(ConfigError, match="learning_rate: must be > 0.0, got 0.0"):
        Geometry(learning_rate=0.0)


@dataclass
class PlainCheck:
    low: float = 0.0
    high: float = 1.0

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError(f"low ({self.low}) must not exceed high ({self.high})")


def test_plain_value_error_in_post_init_gets_section_path() -> None:
    data = {"low": 2.0, "high": 1.0}
    with pytest.raises(ConfigError, match=r"^src: \(top level\): low \(2.0\) must not exceed"):
        from_dict(data, PlainCheck, source="src")


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        ({"value": 2.0, "low": 0, "high": 1}, "x: must be in [0, 1], got 2.0"),
        (
            {"value": 0, "low": 0, "high": 1, "low_inclusive": False, "high_inclusive": False},
            "x: must be in (0, 1), got 0",
        ),
        ({"value": -1, "low": 0}, "x: must be >= 0, got -1"),
        ({"value": 5, "high": 5, "high_inclusive": False}, "x: must be < 5, got 5"),
        ({"value": math.nan, "low": 0}, "x: must be >= 0, got nan"),
        ({"value": (0.5, 3.0), "low": 0, "high": 1}, "x[1]: must be in [0, 1], got 3.0"),
    ],
)
def test_check_range_messages(arguments: dict, expected: str) -> None:
    with pytest.raises(ConfigFieldError) as caught:
        check_range(key="x", **arguments)
    assert str(caught.value) == expected


def test_check_range_accepts_bounds_and_none() -> None:
    check_range(0.0, "x", 0.0, 1.0)
    check_range(1.0, "x", 0.0, 1.0)
    check_range(None, "x", 0.0, 1.0)
    check_range([0.2, 0.4], "x", 0.0, 1.0)


# --------------------------------------------------------------------------- overrides


def test_overrides_scalar_literal_list_and_nested(tmp_path: Path) -> None:
    config = load_config(
        write(tmp_path, FULL),
        Experiment,
        [
            "fit.steps=100",
            "scene.shape=cube",
            "cameras.fov_deg=[40,50]",
            "fit.geometry.learning_rate=2e-2",
            "cameras.names=[left, right]",
            "verbose=false",
            "scene.seed=",  # empty value is null
        ],
    )
    assert config.fit.steps == 100
    assert config.scene.shape == "cube"
    assert config.cameras.fov_deg == [40.0, 50.0]
    assert config.fit.geometry.learning_rate == 0.02
    assert config.cameras.names == ["left", "right"]
    assert config.verbose is False
    assert config.scene.seed is None


def test_override_creates_sections_the_file_left_to_defaults(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL), Experiment, ["fit.geometry.steps=7"])
    assert config.fit.geometry == Geometry(steps=7)
    assert config.fit.steps == 500


def test_override_list_items_by_index(tmp_path: Path) -> None:
    config = load_config(
        write(tmp_path, FULL), Experiment, ["lights[0].power=9", "lights.1.kind=point"]
    )
    assert config.lights[0].power == 9.0
    assert config.lights[1].kind == "point"


def test_override_whole_list_of_sections(tmp_path: Path) -> None:
    config = load_config(
        write(tmp_path, MINIMAL), Experiment, ["lights=[{kind: sun, power: 2}, {kind: point}]"]
    )
    assert config.lights == [Light(kind="sun", power=2.0), Light(kind="point")]


def test_override_dict_entry_adds_key(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, FULL), Experiment, ["fit.weights.mask=0.5"])
    assert config.fit.weights == {"rgb": 1.0, "normal": 0.25, "mask": 0.5}


def test_later_override_wins(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL), Experiment, ["fit.steps=1", "fit.steps=2"])
    assert config.fit.steps == 2


def test_override_unknown_path_suggests(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["fit.geometry.lr=0.1"])
    assert "experiment.yaml (--set fit.geometry.lr=0.1): fit.geometry.lr: unknown key" in message
    assert "did you mean 'learning_rate'?" in message


def test_override_unknown_top_level_suggests(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["scen.shape=cube"])
    assert "scen: unknown key (did you mean 'scene'?)" in message


def test_override_wrong_type_names_override_and_expected(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["fit.steps=many"])
    assert "experiment.yaml (--set fit.steps=many): fit.steps: expected int, got str 'many'" in (
        message
    )


def test_override_literal_mismatch(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["scene.shape=cone"])
    assert "--set scene.shape=cone" in message
    assert "expected one of 'sphere', 'torus', 'cube', got str 'cone'" in message


def test_malformed_override_without_equals(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["fit.steps"])
    assert "--set 'fit.steps': expected KEY=VALUE" in message


@pytest.mark.parametrize("text", ["=3", "fit..steps=3", "[0].power=1", "fit.=3"])
def test_malformed_override_key(tmp_path: Path, text: str) -> None:
    message = load_error(tmp_path, MINIMAL, [text])
    assert "malformed key" in message


def test_override_value_with_bad_yaml(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["cameras.fov_deg=[40, 50"])
    assert "cannot read value '[40, 50' as YAML" in message


@pytest.mark.parametrize("text", [MINIMAL, FULL])  # fit.steps left to its default, or set
def test_override_through_a_scalar(tmp_path: Path, text: str) -> None:
    message = load_error(tmp_path, text, ["fit.steps.inner=1"])
    assert "fit.steps: is int; it has no key 'inner'" in message


def test_override_through_a_wrong_file_value(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "fit: 3\n", ["fit.steps=1"])
    assert "(--set fit.steps=1): fit: is int 3 in the config, not a mapping" in message


def test_override_list_index_out_of_range(tmp_path: Path) -> None:
    message = load_error(tmp_path, FULL, ["lights[5].power=1"])
    assert "lights[5]: index out of range: the list has 2 items" in message


def test_override_list_index_into_defaults(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["lights[0].power=1"])
    assert "lights: is not set in the config" in message


def test_overrides_must_be_a_list() -> None:
    with pytest.raises(TypeError, match="list of 'key=value' strings"):
        from_dict({"name": "x", "scene": {"shape": "cube"}}, Experiment, overrides="fit.steps=1")


def test_override_of_yaml_alias_changes_only_its_target(tmp_path: Path) -> None:
    text = MINIMAL + "lights:\n  - &first {kind: sun, power: 2}\n  - *first\n"
    config = load_config(write(tmp_path, text), Experiment, ["lights[1].power=5"])
    assert [light.power for light in config.lights] == [2.0, 5.0]


def test_recursive_alias_rejected(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL + "cameras: &loop\n  names: [*loop]\n")
    assert "experiment.yaml: recursive YAML alias" in message


def test_earlier_override_origin_dropped_when_section_replaced(tmp_path: Path) -> None:
    message = load_error(tmp_path, MINIMAL, ["fit.steps=1", "fit={steps: bad}"])
    assert "(--set fit={steps: bad}): fit.steps: expected int" in message


# --------------------------------------------------------------------------- round trip, dump, hash


def full_config(tmp_path: Path) -> Experiment:
    return load_config(write(tmp_path, FULL), Experiment)


def test_to_dict_is_plain_data(tmp_path: Path) -> None:
    data = to_dict(full_config(tmp_path))
    assert data["resolution"] == [32, 16]
    assert data["lights"][0] == {"kind": "point", "power": 3.0, "position": [1.0, 2.0, 3.0]}
    assert data["fit"]["geometry"] == {"learning_rate": 0.001, "steps": 20}
    # json round-trips it unchanged only if every value is a plain list/dict/scalar.
    assert json.loads(json.dumps(data)) == data


def test_round_trip_from_dict_to_dict(tmp_path: Path) -> None:
    config = full_config(tmp_path)
    assert from_dict(to_dict(config), Experiment) == config
    defaults = Experiment(name="d", scene=Scene(shape="cube"))
    assert from_dict(to_dict(defaults), Experiment) == defaults


def test_to_dict_rejects_non_instances() -> None:
    with pytest.raises(TypeError):
        to_dict({"a": 1})
    with pytest.raises(TypeError):
        to_dict(Experiment)


def test_dump_resolved_reloads_equal_and_leaves_no_temp_files(tmp_path: Path) -> None:
    config = full_config(tmp_path)
    output = tmp_path / "run" / "resolved.yaml"
    assert dump_resolved(config, output) == output
    assert load_config(output, Experiment) == config
    assert sorted(path.name for path in output.parent.iterdir()) == ["resolved.yaml"]
    assert output.read_text(encoding="utf-8").startswith("name: full\nscene:\n")
    # Overwriting an existing file works the same way.
    dump_resolved(Experiment(name="other", scene=Scene(shape="cube")), output)
    assert load_config(output, Experiment).name == "other"
    assert sorted(path.name for path in output.parent.iterdir()) == ["resolved.yaml"]


def test_dump_resolved_failure_keeps_old_file_and_no_temp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = full_config(tmp_path)
    output = tmp_path / "resolved.yaml"
    output.write_text("old\n", encoding="utf-8")

    def failing_replace(source: str, target: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        dump_resolved(config, output)
    assert output.read_text(encoding="utf-8") == "old\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["experiment.yaml", "resolved.yaml"]


def test_dump_handles_special_floats_and_yaml_like_strings(tmp_path: Path) -> None:
    config = Experiment(
        name="yes",  # would read back as a bool if written unquoted
        scene=Scene(shape="cube", scale=math.inf),
        fit=Fit(geometry=Geometry(learning_rate=1e-7)),
        tag="123",
    )
    output = dump_resolved(config, tmp_path / "special.yaml")
    assert load_config(output, Experiment) == config


def test_hash_is_stable_and_short(tmp_path: Path) -> None:
    first = config_hash(full_config(tmp_path))
    second = config_hash(full_config(tmp_path))
    assert first == second
    assert len(first) == 12
    assert all(character in "0123456789abcdef" for character in first)


def test_hash_changes_when_a_value_changes(tmp_path: Path) -> None:
    config = full_config(tmp_path)
    changed = load_config(write(tmp_path, FULL), Experiment, ["fit.geometry.steps=21"])
    assert config_hash(changed) != config_hash(config)
    nested_list_change = load_config(write(tmp_path, FULL), Experiment, ["lights[1].power=2"])
    assert config_hash(nested_list_change) != config_hash(config)


def test_hash_ignores_int_float_spelling_and_dict_order() -> None:
    scene = Scene(shape="cube")
    built_with_int = Experiment(name="a", scene=scene, fit=Fit(weights={"b": 1, "a": 2}))
    built_with_float = Experiment(name="a", scene=scene, fit=Fit(weights={"a": 2.0, "b": 1.0}))
    assert config_hash(built_with_int) == config_hash(built_with_float)


def test_hash_survives_dump_and_reload(tmp_path: Path) -> None:
    config = full_config(tmp_path)
    reloaded = load_config(dump_resolved(config, tmp_path / "resolved.yaml"), Experiment)
    assert config_hash(reloaded) == config_hash(config)
