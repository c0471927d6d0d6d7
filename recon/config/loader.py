"""Load YAML configs into schema dataclasses, strictly, with ``--set`` overrides.

Every error is a ConfigError whose message reads ``WHERE: KEY.PATH: REASON`` where WHERE is
``file:line`` for values from the file, or ``file (--set key=value)`` for values an override
put there.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml

from recon.config.checks import ConfigFieldError
from recon.config.retired import retired_reason
from recon.config.schema import (
    NONE_TYPE,
    KeyPath,
    describe_type,
    describe_value,
    format_path,
    has_default,
    is_schema,
    schema_fields,
    single_non_null,
    union_members,
)
from recon.config.yaml_io import parse_document, parse_value
from recon.errors import ConfigError, warn_user

Schema = TypeVar("Schema")

_NUMBER_TEXT = re.compile(r"^\s*[-+]?(\d[\d_]*\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")
_INDEX_SUFFIX = re.compile(r"\[(\d+)\]")
_KEY_SEGMENT = re.compile(r"^(?P<name>[^\[\]]*)(?P<indices>(?:\[\d+\])*)$")


# --------------------------------------------------------------------------- suggestions


def suggest(word: str, options: Iterable[str]) -> str | None:
    """The option the user most likely meant by word, or None.

    difflib catches typos (``lerning_rate``); the initials rule catches the common
    abbreviation (``lr`` for ``learning_rate``) that difflib scores far too low; the substring
    rule catches truncations (``fov`` for ``fov_deg``).
    """
    options = list(options)
    matches = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    if matches:
        return matches[0]
    lowered = word.lower()
    for option in options:
        initials = "".join(part[0] for part in option.lower().split("_") if part)
        if len(initials) > 1 and lowered == initials:
            return option
    for option in options:
        candidate = option.lower()
        if len(lowered) >= 2 and lowered in candidate:
            return option
        if len(candidate) >= 3 and candidate in lowered:
            return option
    return None


def _unknown_key_reason(key: str, valid_keys: list[str]) -> str:
    """``unknown key (did you mean 'x'?); valid keys: a, b`` for an unknown key."""
    guess = suggest(key, valid_keys)
    hint = f" (did you mean {guess!r}?)" if guess else ""
    valid = ", ".join(valid_keys) if valid_keys else "none"
    return f"unknown key{hint}; valid keys here: {valid}"


# --------------------------------------------------------------------------- error context


@dataclasses.dataclass(frozen=True)
class _Context:
    """Where values came from, so an error can name the file line or the override."""

    source: str
    lines: Mapping[KeyPath, int]
    origins: Mapping[KeyPath, str]  # key path an override set -> the override's text

    def where(self, path: KeyPath) -> str:
        # An override replaces the whole subtree below its path, so its origin wins over any
        # (now stale) file line below that path.
        for length in range(len(path), -1, -1):
            origin = self.origins.get(path[:length])
            if origin is not None:
                return f"{self.source} (--set {origin})"
        for length in range(len(path), -1, -1):
            line = self.lines.get(path[:length])
            if line is not None:
                return f"{self.source}:{line}"
        return self.source

    def error(self, path: KeyPath, reason: str) -> ConfigError:
        return ConfigError(f"{self.where(path)}: {format_path(path)}: {reason}")


def _mismatch(hint: Any, value: Any) -> str:
    """``expected int, got str '10'`` plus a hint for the usual YAML surprises."""
    reason = f"expected {describe_type(hint)}, got {describe_value(value)}"
    if isinstance(value, bool) and hint in (int, float):
        reason += " (true/false is not a number)"
    elif isinstance(value, str) and hint in (int, float) and _NUMBER_TEXT.match(value):
        reason += " (write the number without quotes)"
    return reason


# --------------------------------------------------------------------------- conversion


def _convert(value: Any, hint: Any, path: KeyPath, context: _Context) -> Any:
    """Check value against hint and return it in the schema's types (tuples, floats, ...)."""
    members = union_members(hint)
    if members is not None:
        return _convert_union(value, hint, members, path, context)
    if hint is NONE_TYPE:
        if value is None:
            return None
        raise context.error(path, _mismatch(hint, value))
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise context.error(path, _mismatch(hint, value))
    if hint is int:
        # bool is a subclass of int in Python, but `steps: true` is a mistake, not 1.
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise context.error(path, _mismatch(hint, value))
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:
                raise context.error(path, f"number too large for a float: {value}") from None
        raise context.error(path, _mismatch(hint, value))
    if hint is str:
        if isinstance(value, str):
            return value
        raise context.error(path, _mismatch(hint, value))
    if is_schema(hint):
        return _build(value, hint, path, context)
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if origin is Literal:
        return _convert_literal(value, arguments, path, context)
    if origin is list and len(arguments) == 1:
        if not isinstance(value, (list, tuple)):
            raise context.error(path, _mismatch(hint, value))
        return [
            _convert(item, arguments[0], (*path, index), context)
            for index, item in enumerate(value)
        ]
    if origin is tuple:
        return _convert_tuple(value, hint, arguments, path, context)
    if origin is dict and len(arguments) == 2 and arguments[0] is str:
        if not isinstance(value, dict):
            raise context.error(path, _mismatch(hint, value))
        result = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise context.error(path, f"keys must be strings, got {describe_value(key)}")
            result[key] = _convert(item, arguments[1], (*path, key), context)
        return result
    # A schema bug, not a user error: say so with the schema's own words.
    raise TypeError(f"config schema: unsupported type hint {hint!r} at {format_path(path)}")


