"""Trajectory files for ``dyn-check``: JointTrajectory as YAML or JSON, or a CSV table; pure.

Formats: docs/dyn-check.md. Reading checks only the *shape*
(:class:`TrajectoryFileError` names file, line and field); values the node would refuse (NaN,
unknown joints, times not increasing) are kept, so the check rejects them with the node's reason.
"""
from __future__ import annotations

import csv
import io
import json
import math
import re
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from dyn_node.errors import TrajectoryFileError
from dyn_node.io.files import FileProblem, read_text
from dyn_node.io.safe_load import LoadError, load_json, load_yaml, yaml_line
from dyn_node.io.text import escape, shown

FORMATS = {".yaml": "yaml", ".yml": "yaml", ".json": "json", ".csv": "csv"}


@dataclass(frozen=True)
class TrajectoryFile:
    """A trajectory read from a file: names, times (s) and per-point rows in the file's joint
    order (velocities / accelerations None when the file has none)."""

    path: str
    format: str
    joint_names: list[str]
    times: list[float]
    positions: list[list[float]]
    velocities: list[list[float]] | None = None
    accelerations: list[list[float]] | None = None
    stamp: tuple[int, int] = (0, 0)
    frame_id: str = ""

    @property
    def stamp_ns(self) -> int:
        return self.stamp[0] * 1_000_000_000 + self.stamp[1]

    def stretched(self, factor: float) -> "TrajectoryFile":
        """The same path run ``factor`` times slower: times × k, velocities ÷ k, accelerations ÷ k²."""
        def div(rows: list[list[float]] | None, by: float) -> list[list[float]] | None:
            return None if rows is None else [[x / by for x in r] for r in rows]

        return replace(self, times=[message_time(t * factor) for t in self.times],
                       velocities=div(self.velocities, factor),
                       accelerations=div(self.accelerations, factor * factor))


def file_format(path: str | Path) -> str:
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise TrajectoryFileError(path, None, "", f"unknown file type '{Path(path).suffix}' "
                                  "(.yaml, .yml, .json or .csv)")
    return fmt


#: Largest trajectory file read (bytes; ``dyn-check --max-file-mb``) and most points (``--max-points``):
#: a file beyond either is refused before it is parsed (parsing 1e5 points takes about a second).
MAX_TRAJECTORY_BYTES = 16_000_000
MAX_POINTS = 100_000


def read_trajectory(path: str | Path, *, max_bytes: int = MAX_TRAJECTORY_BYTES,
                    max_points: int = MAX_POINTS) -> TrajectoryFile:
    """Read one trajectory file (format from its extension); raises :class:`TrajectoryFileError`,
    also for a file of more than ``max_bytes`` bytes or ``max_points`` points."""
    fmt = file_format(path)
    try:
        text = read_text(path, max_bytes=max_bytes)
    except FileProblem as exc:
        hint = " (dyn-check --max-file-mb raises it)" if "at most" in str(exc) else ""
        raise TrajectoryFileError(path, None, "", f"{exc}{hint}") from None
    return parse_trajectory(text, fmt, str(path), max_points=max_points)


def _too_many(path: str, counted: str, max_points: int) -> TrajectoryFileError:
    return TrajectoryFileError(path, None, "points", f"{counted}, more than the {max_points} points "
                               "read at most (dyn-check --max-points raises it)")


def parse_trajectory(text: str, fmt: str, path: str = "<text>", *,
                     max_points: int | None = None) -> TrajectoryFile:
    text = text.removeprefix("\ufeff")    # a byte-order mark is not part of the first field
    if max_points is not None:
        # counted before parsing: every point has a time_from_start (a CSV row a line); an
        # overcount (the word in a comment) only refuses a file already near the cap
        if fmt == "csv":
            n, unit = text.count("\n") - 1, "rows after the header"
        else:
            n, unit = text.count("time_from_start"), "time_from_start entries"
        if n > max_points:
            raise _too_many(path, f"{n} {unit}", max_points)
    try:
        tf = _parse_csv(text, path) if fmt == "csv" else _parse_mapping(text, fmt, path)
    except RecursionError:
        raise TrajectoryFileError(path, None, "", "nested too deeply") from None
    if max_points is not None and len(tf.times) > max_points:   # YAML aliases repeat points
        raise _too_many(path, f"{len(tf.times)} points", max_points)
    return tf


#: Range of builtin_interfaces' int32 ``sec`` (of Time and Duration) and the times it can hold.
SEC_MIN, SEC_MAX = -(2 ** 31), 2 ** 31 - 1


# --- YAML / JSON -------------------------------------------------------------------------------
def _load(text: str, fmt: str, path: str) -> Any:
    try:
        return load_json(text) if fmt == "json" else load_yaml(text)
    except LoadError as exc:
        if exc.field:   # a value the loader refuses (e.g. an integer of 5,000 digits)
            raise TrajectoryFileError(path, exc.line, escape(exc.field), exc.problem) from None
        raise TrajectoryFileError(path, exc.line, "",
                                  f"not valid {fmt.upper()}: {exc.problem}") from None


