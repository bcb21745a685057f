"""Reading spec text: YAML (which also reads JSON) and JSON, with bounds on what a few bytes can cost.

* **Anchors and aliases** are accepted (``examples/tanks.yaml`` repeats a subsystem with ``&tap`` / ``<<: *tap``),
  but the document's size *as expanded* is bounded: :data:`MAX_YAML_NODES` values, counted on the composed node
  graph before anything is constructed (a node reached through ``k`` aliases counts ``k`` times), so a
  "billion laughs" document of a few hundred bytes is refused before it costs anything. A recursive alias (a
  node that contains itself) is refused too.
* **Integers** have at most :data:`MAX_INT_DIGITS` digits (YAML: in any base, by value). Python refuses to
  convert integer strings of more than 4,300 digits (``ValueError``); nothing in a spec needs more than a few
  dozen digits.
* **Non-finite numbers** (``.inf``, ``.nan``, ``1e999``) are read as floats here and refused by the spec model
  (``allow_inf_nan=False``), which names the field; JSON's ``NaN``/``Infinity`` are refused here.
* **Exponents without a dot or a sign** (``1e-6``, ``1.5e3``) are numbers, as in YAML 1.2 and JSON (YAML 1.1 reads them as strings).
* **Duplicate keys** in one mapping (YAML) or object (JSON) are refused, naming the key and where: both readers
  would otherwise keep the last silently. A YAML merge key (``<<: *tap``) is not a duplicate: the mapping's own keys
  override the merged ones, as YAML says.

Every refusal is a :class:`~pipelines.errors.SpecError` naming where: the line and column (YAML) or the path of
the value (JSON).
"""

from __future__ import annotations

import json
import re
from typing import Any

import yaml

from pipelines.errors import SpecError

#: Most digits of an integer in a spec (beyond it, a SpecError naming where).
MAX_INT_DIGITS = 100
#: Most values (scalars, lists and mappings) of a YAML document once its aliases are expanded. An alias-free
#: document of 1 MiB (the service's default ``max_body_bytes``) has at most about 520,000.
MAX_YAML_NODES = 1_000_000

_INT_LIMIT = 10**MAX_INT_DIGITS


def _int_refusal(where: str, digits: int) -> SpecError:
    return SpecError(f"{where}: an integer of {digits:,} digits; integers in a spec have at most {MAX_INT_DIGITS} digits")


def _where(node: yaml.Node) -> str:
    mark = node.start_mark
    return f"line {mark.line + 1}, column {mark.column + 1}"


class SpecLoader(yaml.SafeLoader):
    """PyYAML's safe loader with a bound on the expanded size and on integer literals (module docstring)."""

    max_nodes = MAX_YAML_NODES

    def construct_document(self, node: yaml.Node) -> Any:
        expanded_size(node, self.max_nodes)  # before any value is built
        return super().construct_document(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, yaml.Node] = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node)
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:  # not hashable: the constructor below says so
                    continue
                if first is not key_node:
                    raise SpecError(f"{_where(key_node)}: the key {str(key)[:60]!r} is given twice in one mapping "
                                    f"(first at {_where(first)}); give each key once")
        return super().construct_mapping(node, deep=deep)

    def construct_bounded_int(self, node: yaml.Node) -> int:
        text = str(node.value)
        if len(text) > MAX_INT_DIGITS + 8:  # sign, base prefix, a few '_': beyond it, too long in any form
            raise _int_refusal(_where(node), sum(c.isalnum() for c in text))
        value = int(super().construct_yaml_int(node))
        if abs(value) >= _INT_LIMIT:  # a short literal in base 16 or 60 can still be a long number
            raise _int_refusal(_where(node), len(str(abs(value))))  # < 300 digits: the literal is this short
        return value