def _convert_union(
    value: Any, hint: Any, members: tuple[Any, ...], path: KeyPath, context: _Context
) -> Any:
    """Optional[X] converts as X (its precise errors kept); wider unions try each member."""
    non_null = [member for member in members if member is not NONE_TYPE]
    if value is None:
        if len(non_null) < len(members):
            return None
        raise context.error(path, _mismatch(hint, value))
    if len(non_null) == 1:
        return _convert(value, non_null[0], path, context)
    for member in non_null:
        try:
            return _convert(value, member, path, context)
        except ConfigError:
            continue
    raise context.error(path, _mismatch(hint, value))


def _convert_literal(value: Any, allowed: tuple[Any, ...], path: KeyPath, context: _Context) -> Any:
    """value if it is one of allowed (same type too: 1 does not match True)."""
    for option in allowed:
        if type(value) is type(option) and value == option:
            return option
    reason = (
        f"expected one of {', '.join(repr(option) for option in allowed)}, "
        f"got {describe_value(value)}"
    )
    if isinstance(value, str):
        guess = suggest(value, [option for option in allowed if isinstance(option, str)])
        if guess is not None:
            reason += f" (did you mean {guess!r}?)"
    raise context.error(path, reason)


def _convert_tuple(
    value: Any, hint: Any, arguments: tuple[Any, ...], path: KeyPath, context: _Context
) -> tuple:
    """A YAML list into a tuple: fixed length for tuple[X, Y], any length for tuple[X, ...]."""
    if not isinstance(value, (list, tuple)):
        raise context.error(path, _mismatch(hint, value))
    if len(arguments) == 2 and arguments[1] is Ellipsis:
        item_hints = [arguments[0]] * len(value)
    else:
        if len(value) != len(arguments):
            raise context.error(
                path,
                f"expected {describe_type(hint)}, got a list of {len(value)} items "
                f"{describe_value(value).removeprefix('list ')}",
            )
        item_hints = list(arguments)
    return tuple(
        _convert(item, item_hint, (*path, index), context)
        for index, (item, item_hint) in enumerate(zip(value, item_hints, strict=True))
    )


def _without_retired(
    value: dict, path: KeyPath, fields: Mapping[str, Any], context: _Context
) -> dict:
    """value without the keys an earlier recon had and this one retired (recon.config.retired),
    each skipped with a warning: a run folder written before still loads."""
    kept = {}
    for key, item in value.items():
        reason = retired_reason((*path, key)) if key not in fields else None
        if reason is None:
            kept[key] = item
            continue
        warn_user(
            f"{context.where((*path, key))}: {format_path((*path, key))}: retired key, ignored; {reason}"
        )
    return kept


def _build(value: Any, schema_cls: type, path: KeyPath, context: _Context) -> Any:
    """Build schema_cls from a mapping: unknown, missing and invalid keys are errors."""
    if not isinstance(value, dict):
        raise context.error(path, _mismatch(schema_cls, value))
    fields = schema_fields(schema_cls)
    value = _without_retired(value, path, fields, context)
    for key in value:
        if not isinstance(key, str):
            raise context.error(path, f"keys must be strings, got {describe_value(key)}")
        if key not in fields:
            raise context.error((*path, key), _unknown_key_reason(key, list(fields)))
    missing = [
        name for name, (field, _) in fields.items() if name not in value and not has_default(field)
    ]
    if missing:
        reason = "missing required key"
        if len(missing) > 1:
            others = ", ".join(format_path((*path, name)) for name in missing[1:])
            reason += f" (also missing: {others})"
        raise context.error((*path, missing[0]), reason)
    arguments = {
        key: _convert(item, fields[key][1], (*path, key), context) for key, item in value.items()
    }
    try:
        return schema_cls(**arguments)
    except ConfigFieldError as error:
        # Raised by the schema's __post_init__ with a key relative to the dataclass.
        raise context.error((*path, *_parse_relative_key(error.key)), error.reason) from None
    except ValueError as error:  # any other validation in __post_init__ (ConfigError included)
        raise context.error(path, str(error)) from None


