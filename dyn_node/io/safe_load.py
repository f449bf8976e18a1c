"""YAML and JSON of user files, parsed fast and strictly.

YAML: libyaml's events (PyYAML's C parser when it has one) built into values by one iterative
loop, faster than PyYAML's constructor and never recursive. Stricter than ``yaml.safe_load``
where YAML 1.1 silently changes a value: numbers are YAML 1.2's (``1:30`` is text, not 90;
``1_000`` is text, ``012`` is twelve), duplicate keys are refused (the last would win), nesting
stops at :data:`MAX_DEPTH`, and aliases may not expand the document beyond
:data:`ALIAS_GROWTH` times its written node count (a "billion laughs" is refused while read).
JSON: the standard parser, duplicate keys refused, too deep an error. Line numbers are found
only when an error is reported (:func:`yaml_line`)."""
from __future__ import annotations

import json
import math
import re
import sys
from typing import Any

import yaml

from dyn_node.io.text import shown

try:
    from yaml.cyaml import CParser as _CParser
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    _CParser = None

#: Aliases may make the document at most this many times its written node count (plus a
#: little): enough for anchors reused as defaults, far from an exponential bomb.
ALIAS_GROWTH = 10
ALIAS_SLACK = 10_000
#: Nesting depth of a document at most (a limits file needs 5, a trajectory 4).
MAX_DEPTH = 64
#: Digits an integer may be written with: Python's own default conversion limit, beyond which
#: ``int()`` raises (a traceback, not an answer). Smaller ones are read; every field then refuses
#: what it cannot hold (a number beyond float's 309 digits is "too large", a time out of range).
MAX_INT_DIGITS = 4300


def _max_digits() -> int:
    """:data:`MAX_INT_DIGITS`, or the interpreter's limit when set lower (0: none)."""
    limit = sys.get_int_max_str_digits()
    return min(MAX_INT_DIGITS, limit) if limit else MAX_INT_DIGITS



class LoadError(ValueError):
    """The text is not acceptable YAML/JSON: ``problem`` and its 1-based ``line`` (or None);
    ``field`` the value's path (``points[3].time_from_start.sec``) when the problem is a value."""

    def __init__(self, problem: str, line: int | None = None, field: str = ""):
        at = f"{field}: {problem}" if field else problem
        super().__init__(f"line {line}: {at}" if line else at)
        self.problem, self.line, self.field = problem, line, field


