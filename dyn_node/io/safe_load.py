"""YAML and JSON of user files, parsed fast and strictly.

YAML goes through libyaml (``CSafeLoader``) when PyYAML has it. Stricter than ``yaml.safe_load``
where YAML 1.1 silently changes a value: numbers are YAML 1.2's (``1:30`` is text, not 90;
``1_000`` and ``012`` are not read as 1000 and 10), duplicate keys are refused (the last would
win), and aliases may not expand the document beyond :data:`ALIAS_GROWTH` times its own node
count (a "billion laughs" file is refused before anything walks it). JSON refuses duplicate
keys too. Nesting deeper than Python's recursion allows is an error, not a crash. Line numbers
are found only when an error is reported (:func:`yaml_line`)."""
from __future__ import annotations

import json
import re
from typing import Any

import yaml
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.resolver import Resolver

from dyn_node.io.text import shown

#: Aliases may make the document at most this many times its written node count (plus a
#: little): enough for anchors reused as defaults, far from an exponential bomb.
ALIAS_GROWTH = 10
ALIAS_SLACK = 10_000
#: Nesting depth of a document at most (a limits file needs 5, a trajectory 4).
MAX_DEPTH = 64

_INT = "tag:yaml.org,2002:int"
_FLOAT = "tag:yaml.org,2002:float"
_MERGE = "tag:yaml.org,2002:merge"


class LoadError(ValueError):
    """The text is not acceptable YAML/JSON: ``problem`` and its 1-based ``line`` (or None)."""

    def __init__(self, problem: str, line: int | None = None):
        super().__init__(f"line {line}: {problem}" if line else problem)
        self.problem, self.line = problem, line


class _StrictResolver(Resolver):
    """YAML 1.2 core-schema numbers: no sexagesimal, no underscores, no leading-zero octal."""


_StrictResolver.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in rules if tag not in (_INT, _FLOAT)]
    for first, rules in Resolver.yaml_implicit_resolvers.items()}
_StrictResolver.add_implicit_resolver(
    _INT, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), list("-+0123456789"))
_StrictResolver.add_implicit_resolver(
    _FLOAT, re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                       r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"), list("-+.0123456789"))


class _StrictConstructor(SafeConstructor):
    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        value = self.construct_scalar(node)
        return int(value, 0) if value[:2] in ("0o", "0x") else int(value, 10)

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == _MERGE or not isinstance(key_node, yaml.ScalarNode):
                    continue
                key = self.construct_object(key_node)
                if key in seen:
                    raise ConstructorError(
                        None, None, f"duplicate key {shown(key)} (first at line {seen[key]}): "
                        "each key once", key_node.start_mark)
                seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)


_StrictConstructor.add_constructor(_INT, _StrictConstructor.construct_yaml_int)
_StrictConstructor.add_constructor("tag:yaml.org,2002:map", SafeConstructor.construct_yaml_map)
_Parser = getattr(yaml, "CParser", None)
if _Parser is not None:
    class _Loader(yaml.CParser, _StrictConstructor, _StrictResolver):  # type: ignore[misc]
        def __init__(self, stream: str):
            yaml.CParser.__init__(self, stream)
            _StrictConstructor.__init__(self)
            _StrictResolver.__init__(self)
else:  # pragma: no cover - PyYAML built without libyaml
    from yaml.composer import Composer
    from yaml.parser import Parser
    from yaml.reader import Reader
    from yaml.scanner import Scanner

    class _Loader(Reader, Scanner, Parser, Composer, _StrictConstructor, _StrictResolver):  # type: ignore[no-redef]
        def __init__(self, stream: str):
            Reader.__init__(self, stream)
            Scanner.__init__(self)
            Parser.__init__(self)
            Composer.__init__(self)
            _StrictConstructor.__init__(self)
            _StrictResolver.__init__(self)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return node.value
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a document whose aliases expand it beyond the bound, nest too deep or refer back
    to themselves: one walk over the distinct nodes, sizes and heights memoised."""
    done: dict[int, tuple[int, int]] = {}
    open_: dict[int, list[int]] = {id(root): [1, 0]}
    stack = [(root, iter(_children(root)))]
    while stack:
        node, it = stack[-1]
        child = next(it, None)
        if child is None:
            stack.pop()
            size, height = open_.pop(id(node))
            done[id(node)] = (size, height + 1)
            if height + 1 > MAX_DEPTH:
                raise LoadError(f"nested more than {MAX_DEPTH} levels deep", node.start_mark.line + 1)
            if size > ALIAS_GROWTH * len(done) + ALIAS_SLACK:
                raise LoadError(f"aliases expand the document to more than {size} nodes "
                                f"(from {len(done)} written): refused", node.start_mark.line + 1)
            if stack:
                parent = open_[id(stack[-1][0])]
                parent[0] += size
                parent[1] = max(parent[1], height + 1)
            continue
        key = id(child)
        if key in open_:
            raise LoadError("an alias refers to a node containing it (recursive)",
                            child.start_mark.line + 1)
        if key in done:
            parent = open_[id(node)]
            parent[0] += done[key][0]
            parent[1] = max(parent[1], done[key][1])
            if parent[0] > ALIAS_GROWTH * len(done) + ALIAS_SLACK:
                raise LoadError(f"aliases expand the document to more than {parent[0]} nodes "
                                f"(from {len(done)} written): refused", child.start_mark.line + 1)
            continue
        open_[key] = [1, 0]
        stack.append((child, iter(_children(child))))


def _mark_line(exc: yaml.YAMLError) -> int | None:
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    return mark.line + 1 if mark is not None else None


def load_yaml(text: str) -> Any:
    """The one YAML document of ``text`` (None when empty); raises :class:`LoadError`."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if "*" in text:  # no alias can expand a document without one
            _check_expansion(node)
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise LoadError(str(problem), _mark_line(exc)) from None
    except RecursionError:
        raise LoadError("nested too deeply") from None
    finally:
        loader.dispose()


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise LoadError(f"duplicate key {shown(k)}: each key once")
        out[k] = v
    return out


def load_json(text: str) -> Any:
    """The JSON value of ``text``; raises :class:`LoadError` (with the line where json says)."""
    try:
        return json.loads(text, object_pairs_hook=_unique_pairs)
    except json.JSONDecodeError as exc:
        raise LoadError(exc.msg, exc.lineno) from None
    except RecursionError:
        raise LoadError("nested too deeply") from None


def yaml_line(text: str, *path: str | int) -> int | None:
    """The 1-based line of the node at ``path`` (keys and indices; JSON is YAML here) or of
    its deepest existing ancestor; None when the text does not compose."""
    try:
        node = yaml.compose(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (yaml.YAMLError, RecursionError):
        return None
    best = None
    for key in path:
        if node is None:
            break
        best = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode) and isinstance(key, str):
            node = next((v for k, v in node.value if getattr(k, "value", None) == key), None)
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            node = None
    return node.start_mark.line + 1 if node is not None else best


__all__ = ["ALIAS_GROWTH", "LoadError", "MAX_DEPTH", "load_json", "load_yaml", "yaml_line"]