def _parse_relative_key(key: str) -> KeyPath:
    """``geometry.lr`` / ``fov_deg[1]`` -> ('geometry', 'lr') / ('fov_deg', 1)."""
    parts: list[str | int] = []
    for segment in key.split("."):
        match = _KEY_SEGMENT.match(segment)
        if match is None:
            parts.append(segment)
            continue
        if match["name"]:
            parts.append(match["name"])
        parts.extend(int(index) for index in _INDEX_SUFFIX.findall(match["indices"]))
    return tuple(parts)


# --------------------------------------------------------------------------- overrides


def _parse_override(text: str, source: str) -> tuple[list[str | int], Any]:
    """``a.b[0].c=value`` -> (['a', 'b', 0, 'c'], parsed YAML value)."""
    if "=" not in text:
        raise ConfigError(f"{source}: --set {text!r}: expected KEY=VALUE, e.g. --set fit.steps=100")
    key_text, value_text = text.split("=", 1)
    key_text = key_text.strip()
    parts: list[str | int] = []
    for segment in key_text.split("."):
        match = _KEY_SEGMENT.match(segment.strip())
        if match is None or not (match["name"] or (parts and match["indices"])):
            raise ConfigError(
                f"{source}: --set {text!r}: malformed key {key_text!r}; "
                "expected dotted names like fit.geometry.steps or lights[0].power"
            )
        if match["name"]:
            parts.append(match["name"])
        parts.extend(int(index) for index in _INDEX_SUFFIX.findall(match["indices"]))
    try:
        value = parse_value(value_text)
    except yaml.YAMLError as error:
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError(
            f"{source}: --set {text!r}: cannot read value {value_text!r} as YAML: {problem}"
        ) from None
    return parts, value


def _index(part: str | int) -> int | None:
    """A list index from ``3`` or ``[3]`` (both reach here as written), else None."""
    if isinstance(part, int):
        return part
    return int(part) if part.isdigit() else None


def _apply_override(
    data: dict, parts: list[str | int], value: Any, schema_cls: type, text: str, source: str
) -> KeyPath:
    """Set value at parts inside data, checking the path against the schema; return the path.

    Missing sections on the way are created (the file may rely on defaults). List items must
    already exist in the file: the schema's default list is not in the raw data.
    """

    def fail(path: KeyPath, reason: str) -> ConfigError:
        return ConfigError(f"{source} (--set {text}): {format_path(path)}: {reason}")

    hint: Any = schema_cls
    container: Any = data
    path: KeyPath = ()
    for position, part in enumerate(parts):
        last = position == len(parts) - 1
        hint = single_non_null(hint)  # navigate through Optional[X] into X
        origin = typing.get_origin(hint)
        arguments = typing.get_args(hint)
        if is_schema(hint):
            fields = schema_fields(hint)
            if not isinstance(part, str) or part not in fields:
                raise fail((*path, part), _unknown_key_reason(str(part), list(fields)))
            key: str | int = part
            child_hint = fields[part][1]
        elif origin is dict and len(arguments) == 2:
            key = str(part)
            child_hint = arguments[1]
        elif origin in (list, tuple):
            index = _index(part)
            if index is None:
                raise fail(path, f"is {describe_type(hint)}; {part!r} is not a list index")
            key = index
            fixed = origin is tuple and not (len(arguments) == 2 and arguments[1] is Ellipsis)
            if fixed and index >= len(arguments):
                raise fail((*path, index), f"index out of range for {describe_type(hint)}")
            child_hint = arguments[index] if fixed else arguments[0]
        else:
            what = "a union of several types" if hint is None else describe_type(hint)
            raise fail(path, f"is {what}; it has no key {part!r}")

        if isinstance(key, str) and not isinstance(container, dict):
            raise fail(path, f"is {describe_value(container)} in the config, not a mapping")
        if isinstance(key, int):
            if not isinstance(container, list):
                raise fail(path, f"cannot index into {describe_value(container)}")
            if key >= len(container):
                raise fail(
                    (*path, key),
                    f"index out of range: the list has {len(container)} items in the config "
                    f"(set the whole list instead: --set {format_path(path)}=[...])",
                )
        path = (*path, key)
        if last:
            container[key] = value
            return path
        child = container[key] if isinstance(key, int) else container.get(key)
        child_type = single_non_null(child_hint)
        child_origin = typing.get_origin(child_type)
        if child is None and (is_schema(child_type) or child_origin is dict):
            child = container[key] = {}  # the file relies on the section's defaults
        elif child is None and child_origin in (list, tuple):
            raise fail(path, "is not set in the config, so it has no items to change")
        elif child is None:
            # A scalar: the next step reports that it has no keys, without raw data to walk.
            child = {}
        hint = child_hint
        container = child
    raise AssertionError("unreachable: _parse_override returns at least one key part")