SpecLoader.add_constructor("tag:yaml.org,2002:int", SpecLoader.construct_bounded_int)
# YAML 1.1 (PyYAML) reads an exponent without a dot or without a sign (``1e-6``, ``2E5``, ``1.5e3``) as a string;
# YAML 1.2 and JSON read a number, and so does a spec (the strict model would refuse `alpha: 1e-6` as a string).
#: A number with an exponent that YAML 1.1 does not read as one (no dot, or an exponent without a sign).
EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
SpecLoader.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT_FLOAT, list("-+.0123456789"))


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def expanded_size(root: yaml.Node, limit: int = MAX_YAML_NODES) -> int:
    """The number of values of the document ``root`` with every alias expanded, without expanding them.

    Each node's expanded size is computed once (memoised), so the walk is linear in the composed graph.

    Raises
    ------
    SpecError
        Past ``limit`` values, or for a node that contains itself, naming the line.
    """
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, finished = stack.pop()
        key = id(node)
        if finished:
            on_path.discard(key)
            size = 1 + sum(sizes[id(c)] for c in _children(node))
            if size > limit:
                raise SpecError(
                    f"{_where(node)}: the YAML document expands to more than {limit:,} values through its anchors "
                    f"and aliases, beyond the bound on a spec's expanded size (MAX_YAML_NODES = {limit:,} values)"
                )
            sizes[key] = size
            continue
        if key in sizes:
            continue
        if key in on_path:
            raise SpecError(f"{_where(node)}: a YAML alias refers to a value that contains it (a recursive alias)")
        on_path.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node) if id(c) not in sizes)
    return sizes[id(root)]


def load_yaml(text: str, max_nodes: int = MAX_YAML_NODES) -> Any:
    """The value of a YAML (or JSON) document, within the bounds of the module docstring.

    Raises
    ------
    SpecError
        For a bound exceeded, naming the line and column.
    yaml.YAMLError
        For text that does not parse.
    """
    loader = SpecLoader(text)
    loader.max_nodes = max_nodes
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


class _BigInt:
    """A JSON integer literal beyond :data:`MAX_INT_DIGITS`, kept until its path is known."""

    def __init__(self, digits: int) -> None:
        self.digits = digits


class _Constant:
    """JSON's ``NaN``, ``Infinity`` or ``-Infinity``, kept until its path is known."""

    def __init__(self, name: str) -> None:
        self.name = name


class _Duplicate:
    """A JSON object with a key given twice, kept until its path is known."""

    def __init__(self, key: str) -> None:
        self.key = key


def _find_marker(data: Any) -> tuple[str, _BigInt | _Constant | _Duplicate] | None:
    """The path and marker of the first refused literal in document order."""
    stack: list[tuple[str, Any]] = [("", data)]
    while stack:
        path, value = stack.pop()
        if isinstance(value, (_BigInt, _Constant, _Duplicate)):
            return path or "(the document)", value
        items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
        stack.extend((f"{path}.{k}" if path else str(k), v) for k, v in reversed(list(items)))
    return None


def load_json(text: str) -> Any:
    """The value of a JSON document; ``NaN``/``Infinity`` and integers beyond :data:`MAX_INT_DIGITS` refused.

    Raises
    ------
    SpecError
        Naming the path of an integer that is too long (``subsystems.0.samples``), the constant, or the object with
        a key given twice.
    json.JSONDecodeError
        For text that does not parse.
    """
    refused = 0

    def parse_int(literal: str) -> int | _BigInt:
        nonlocal refused
        digits = len(literal.lstrip("-"))
        if digits <= MAX_INT_DIGITS:
            return int(literal)
        refused += 1
        return _BigInt(digits)

    def parse_constant(name: str) -> _Constant:
        nonlocal refused
        refused += 1
        return _Constant(name)

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any] | _Duplicate:
        nonlocal refused
        out = dict(items)
        if len(out) < len(items):
            refused += 1
            keys = [k for k, _ in items]
            return _Duplicate(next(k for i, k in enumerate(keys) if k in keys[:i]))
        return out

    data = json.loads(text, parse_constant=parse_constant, parse_int=parse_int, object_pairs_hook=pairs)
    found = _find_marker(data) if refused else None
    if found is not None:
        path, marker = found
        if isinstance(marker, _Constant):
            raise SpecError(f"{path}: {marker.name} is not a number a spec can use (give a finite number)")
        if isinstance(marker, _Duplicate):
            raise SpecError(f"{path}: the key {marker.key[:60]!r} is given twice in one object; give each key once")
        raise _int_refusal(path, marker.digits)
    return data
