"""Type-hint helpers shared by the loader and the serializer.

A schema is a ``@dataclass`` whose fields carry one of the supported type hints: ``int``,
``float``, ``bool``, ``str``, ``Literal[...]``, ``list[X]``, ``tuple[X, Y]``, ``tuple[X, ...]``,
``dict[str, X]``, ``Optional[X]`` / ``X | None`` (and other unions of these) and nested schema
dataclasses.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from typing import Any, Literal, Union

# A key path inside a config: mapping keys are str, list indices are int.
KeyPath = tuple[str | int, ...]

NONE_TYPE = type(None)


def setting(
    default: Any = dataclasses.MISSING,
    doc: str = "",
    *,
    factory: Callable[[], Any] | Any = dataclasses.MISSING,
) -> Any:
    """A schema field with its documentation: ``dataclasses.field`` plus ``metadata["doc"]``.

    default: the value when a config leaves the key out; factory: a callable building a
    mutable default (lists, nested sections) instead. doc: one user-facing sentence, shown in
    docs/config.md and ``recon config keys``. Validation stays in the schema's __post_init__.
    """
    if not doc:
        raise TypeError("config schema: setting() needs a doc string")
    return dataclasses.field(default=default, default_factory=factory, metadata={"doc": doc})


def field_doc(field: dataclasses.Field) -> str | None:
    """The field's description from ``setting(..., doc)``, or None when it has none."""
    doc = field.metadata.get("doc")
    return doc if isinstance(doc, str) and doc.strip() else None


def is_schema(hint: Any) -> bool:
    """True when hint is a dataclass type (a section of the config)."""
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def schema_fields(schema_cls: type) -> dict[str, tuple[dataclasses.Field, Any]]:
    """The fields of schema_cls a config may set, in declaration order, with resolved hints.

    Fields with ``init=False`` are left out: the constructor does not take them, so a config
    cannot set them and to_dict must not emit them (or the round trip would break).
    """
    try:
        # get_type_hints resolves string annotations (``from __future__ import annotations``).
        hints = typing.get_type_hints(schema_cls)
    except NameError as error:
        raise TypeError(
            f"config schema {schema_cls.__qualname__}: cannot resolve a type hint ({error}); "
            "define schema classes at module level"
        ) from error
    return {
        field.name: (field, hints[field.name])
        for field in dataclasses.fields(schema_cls)
        if field.init
    }


def has_default(field: dataclasses.Field) -> bool:
    """True when the field may be left out of a config."""
    return (
        field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING
    )


def union_members(hint: Any) -> tuple[Any, ...] | None:
    """The members of a ``Union[...]`` / ``X | Y`` hint, or None when hint is not a union."""
    origin = typing.get_origin(hint)
    if origin is Union or origin is types.UnionType:
        return typing.get_args(hint)
    return None


def single_non_null(hint: Any) -> Any:
    """X for ``Optional[X]``, hint itself for a non-union, None for a union of several types."""
    members = union_members(hint)
    if members is None:
        return hint
    non_null = [member for member in members if member is not NONE_TYPE]
    return non_null[0] if len(non_null) == 1 else None


def describe_type(hint: Any) -> str:
    """A short, YAML-minded description of a type hint for error messages."""
    if hint is NONE_TYPE:
        return "null"
    if hint in (bool, int, float, str):
        return hint.__name__
    if is_schema(hint):
        return f"a mapping ({hint.__name__})"
    members = union_members(hint)
    if members is not None:
        return " or ".join(describe_type(member) for member in members)
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if origin is Literal:
        return "one of " + ", ".join(repr(option) for option in arguments)
    if origin is list and len(arguments) == 1:
        return f"a list of {_describe_items(arguments[0])}"
    if origin is tuple:
        if len(arguments) == 2 and arguments[1] is Ellipsis:
            return f"a list of {_describe_items(arguments[0])}"
        items = ", ".join(describe_type(argument) for argument in arguments)
        return f"a list of {len(arguments)} items [{items}]"
    if origin is dict and len(arguments) == 2:
        return f"a mapping of {describe_type(arguments[0])} to {describe_type(arguments[1])}"
    return repr(hint)


def _describe_items(hint: Any) -> str:
    """What a list holds: ``float`` or ``Light mappings`` (not ``a mapping (Light)``)."""
    return f"{hint.__name__} mappings" if is_schema(hint) else describe_type(hint)


def describe_value(value: Any, limit: int = 60) -> str:
    """The YAML type and a (shortened) repr of a value, e.g. ``str 'ten'`` or ``null``."""
    if value is None:
        return "null"
    if isinstance(value, dict):
        kind = "mapping"
    elif isinstance(value, (list, tuple)):
        kind = "list"
    else:
        kind = type(value).__name__
    text = repr(value)
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{kind} {text}"


def format_path(path: KeyPath) -> str:
    """Dotted key path for messages: ``('lights', 0, 'power')`` -> ``lights[0].power``."""
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else part
    return text or "(top level)"