def _copy_tree(value: Any, source: str, parents: frozenset[int] = frozenset()) -> Any:
    """A copy of plain YAML data in which no two places share one dict or list.

    copy.deepcopy would keep YAML aliases (``b: *a``) shared, so an override of ``b.x`` would
    change ``a.x`` as well.
    """
    if not isinstance(value, (dict, list)):
        return value
    if id(value) in parents:
        raise ConfigError(f"{source}: recursive YAML alias (an anchor used inside itself)")
    parents = parents | {id(value)}
    if isinstance(value, dict):
        return {key: _copy_tree(item, source, parents) for key, item in value.items()}
    return [_copy_tree(item, source, parents) for item in value]


def _apply_overrides(
    data: dict, overrides: Iterable[str], schema_cls: type, source: str
) -> tuple[dict, dict[KeyPath, str]]:
    """A deep copy of data with the overrides applied, and the path -> override text map."""
    if isinstance(overrides, str):  # a lone string would be iterated character by character
        raise TypeError("overrides must be a list of 'key=value' strings, not one string")
    data = _copy_tree(data, source)
    origins: dict[KeyPath, str] = {}
    for text in overrides:
        parts, value = _parse_override(text, source)
        path = _apply_override(data, parts, value, schema_cls, text, source)
        # A later override of a whole section replaces what earlier ones set inside it.
        for earlier in [known for known in origins if known[: len(path)] == path]:
            del origins[earlier]
        origins[path] = text
    return data, origins


# --------------------------------------------------------------------------- public API


def _check_schema(schema_cls: Any) -> None:
    if not is_schema(schema_cls):
        raise TypeError(f"schema_cls must be a dataclass type, got {schema_cls!r}")


def _load(
    data: Any,
    schema_cls: type[Schema],
    source: str,
    overrides: Iterable[str],
    lines: Mapping[KeyPath, int],
) -> Schema:
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: the top level must be a mapping of keys to values, "
            f"got {describe_value(data)}"
        )
    data, origins = _apply_overrides(data, overrides, schema_cls, source)
    return _build(data, schema_cls, (), _Context(source, lines, origins))


def from_dict(
    data: dict,
    schema_cls: type[Schema],
    source: str = "<dict>",
    overrides: Iterable[str] = (),
) -> Schema:
    """Build schema_cls from plain data (as YAML would give it), strictly.

    source names the data's origin in error messages. overrides are ``key.path=value``
    strings applied to a copy of data before validation; data itself is never modified.
    Raises ConfigError for any invalid input, TypeError for an unsupported schema.
    """
    _check_schema(schema_cls)
    return _load(data, schema_cls, source, overrides, lines={})


def load_config(
    path: str | Path, schema_cls: type[Schema], overrides: Iterable[str] = ()
) -> Schema:
    """Read the YAML file at path into schema_cls, applying ``key.path=value`` overrides.

    An empty file counts as an empty mapping (all defaults). Raises ConfigError naming the
    file (and line, where known) for a missing or unreadable file, invalid YAML, duplicate
    keys, or any value the schema rejects.
    """
    _check_schema(schema_cls)
    path = Path(path)
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{source}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{source}: is a folder, expected a YAML config file") from None
    except UnicodeDecodeError as error:
        raise ConfigError(f"{source}: not UTF-8 text ({error.reason})") from None
    except OSError as error:
        raise ConfigError(f"{source}: cannot read config file ({error.strerror})") from None
    data, lines = parse_document(text, source)
    if data is None:
        data = {}
    return _load(data, schema_cls, source, overrides, lines)