def _number(x: Any, fail: Any) -> float:
    # bool is an int in Python, not a number in a trajectory
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        if isinstance(x, str) and x.strip().lower() in ("nan", ".nan", "inf", ".inf", "-inf", "-.inf"):
            return float(x.strip().lower().replace(".", ""))  # parsed: the check rejects it
        fail(f"not a number ({shown(x)})")
    try:
        return float(x)
    except OverflowError:
        fail(f"too large for a number ({shown(x)})")
        raise   # not reached: fail raises


_FLOAT_ONLY = frozenset({float})


def _numbers(seq: list[Any], fail: Any) -> list[float]:
    # the common case at C speed: every item an int or a float (no bool, no huge int)
    if set(map(type, seq)) <= _FLOAT_ONLY:
        return seq
    return [_number(x, lambda p, j=j: fail(p, j)) for j, x in enumerate(seq)]


def _parse_mapping(text: str, fmt: str, path: str) -> TrajectoryFile:
    doc = _load(text, fmt, path)

    def fail(field: str, problem: str, *at: str | int) -> None:
        # the line is looked up only now, when there is an error to report
        raise TrajectoryFileError(path, yaml_line(text, *at), field, problem)

    if not isinstance(doc, dict):
        fail("", "expected a mapping with joint_names and points (a trajectory_msgs/JointTrajectory)")
    names = doc.get("joint_names")
    if names is None:
        fail("joint_names", "missing")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        fail("joint_names", "must be a list of joint names (strings)", "joint_names")
    points = doc.get("points")
    if points is None:
        fail("points", "missing")
    if not isinstance(points, list):
        fail("points", "must be a list of points", "points")
    unknown = _Unknown()
    unknown.check(doc, _TOP_KEYS, "", ())
    if isinstance(doc.get("header"), dict):
        unknown.check(doc["header"], _HEADER_KEYS, "header.", ("header",))
        if isinstance(doc["header"].get("stamp"), dict):
            unknown.check(doc["header"]["stamp"], _TIME_KEYS, "header.stamp.", ("header", "stamp"))
    stamp, frame_id = _header(doc.get("header"), lambda f, p, *at: fail(f"header.{f}", p, "header", *at))
    times: list[float] = []
    rows: dict[str, list[list[float]]] = {"positions": [], "velocities": [], "accelerations": []}
    for i, pt in enumerate(points):
        where = f"points[{i}]"
        if not isinstance(pt, dict):
            fail(where, "must be a mapping (positions, velocities, accelerations, time_from_start)",
                 "points", i)
        if not _POINT_KEYS.issuperset(pt):   # (the f-string only when some key is unknown)
            unknown.check(pt, _POINT_KEYS, f"{where}.", ("points", i))
        d = pt.get("time_from_start")
        if isinstance(d, dict) and not _TIME_KEYS.issuperset(d):
            unknown.check(d, _TIME_KEYS, f"{where}.time_from_start.", ("points", i, "time_from_start"))
        for key in rows:
            seq = pt.get(key, [])
            if key == "positions" and key not in pt:
                fail(f"{where}.positions", "missing", "points", i)
            if not isinstance(seq, list):
                fail(f"{where}.{key}", "must be a list of numbers", "points", i, key)
            rows[key].append(_numbers(seq, lambda p, j, key=key: fail(
                f"{where}.{key}[{j}]", p, "points", i, key, j)))
        _effort(pt, len(names), lambda p, *at: fail(f"{where}.effort", p, "points", i, "effort", *at))
        times.append(_duration(pt.get("time_from_start"),
                               lambda f, p: fail(f"{where}.time_from_start{f}", p, "points", i,
                                                 "time_from_start")))
    if unknown.found:
        fail(*unknown.problem())
    vel = rows["velocities"] if any(rows["velocities"]) else None
    acc = rows["accelerations"] if any(rows["accelerations"]) else None
    return TrajectoryFile(path, fmt, list(names), times, rows["positions"], vel, acc, stamp, frame_id)


_TOP_KEYS = frozenset({"header", "joint_names", "points"})
_HEADER_KEYS = frozenset({"stamp", "frame_id"})
_POINT_KEYS = frozenset({"positions", "velocities", "accelerations", "effort", "time_from_start"})
_TIME_KEYS = frozenset({"sec", "nanosec"})
#: Unknown keys named in the error at most (the rest counted).
UNKNOWN_SHOWN = 10


