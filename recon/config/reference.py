"""The config reference, generated from the schema: every key with type, default, allowed values
and the doc its field carries (``setting(default, doc)`` in recon/config/run_config.py).

``config_keys`` lists the keys as records (``recon config keys`` prints them);
``reference_markdown`` renders them as docs/config.md, which a test compares with the file.
Allowed ranges are read from the ``check_range`` calls in each schema's ``__post_init__`` (the
validation itself), so the reference cannot drift from what the loader accepts.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing
from typing import Any, Literal

import yaml

from recon.config.checks import describe_bounds
from recon.config.schema import (
    NONE_TYPE,
    field_doc,
    has_default,
    is_schema,
    schema_fields,
    union_members,
)

REGENERATE_COMMAND = "recon config keys --markdown > docs/config.md"


@dataclasses.dataclass(frozen=True)
class ConfigKey:
    """One key of the config reference.

    key: dotted path (``capture.cameras.fov_deg``; ``[]`` marks the items of a list of sections).
    type: short type name (``float``, ``list[int]``, ``str | null``, ``section``).
    default: the default as YAML, or ``required``.
    allowed: the accepted values (literal options or a range), empty when any value of the type is.
    doc: the field's description; None when the field has none (a test forbids that).
    section: the dataclass that declares the key.
    """

    key: str
    type: str
    default: str
    allowed: str
    doc: str | None
    section: str


def type_name(hint: Any) -> str:
    """A short, YAML-minded name of a type hint: ``float``, ``list[int]``, ``str | null``."""
    if hint is NONE_TYPE:
        return "null"
    if hint in (bool, int, float, str):
        return hint.__name__
    if is_schema(hint):
        return "section"
    members = union_members(hint)
    if members is not None:
        return " | ".join(type_name(member) for member in members)
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if origin is Literal:
        kinds = sorted({type(option).__name__ for option in arguments})
        return " | ".join(kinds)
    if origin is list and len(arguments) == 1:
        return f"list[{_item_name(arguments[0])}]"
    if origin is tuple:
        return f"list[{', '.join(_item_name(argument) for argument in arguments)}]"
    if origin is dict and len(arguments) == 2:
        return f"map[{type_name(arguments[0])}, {type_name(arguments[1])}]"
    return repr(hint)


def _item_name(hint: Any) -> str:
    if hint is Ellipsis:
        return "..."
    return hint.__name__ if is_schema(hint) else type_name(hint)


def _literal_options(hint: Any) -> tuple[Any, ...]:
    """The options of a Literal hint, also inside Optional[...] and list[...]; else ()."""
    origin = typing.get_origin(hint)
    if origin is Literal:
        return typing.get_args(hint)
    members = union_members(hint)
    if members is not None:
        return tuple(option for member in members for option in _literal_options(member))
    if origin in (list, tuple):
        return tuple(
            option for argument in typing.get_args(hint) for option in _literal_options(argument)
        )
    return ()


def _constant(node: ast.expr | None) -> Any:
    if node is None:
        return None
    try:
        return ast.literal_eval(node)
    except ValueError:
        return None


def _loop_keys(loop: ast.For) -> list[str]:
    """The names a ``for key in ("a", "b"):`` loop walks over, or [] for any other loop."""
    values = _constant(loop.iter)
    if isinstance(values, (tuple, list)) and all(isinstance(value, str) for value in values):
        return list(values)
    return []


def _range_call_bounds(call: ast.Call) -> str:
    """``in [8, 512]`` from ``check_range(value, key, low=8, high=512)`` (keywords or positional)."""
    options = {"low": None, "high": None, "low_inclusive": True, "high_inclusive": True}
    for name, node in zip(("low", "high"), call.args[2:4], strict=False):
        options[name] = _constant(node)
    for keyword in call.keywords:
        if keyword.arg in options:
            options[keyword.arg] = _constant(keyword.value)
    if options["low"] is None and options["high"] is None:
        return ""
    return describe_bounds(
        options["low"], options["high"], options["low_inclusive"], options["high_inclusive"]
    )


def _is_range_call(node: ast.AST) -> bool:
    if not isinstance(node, ast.Call) or len(node.args) < 2:
        return False
    function = node.func
    name = function.id if isinstance(function, ast.Name) else getattr(function, "attr", "")
    return name == "check_range"


def checked_ranges(schema_cls: type) -> dict[str, str]:
    """Field name -> accepted range, read from the schema's ``__post_init__`` check_range calls.

    Understands ``check_range(self.field, ...)`` and a loop
    ``for key in ("a", "b"): check_range(getattr(self, key), key, ...)``; other checks (a
    relation between fields, a list's length) are described in the fields' docs instead.
    """
    post_init = schema_cls.__dict__.get("__post_init__")
    if post_init is None:
        return {}
    tree = ast.parse(textwrap.dedent(inspect.getsource(post_init)))
    ranges: dict[str, str] = {}
    loops = [node for node in ast.walk(tree) if isinstance(node, ast.For)]
    loop_of: dict[int, ast.For] = {}
    for loop in loops:
        for node in ast.walk(loop):
            loop_of.setdefault(id(node), loop)
    for node in ast.walk(tree):
        if not _is_range_call(node):
            continue
        bounds = _range_call_bounds(node)
        if not bounds:
            continue
        value = node.args[0]
        if (
            isinstance(value, ast.Attribute)
            and isinstance(value.value, ast.Name)
            and value.value.id == "self"
        ):
            ranges[value.attr] = bounds
        elif isinstance(value, ast.Call) and getattr(value.func, "id", "") == "getattr":
            loop = loop_of.get(id(node))
            for name in _loop_keys(loop) if loop is not None else []:
                ranges[name] = bounds
    return ranges


def _default_text(field: dataclasses.Field) -> str:
    """The default as one line of YAML (sections by their defaults' values), or ``required``."""
    if not has_default(field):
        return "required"
    if field.default is not dataclasses.MISSING:
        value = field.default
    else:
        value = field.default_factory()
    if is_schema(type(value)):
        return "(section)"
    value = _plain(value)
    text = yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
    return text.removesuffix("\n...").removesuffix("...").strip()


def _plain(value: Any) -> Any:
    """Dataclass instances inside a default (a list of sections) as plain mappings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {name: _plain(getattr(value, name)) for name in schema_fields(type(value))}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    return value


def _section_of(hint: Any) -> tuple[type | None, str]:
    """(schema, suffix) when hint holds a section: ``X``, ``X | None`` -> '', ``list[X]`` -> '[]'."""
    if is_schema(hint):
        return hint, ""
    members = union_members(hint)
    if members is not None:
        non_null = [member for member in members if member is not NONE_TYPE]
        if len(non_null) == 1 and is_schema(non_null[0]):
            return non_null[0], ""
    if typing.get_origin(hint) is list:
        arguments = typing.get_args(hint)
        if len(arguments) == 1 and is_schema(arguments[0]):
            return arguments[0], "[]"
    return None, ""


def config_keys(schema_cls: type, prefix: str = "") -> list[ConfigKey]:
    """Every key of schema_cls, depth first in declaration order, sections before their keys."""
    keys: list[ConfigKey] = []
    ranges = checked_ranges(schema_cls)
    for name, (field, hint) in schema_fields(schema_cls).items():
        path = f"{prefix}{name}"
        section, suffix = _section_of(hint)
        options = _literal_options(hint)
        allowed = ", ".join(repr(option) for option in options) if options else ""
        if name in ranges:
            allowed = ranges[name] if not allowed else f"{allowed}; {ranges[name]}"
        keys.append(
            ConfigKey(
                key=path,
                type=f"list[{section.__name__}]" if suffix else type_name(hint),
                default=_default_text(field),
                allowed=allowed,
                doc=field_doc(field),
                section=schema_cls.__name__,
            )
        )
        if section is not None:
            keys.extend(config_keys(section, f"{path}{suffix}."))
    return keys


def _summary(schema_cls: type) -> str:
    """The first paragraph of a schema's docstring on one line ('' when it has none)."""
    doc = schema_cls.__doc__ or ""
    if doc.startswith(f"{schema_cls.__name__}("):  # the dataclass's generated signature
        return ""
    return " ".join(inspect.cleandoc(doc).split("\n\n")[0].split())


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def format_keys(keys: list[ConfigKey]) -> str:
    """The keys as plain text for a terminal: ``key  type = default  (allowed)`` + the doc."""
    lines = []
    for item in keys:
        allowed = f"  ({item.allowed})" if item.allowed else ""
        lines.append(f"{item.key}  {item.type} = {item.default}{allowed}")
        lines.append(f"    {item.doc or '(undocumented)'}")
    return "\n".join(lines) + "\n"


def reference_markdown(schema_cls: type | None = None) -> str:
    """docs/config.md: one table per section, every key with type, default, allowed values, doc."""
    if schema_cls is None:
        from recon.config.run_config import RunConfig

        schema_cls = RunConfig
    keys = config_keys(schema_cls)
    sections: dict[str, list[ConfigKey]] = {"": []}
    for item in keys:
        parent = item.key.rsplit(".", 1)[0] if "." in item.key else ""
        sections.setdefault(parent, []).append(item)
    schemas = _section_schemas(schema_cls)
    out = [
        "# Config reference",
        "",
        f"Generated from the schema's field docs ({schema_cls.__module__}); do not edit by hand.",
        f"Regenerate with `{REGENERATE_COMMAND}`; a test fails when this file is stale.",
        "",
        "A config is YAML; every key is optional (defaults below) and unknown keys are errors.",
        "Override any key on the command line with `--set key=value` (YAML syntax for the value)",
        "and see the resolved result with `recon config show CONFIG [--set ...]`.",
        "`[]` in a key marks the items of a list of sections.",
        "",
    ]
    for parent, items in sections.items():
        schema = schemas.get(parent, schema_cls)
        title = parent or "top level"
        out.append(f"## `{title}` ({schema.__name__})")
        out.append("")
        summary = _summary(schema)
        if summary:
            out.extend([summary, ""])
        out.append("| key | type | default | allowed | description |")
        out.append("|---|---|---|---|---|")
        for item in items:
            name = item.key.rsplit(".", 1)[-1]
            default = f"`{_cell(item.default)}`" if item.default != "(section)" else "(section)"
            out.append(
                f"| `{name}` | {_cell(item.type)} | {default} | {_cell(item.allowed)} | "
                f"{_cell(item.doc or '')} |"
            )
        out.append("")
    return "\n".join(out)


def _section_schemas(schema_cls: type, prefix: str = "") -> dict[str, type]:
    """Dotted section path -> its schema class (``capture.cameras`` -> CameraRigConfig)."""
    found = {prefix.rstrip("."): schema_cls}
    for name, (_, hint) in schema_fields(schema_cls).items():
        section, suffix = _section_of(hint)
        if section is not None:
            found.update(_section_schemas(section, f"{prefix}{name}{suffix}."))
    return found
