"""YAML for scenario files, batch files and ``--set`` values: safe, strict and bounded.

:func:`load` parses with a :class:`yaml.SafeLoader` (no Python tags) that also rejects
duplicate keys, nesting deeper than :data:`MAX_DEPTH`, aliases that expand to more than
:data:`MAX_VALUES` values (the "billion laughs" of a few anchors) or that contain
themselves, and input over :data:`MAX_BYTES` or not UTF-8. Every problem is a
:class:`YamlError` of one line.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

MAX_BYTES = 1_000_000  # the largest shipped scenario has about 5 KB
MAX_DEPTH = 50  # nested mappings and lists; a scenario nests about 6 deep
MAX_VALUES = 100_000  # scalars, lists and mappings after expanding aliases; a scenario has a few hundred


class YamlError(ValueError):
    """YAML that cannot be loaded: the message says why, and where, in one line."""


class _Loader(yaml.SafeLoader):
    """A safe loader that counts its nesting, rejects duplicate keys and reads ``1e-9`` and
    ``1.5e3`` as numbers (YAML 1.2; PyYAML's YAML 1.1 wants ``1.5e+3`` and reads them as text)."""

    def __init__(self, stream: str):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise YamlError(f"line {self.peek_event().start_mark.line + 1}: nested deeper than {MAX_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                continue  # merged keys may be overridden; an unhashable key fails in construction
            key = self.construct_object(key_node)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise YamlError(f"line {line}: duplicate key {key!r} (first at line {seen[key]})")
            seen[key] = line
        return super().construct_mapping(node, deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"), list("-+.0123456789")
)


def _check_expansion(root: Node) -> None:
    """Raise :class:`YamlError` if ``root``, its aliases expanded, nests deeper than
    :data:`MAX_DEPTH`, has more than :data:`MAX_VALUES` values, or contains itself."""
    expanded: dict[int, tuple[int, int]] = {}  # id(node) -> (values, depth below it)
    open_nodes: set[int] = set()

    def walk(node: Node, depth: int) -> tuple[int, int]:
        key = id(node)
        line = node.start_mark.line + 1
        if key in open_nodes:
            raise YamlError(f"line {line}: an alias refers to a value that contains it")
        if key not in expanded:
            open_nodes.add(key)
            children = [n for pair in node.value for n in pair] if isinstance(node, MappingNode) else node.value
            values, below = 1, 0
            for child in children if isinstance(node, (MappingNode, SequenceNode)) else []:
                count, height = walk(child, depth + 1)
                values, below = values + count, max(below, height + 1)
            open_nodes.discard(key)
            expanded[key] = values, below
        values, below = expanded[key]
        if depth + below > MAX_DEPTH:
            raise YamlError(f"line {line}: nested deeper than {MAX_DEPTH} levels once aliases are expanded")
        if values > MAX_VALUES:
            raise YamlError(f"line {line}: more than {MAX_VALUES} values (aliases expanded)")
        return values, below

    walk(root, 1)


def _message(exc: yaml.YAMLError) -> str:
    """A YAML error in one line: where, what, and what it was parsing."""
    if not isinstance(exc, yaml.MarkedYAMLError):
        return " ".join(str(exc).split())
    where = f"line {exc.problem_mark.line + 1}, column {exc.problem_mark.column + 1}: " if exc.problem_mark else ""
    context = ""
    if exc.context:
        at = f" at line {exc.context_mark.line + 1}" if exc.context_mark else ""
        context = f" ({exc.context}{at})"
    return f"{where}{exc.problem}{context}"


def load(source: str | bytes | Path) -> Any:
    """The data of a YAML file (a :class:`~pathlib.Path`) or text; :class:`YamlError` if it
    cannot be read, is not YAML, or breaks one of the limits of this module."""
    if isinstance(source, Path):
        try:
            with source.open("rb") as f:
                source = f.read(MAX_BYTES + 1)
        except OSError as exc:
            raise YamlError(f"cannot read: {exc.strerror}") from None
    if len(source) > MAX_BYTES:
        raise YamlError(f"larger than {MAX_BYTES} bytes")
    if isinstance(source, bytes):
        try:
            source = source.decode("utf-8")
        except UnicodeDecodeError as exc:
            line = source.count(b"\n", 0, exc.start) + 1
            raise YamlError(f"line {line}: not UTF-8 text (byte 0x{source[exc.start]:02x} at offset {exc.start})") from None
    try:
        loader = _Loader(source)
        root = loader.get_single_node()
        if root is None:
            return None
        _check_expansion(root)
        return loader.construct_document(root)
    except YamlError:
        raise
    except yaml.YAMLError as exc:
        raise YamlError(f"not valid YAML: {_message(exc)}") from None
    except ValueError as exc:  # a constructor's own, e.g. an integer of more than 4300 digits
        raise YamlError(f"not valid YAML: {exc}") from None