class _Unknown:
    """Unknown keys of a trajectory file, all collected, so one error names every one (a key
    dropped silently changes the trajectory: a ``nanosecs`` typo turns 1.9 s into 1 s)."""

    def __init__(self) -> None:
        self.found: list[tuple[str, str]] = []     # (field, hint)
        self.first_at: tuple[str | int, ...] = ()

    def check(self, mapping: dict, known: frozenset[str], prefix: str, at: tuple[str | int, ...]) -> None:
        if known.issuperset(mapping):
            return
        # only now: the suggestion's module brings numpy, which reading a file needs not
        from dyn_node.core.robot.task_limits import did_you_mean

        for key in mapping:
            if key not in known:
                if not self.found:
                    self.first_at = (*at, key) if isinstance(key, str) else at
                self.found.append((f"{prefix}{escape(str(key), 80)}", did_you_mean(str(key), known)))

    def problem(self) -> tuple[str, str, *tuple[str | int, ...]]:
        """(field, problem, path of the first) for ``fail``: one key named as the field."""
        if len(self.found) == 1:
            return self.found[0][0], f"unknown key{self.found[0][1]}", *self.first_at
        listed = "; ".join(f"{f}{h}" for f, h in self.found[:UNKNOWN_SHOWN])
        more = f"; … and {len(self.found) - UNKNOWN_SHOWN} more" if len(self.found) > UNKNOWN_SHOWN else ""
        return "", f"{len(self.found)} unknown keys: {listed}{more}", *self.first_at


def _effort(pt: dict, n_joints: int, fail: Any) -> None:
    """joint_trajectory_controller's rule: a point's effort is empty or one value per joint
    (its values are not used: dyn_node computes the torque)."""
    if "effort" not in pt:
        return
    effort = pt["effort"]
    if not isinstance(effort, list):
        fail("must be a list of numbers")
    if effort and len(effort) != n_joints:
        fail(f"{len(effort)} values for {n_joints} joints (joint_trajectory_controller refuses an "
             "effort that is neither empty nor one value per joint)")
    _numbers(effort, lambda p, j: fail(p, j))


def _header(h: Any, fail: Any) -> tuple[tuple[int, int], str]:
    if h is None:
        return (0, 0), ""
    if not isinstance(h, dict):
        fail("", "must be a mapping (stamp, frame_id)")
    frame_id = h.get("frame_id", "")
    if not isinstance(frame_id, str):
        fail("frame_id", "must be a string", "frame_id")
    st = h.get("stamp", {}) or {}
    if not isinstance(st, dict):
        fail("stamp", "must be a mapping {sec, nanosec}", "stamp")
    out = []
    for key in ("sec", "nanosec"):
        v = st.get(key, 0)
        top = SEC_MAX if key == "sec" else 10**9 - 1
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= top:
            fail(f"stamp.{key}", f"must be an integer from 0 to {top} ({shown(v)})", "stamp", key)
        out.append(int(v))
    return (out[0], out[1]), frame_id


def _duration(d: Any, fail: Any) -> float:
    """A builtin_interfaces/Duration {int32 sec, uint32 nanosec < 1e9}, or seconds within its
    range (rounded to it, as the message would carry them)."""
    if d is None:
        fail("", "missing")
    if isinstance(d, dict):
        sec, nsec = d.get("sec", 0), d.get("nanosec", 0)
        for key, v, lo, hi in (("sec", sec, SEC_MIN, SEC_MAX), ("nanosec", nsec, 0, 10**9 - 1)):
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                fail(f".{key}", f"must be an integer from {lo} to {hi} ({shown(v)})")
        return sec + nsec * 1e-9
    t = _number(d, lambda p: fail("", p + "; expected {sec, nanosec} or seconds"))
    if math.isfinite(t) and not SEC_MIN <= t < SEC_MAX + 1:
        fail("", f"{t:g} s is beyond what a message's time_from_start holds "
                 f"(int32 seconds: {SEC_MIN} to {SEC_MAX})")
    return message_time(t)


def message_time(t: float) -> float:
    """``t`` s as the node reads it from a message: rounded to {sec, nanosec}, then
    sec + nanosec·1e-9 (non-finite values stay, for the check to reject)."""
    if not math.isfinite(t):
        return t
    d = _split_seconds(t)
    return d["sec"] + d["nanosec"] * 1e-9


# --- CSV -----------------------------------------------------------------------------------------
#: A CSV cell that is a number: ASCII digits only (float() would take '1_000' and other
#: scripts' digits), or nan / inf.
_CSV_NUMBER = re.compile(r"[-+]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|nan|inf|infinity)\Z",
                         re.ASCII | re.IGNORECASE)


