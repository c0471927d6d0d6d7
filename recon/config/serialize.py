"""Config instances back to plain data: to_dict, the resolved YAML dump and the config hash."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import tempfile
import typing
from pathlib import Path
from typing import Any

import yaml

from recon.config.schema import KeyPath, format_path, schema_fields, single_non_null


def _plain(value: Any, hint: Any, path: KeyPath) -> Any:
    """value as plain Python data; hint (the field's type, or None) normalises ints to floats.

    The hint matters for config_hash: a float field built in code as ``1`` must hash like the
    ``1.0`` that loading the dumped YAML gives back.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            name: _plain(getattr(value, name), field_hint, (*path, name))
            for name, (_, field_hint) in schema_fields(type(value)).items()
        }
    hint = single_non_null(hint)
    if value is None:
        return None
    # The builtin constructors drop subclasses (numpy scalars, str enums) that yaml.safe_dump
    # cannot represent.
    if isinstance(value, bool):
        return bool(value)
    if isinstance(value, int):
        return float(value) if hint is float else int(value)
    if isinstance(value, float):
        return float(value)
    if isinstance(value, str):
        return str(value)
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if isinstance(value, (list, tuple)):
        if origin is tuple and arguments and arguments[-1] is not Ellipsis:
            item_hints = list(arguments) if len(arguments) == len(value) else [None] * len(value)
        elif origin in (list, tuple) and arguments:
            item_hints = [arguments[0]] * len(value)
        else:
            item_hints = [None] * len(value)
        return [
            _plain(item, item_hint, (*path, index))
            for index, (item, item_hint) in enumerate(zip(value, item_hints, strict=True))
        ]
    if isinstance(value, dict):
        value_hint = arguments[1] if origin is dict and len(arguments) == 2 else None
        result = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"to_dict: {format_path(path)}: key {key!r} is not a string")
            result[str(key)] = _plain(item, value_hint, (*path, key))
        return result
    raise TypeError(
        f"to_dict: {format_path(path)}: cannot convert {type(value).__name__} to plain data"
    )


def to_dict(instance: Any) -> dict[str, Any]:
    """The config as plain dicts, lists, str, int, float, bool and None (tuples become lists).

    from_dict(to_dict(config), type(config)) == config for any valid config.
    """
    if not dataclasses.is_dataclass(instance) or isinstance(instance, type):
        raise TypeError(f"to_dict expects a config dataclass instance, got {instance!r}")
    return _plain(instance, type(instance), ())


def config_hash(instance: Any, exclude: tuple[str, ...] = ()) -> str:
    """First 12 hex digits of the sha256 of the config's canonical JSON.

    Keys are sorted so that dict order (which == ignores) does not change the hash. exclude:
    top-level sections left out (a fit's hash need not change with the diagnose section).
    """
    record = {key: value for key, value in to_dict(instance).items() if key not in exclude}
    canonical = json.dumps(record, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:12]


def _write_text_atomic(path: str | Path, text: str) -> Path:
    """Write text to path so readers see the old file or the new one, never half of one.

    The temporary file sits in the same folder because os.replace is only atomic within one
    file system.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, temporary = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
    )
    try:
        with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        # mkstemp creates the file private (0600); a resolved config is meant to be shared.
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise
    return path


def dump_resolved(instance: Any, path: str | Path) -> Path:
    """Write the config as plain YAML (fields in schema order) atomically; return the path.

    Loading the file with load_config and the same schema gives back an equal config.
    """
    text = yaml.safe_dump(
        to_dict(instance), sort_keys=False, default_flow_style=False, allow_unicode=True
    )
    return _write_text_atomic(path, text)