_INT_RX = re.compile(r"[-+]?[0-9]+\Z|0o[0-7]+\Z|0x[0-9a-fA-F]+\Z")
_FLOAT_RX = re.compile(r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?\Z")
_SPECIAL = {".inf": math.inf, ".Inf": math.inf, ".INF": math.inf, "+.inf": math.inf,
            "+.Inf": math.inf, "+.INF": math.inf, "-.inf": -math.inf, "-.Inf": -math.inf,
            "-.INF": -math.inf, ".nan": math.nan, ".NaN": math.nan, ".NAN": math.nan,
            "": None, "~": None, "null": None, "Null": None, "NULL": None}
# YAML 1.1's word booleans too (PyYAML's safe_load reads them so; ROS parameter files use them)
for _w in ("true", "True", "TRUE", "yes", "Yes", "YES", "on", "On", "ON"):
    _SPECIAL[_w] = True
for _w in ("false", "False", "FALSE", "no", "No", "NO", "off", "Off", "OFF"):
    _SPECIAL[_w] = False


class _HugeInt(LoadError):
    """An integer written with more than :data:`MAX_INT_DIGITS` digits (where is added later)."""


def _too_large(digits: int) -> str:
    return f"too large for a number (an integer of {digits} digits; at most {_max_digits()})"


def _int(value: str, base: int) -> int:
    if len(value) > 640:   # Python's smallest limit; a sign or a 0x / 0o prefix is not a digit
        digits = len(value.lstrip("+-").removeprefix("0x").removeprefix("0o"))
        if digits > _max_digits():
            raise _HugeInt(_too_large(digits))
    return int(value, base)


_TAGGED = {"tag:yaml.org,2002:str": str, "tag:yaml.org,2002:float": float,
           "tag:yaml.org,2002:int": lambda v: _int(v, 0) if v[:2] in ("0o", "0x") else _int(v, 10),
           "tag:yaml.org,2002:bool": lambda v: {"true": True, "false": False}[v.lower()],
           "tag:yaml.org,2002:null": lambda v: None}


_MISS = object()


def _plain(value: str) -> Any:
    """A plain (unquoted) scalar by YAML 1.2's core schema: null, bool, int, float, else text
    (``1:30`` stays text; ``012`` is twelve; no underscores in numbers)."""
    known = _SPECIAL.get(value, _MISS)
    if known is not _MISS:
        return known
    if _FLOAT_RX.match(value):
        return float(value) if ("." in value or "e" in value or "E" in value) else _int(value, 10)
    if _INT_RX.match(value):
        return _int(value, 0) if value[:2] in ("0o", "0x") else _int(value, 10)
    return value


def _scalar(ev: Any) -> Any:
    if ev.tag in (None, "!") or ev.tag == "?":
        return _plain(ev.value) if ev.implicit[0] else ev.value
    convert = _TAGGED.get(ev.tag)
    if convert is None:
        raise LoadError(f"tag {shown(ev.tag)} is not supported", ev.start_mark.line + 1)
    try:
        return convert(ev.value)
    except _HugeInt:
        raise
    except (ValueError, KeyError):
        raise LoadError(f"{shown(ev.value)} is not a {ev.tag.rsplit(':', 1)[-1]}",
                        ev.start_mark.line + 1) from None


class _Builder:
    """Python values from libyaml's events, iteratively (no recursion however deep the text:
    refused beyond :data:`MAX_DEPTH`, before libyaml's per-level cost grows). Each value's
    expanded size (aliases counted at every use) is tracked to bound alias growth."""

    def __init__(self) -> None:
        self.stack: list[list[Any]] = []     # [container, size, pending key | _NO_KEY, line]
        self.anchors: dict[str, tuple[Any, int]] = {}
        self.written = 0                      # nodes in the text
        self.result: Any = None
        self.done = False

    def add(self, value: Any, size: int, line: int) -> None:
        if size > ALIAS_GROWTH * self.written + ALIAS_SLACK:
            raise LoadError(f"aliases expand the document to more than {size} nodes "
                            f"(from {self.written} written): refused", line)
        if not self.stack:
            self.result, self.done = value, True
            return
        top = self.stack[-1]
        top[1] += size
        container = top[0]
        if isinstance(container, list):
            container.append(value)
        elif top[2] is _NO_KEY:
            try:
                hash(value)
            except TypeError:
                raise LoadError("a mapping key must be a scalar", line) from None
            if value in container:
                raise LoadError(f"duplicate key {shown(value)}: each key once", line)
            top[2] = value
        else:
            if top[2] == "<<" and isinstance(value, (dict, list)):
                top[4].append(value)          # a merge: applied under the explicit keys
            else:
                container[top[2]] = value
            top[2] = _NO_KEY

    def where(self) -> str:
        """The field the next value goes to, e.g. ``points[3].time_from_start.sec``."""
        out = ""
        for container, _, key, *_ in self.stack:
            if isinstance(container, list):
                out += f"[{len(container)}]"
            elif key is _NO_KEY:
                return f"{out or 'the document'}'s keys"
            else:
                out += f".{key}" if out else str(key)
        return out or "the document"

    def open(self, container: Any, ev: Any) -> None:
        if len(self.stack) >= MAX_DEPTH:
            raise LoadError(f"nested more than {MAX_DEPTH} levels deep", ev.start_mark.line + 1)
        self.written += 1
        self.stack.append([container, 1, _NO_KEY, ev.anchor, []])

    def close(self, line: int) -> None:
        container, size, _, anchor, merges = self.stack.pop()
        for m in merges:
            for part in (m if isinstance(m, list) else [m]):
                if isinstance(part, dict):
                    for k, v in part.items():
                        container.setdefault(k, v)
        if anchor is not None:
            self.anchors[anchor] = (container, size)
        self.add(container, size, line)


_NO_KEY = object()


def _mark_line(exc: yaml.YAMLError) -> int | None:
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    return mark.line + 1 if mark is not None else None


def load_yaml(text: str) -> Any:
    """The one YAML document of ``text`` (None when empty); raises :class:`LoadError`."""
    parser = _CParser(text) if _CParser is not None else yaml.SafeLoader(text)
    b = _Builder()
    try:
        while parser.check_event():
            ev = parser.get_event()
            kind = type(ev)
            if kind is yaml.ScalarEvent:
                b.written += 1
                try:
                    value = _plain(ev.value) if ev.tag is None and ev.implicit[0] else _scalar(ev)
                except _HugeInt as exc:
                    raise LoadError(exc.problem, ev.start_mark.line + 1, b.where()) from None
                if ev.anchor is not None:
                    b.anchors[ev.anchor] = (value, 1)
                top = b.stack[-1] if b.stack else None
                if top is not None and type(top[0]) is list:    # the common case, inline
                    top[0].append(value)
                    top[1] += 1
                else:
                    b.add(value, 1, ev.start_mark.line + 1)
            elif kind is yaml.SequenceStartEvent:
                b.open([], ev)
            elif kind is yaml.MappingStartEvent:
                b.open({}, ev)
            elif kind in (yaml.SequenceEndEvent, yaml.MappingEndEvent):
                b.close(ev.start_mark.line + 1)
            elif kind is yaml.AliasEvent:
                if ev.anchor not in b.anchors:
                    raise LoadError(f"alias *{shown(ev.anchor)} before its anchor (or inside it)",
                                    ev.start_mark.line + 1)
                b.add(*b.anchors[ev.anchor], ev.start_mark.line + 1)
            elif kind is yaml.DocumentStartEvent and b.done:
                raise LoadError("more than one document", ev.start_mark.line + 1)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise LoadError(str(problem), _mark_line(exc)) from None
    finally:
        if hasattr(parser, "dispose"):
            parser.dispose()
    return b.result


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(pairs)
    if len(out) != len(pairs):      # rare: find the key written twice
        seen: set[str] = set()
        for k, _ in pairs:
            if k in seen:
                raise LoadError(f"duplicate key {shown(k)}: each key once")
            seen.add(k)
    return out


class _Huge(str):
    """A JSON integer of too many digits, kept as its text until it is found and named."""


def _huge_at(value: Any, where: str = "") -> tuple[str, _Huge] | None:
    """(path, text) of the first :class:`_Huge` in a parsed JSON value, else None."""
    stack = [(where, value)]
    while stack:
        at, v = stack.pop()
        if isinstance(v, _Huge):
            return at or "the document", v
        if isinstance(v, dict):
            stack.extend((f"{at}.{k}" if at else str(k), x) for k, x in reversed(v.items()))
        elif isinstance(v, list):
            stack.extend((f"{at}[{i}]", x) for i, x in reversed(list(enumerate(v))))
    return None


def load_json(text: str) -> Any:
    """The JSON value of ``text``; raises :class:`LoadError` (with the line where json says).
    An integer of more than :data:`MAX_INT_DIGITS` digits is refused, naming its field."""
    try:
        return json.loads(text, object_pairs_hook=_unique_pairs)
    except json.JSONDecodeError as exc:
        raise LoadError(exc.msg, exc.lineno) from None
    except RecursionError:
        raise LoadError("nested too deeply") from None
    except ValueError as exc:   # int()'s digit limit: read again, only now, to name the field
        if "digits" not in str(exc):
            raise
    limit = _max_digits()
    found = _huge_at(json.loads(text, object_pairs_hook=_unique_pairs, parse_int=lambda d: (
        _Huge(d) if len(d.lstrip("-")) > limit else int(d))))
    if found is None:   # pragma: no cover - json raised for the limit, so some integer is over it
        raise LoadError(_too_large(limit + 1))
    raise LoadError(_too_large(len(found[1].lstrip("-"))), None, found[0])


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