def _parse_csv(text: str, path: str) -> TrajectoryFile:
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except StopIteration:
        raise TrajectoryFileError(path, 1, "", "empty file: expected a header row (time, joints)") from None
    except csv.Error as exc:
        raise TrajectoryFileError(path, 1, "", f"not valid CSV: {exc}") from None
    cols = [c.strip() for c in header]
    if "time" not in cols:
        raise TrajectoryFileError(path, 1, "time", "missing column (seconds from the start)")
    dup = sorted(c for c, n in Counter(cols).items() if n > 1)
    if dup:
        raise TrajectoryFileError(path, 1, escape(dup[0]), "column appears twice")
    joints = [c for c in cols if c != "time" and not c.endswith((".vel", ".acc"))]
    if not joints:
        raise TrajectoryFileError(path, 1, "", "no joint columns (one column per joint, named as the joint)")
    extra: dict[str, bool] = {}
    for suffix in (".vel", ".acc"):
        given = [c for c in cols if c.endswith(suffix)]
        for c in given:
            if c[:-len(suffix)] not in joints:
                raise TrajectoryFileError(path, 1, escape(c),
                                          f"no position column '{escape(c[:-len(suffix)])}' for it")
        if given and len(given) != len(joints):
            have = set(given)
            missing = next(f"{j}{suffix}" for j in joints if f"{j}{suffix}" not in have)
            raise TrajectoryFileError(path, 1, escape(missing), f"missing column (the {suffix} columns must "
                                      "cover every joint or none)")
        extra[suffix] = bool(given)
    idx = {c: i for i, c in enumerate(cols)}
    times: list[float] = []
    P: list[list[float]] = []
    V: list[list[float]] = []
    A: list[list[float]] = []
    try:
        for row in reader:
            line = reader.line_num
            if not any(cell.strip() for cell in row):
                continue  # blank line
            if len(row) != len(cols):
                raise TrajectoryFileError(path, line, "", f"{len(row)} cells for {len(cols)} columns")

            def cell(name: str) -> float:
                raw = row[idx[name]].strip()
                if not _CSV_NUMBER.match(raw):
                    raise TrajectoryFileError(path, line, escape(name), f"not a number ({shown(raw)}) (ASCII "
                                              "digits, '.', an exponent, nan or inf)")
                return float(raw)

            t = cell("time")
            if math.isfinite(t) and not SEC_MIN <= t < SEC_MAX + 1:
                raise TrajectoryFileError(path, line, "time", f"{t:g} s is beyond what a message's "
                                          f"time_from_start holds (int32 seconds)")
            times.append(message_time(t))
            P.append([cell(j) for j in joints])
            if extra[".vel"]:
                V.append([cell(f"{j}.vel") for j in joints])
            if extra[".acc"]:
                A.append([cell(f"{j}.acc") for j in joints])
    except csv.Error as exc:
        raise TrajectoryFileError(path, reader.line_num, "", f"not valid CSV: {exc}") from None
    if not times:
        raise TrajectoryFileError(path, 2, "", "no rows after the header")
    return TrajectoryFile(path, "csv", joints, times, P, V or None, A or None)


# --- writing -------------------------------------------------------------------------------------
def _split_seconds(t: float) -> dict[str, int]:
    ns = int(round(t * 1e9))
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def to_mapping(tf: TrajectoryFile) -> dict[str, Any]:
    """The trajectory as the message's fields (what the YAML and JSON files hold)."""
    points = []
    for i, t in enumerate(tf.times):
        pt: dict[str, Any] = {"positions": [float(x) for x in tf.positions[i]]}
        if tf.velocities is not None:
            pt["velocities"] = [float(x) for x in tf.velocities[i]]
        if tf.accelerations is not None:
            pt["accelerations"] = [float(x) for x in tf.accelerations[i]]
        pt["time_from_start"] = _split_seconds(t)
        points.append(pt)
    return {"header": {"stamp": {"sec": int(tf.stamp[0]), "nanosec": int(tf.stamp[1])},
                       "frame_id": tf.frame_id},
            "joint_names": list(tf.joint_names), "points": points}


def format_trajectory(tf: TrajectoryFile, fmt: str | None = None) -> str:
    """The text of ``tf`` in ``fmt`` (default: its own format); floats round-trip exactly."""
    fmt = fmt or tf.format
    if fmt == "json":
        return json.dumps(to_mapping(tf), indent=1) + "\n"
    if fmt == "yaml":
        return yaml.safe_dump(to_mapping(tf), sort_keys=False, default_flow_style=None)
    cols = ["time", *tf.joint_names]
    if tf.velocities is not None:
        cols += [f"{j}.vel" for j in tf.joint_names]
    if tf.accelerations is not None:
        cols += [f"{j}.acc" for j in tf.joint_names]
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(cols)
    for i, t in enumerate(tf.times):
        row: list[float] = [t, *tf.positions[i]]
        if tf.velocities is not None:
            row += tf.velocities[i]
        if tf.accelerations is not None:
            row += tf.accelerations[i]
        w.writerow([repr(float(x)) for x in row])
    return out.getvalue()

