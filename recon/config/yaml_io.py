"""Strict YAML reading for configs: plain data, line numbers per key, clear syntax errors."""

from __future__ import annotations

import re
from typing import Any

import yaml

from recon.config.schema import KeyPath
from recon.errors import ConfigError

_MERGE_TAG = "tag:yaml.org,2002:merge"
_FLOAT_TAG = "tag:yaml.org,2002:float"

# PyYAML follows YAML 1.1, which reads ``1e-3`` (no dot) as the string "1e-3". Learning rates
# are written that way all the time, and a string where a float belongs would be rejected, so
# exponent notation without a dot is resolved as a float too (YAML 1.2 does the same).
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads ``1e-3`` as a float.

    Duplicate keys are an error because PyYAML otherwise keeps the last one silently, so an
    edit to the first occurrence would have no effect.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        first_lines: dict[Any, int] = {}
        for key_node, _ in node.value:
            # Merge keys (<<) may legitimately be overridden by explicit keys; only explicit
            # scalar keys are checked against each other.
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node)
            try:
                first_line = first_lines.get(key)
            except TypeError:  # unhashable key: SafeConstructor reports it below
                continue
            if first_line is not None:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping",
                    node.start_mark,
                    f"found duplicate key {key!r} (first set on line {first_line})",
                    key_node.start_mark,
                )
            first_lines[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_implicit_resolver(_FLOAT_TAG, _EXPONENT_FLOAT, list("-+0123456789."))


def _syntax_message(error: yaml.YAMLError, source: str) -> str:
    """``file:line:column: invalid YAML: problem`` from a PyYAML error."""
    if isinstance(error, yaml.MarkedYAMLError):
        mark = error.problem_mark or error.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark is not None else source
        problem = ", ".join(part for part in (error.context, error.problem) if part)
        return f"{where}: invalid YAML: {problem}"
    return f"{source}: invalid YAML: {error}"


def _record_lines(node: yaml.Node, path: KeyPath, lines: dict[KeyPath, int], stack: set) -> None:
    """Fill lines with the 1-based line of every key and list item below node."""
    if id(node) in stack:  # a recursive alias (&a [*a]) would otherwise loop forever
        return
    stack.add(id(node))
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            if isinstance(key_node, yaml.ScalarNode) and key_node.tag != _MERGE_TAG:
                child = (*path, key_node.value)
                lines.setdefault(child, key_node.start_mark.line + 1)
                _record_lines(value_node, child, lines, stack)
    elif isinstance(node, yaml.SequenceNode):
        for index, item_node in enumerate(node.value):
            child = (*path, index)
            lines.setdefault(child, item_node.start_mark.line + 1)
            _record_lines(item_node, child, lines, stack)
    stack.discard(id(node))


def parse_document(text: str, source: str) -> tuple[Any, dict[KeyPath, int]]:
    """Parse one YAML document into plain data and a map from key path to line number.

    An empty document gives None. Syntax errors raise ConfigError naming source and line.
    """
    loader = _StrictLoader(text)
    try:
        node = loader.get_single_node()
        data = None if node is None else loader.construct_document(node)
    except yaml.YAMLError as error:
        raise ConfigError(_syntax_message(error, source)) from None
    finally:
        loader.dispose()
    lines: dict[KeyPath, int] = {}
    if node is not None:
        _record_lines(node, (), lines, set())
    return data, lines


def parse_value(text: str) -> Any:
    """Parse a YAML scalar or flow value (``100``, ``torus``, ``[40, 50]``).

    Raises yaml.YAMLError for text that is not valid YAML.
    """
    # _StrictLoader derives from SafeLoader, so this constructs no arbitrary objects.
    return yaml.load(text, Loader=_StrictLoader)
