"""dyn-check: check trajectory files with no ROS graph, through the node's own core.

Each file (see :mod:`dyn_node.audit.trajectory_files`) is checked exactly as dyn_node checks a
trajectory it receives (:func:`dyn_node.core.check.on_demand.check`); one verdict line per file. Options,
``--retime`` and exit codes: docs/dyn-check.md. No rclpy import: this runs in a
CI job without ROS.
"""
from __future__ import annotations

import argparse
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from dyn_node.audit.accounting import CHECK, RequestTally
from dyn_node.errors import CheckError, DynNodeError, PLANNING_ERROR, STATE_ERROR, TrajectoryFileError
from dyn_node.audit.exit_codes import EXIT_UNUSABLE, MEANINGS, exit_code
from dyn_node.audit.trajectory_files import (MAX_POINTS, MAX_TRAJECTORY_BYTES, TrajectoryFile,
                                             format_trajectory, parse_trajectory, read_trajectory)
from dyn_node.core.robot.limits_file import MAX_LIMITS_BYTES
from dyn_node.io.files import FileProblem, read_text
from dyn_node.io.safe_load import LoadError
from dyn_node.io.text import escape

#: Characters of one printed line at most (values inside are capped already; this bounds the
#: rest, e.g. a path), its unprintable characters escaped.
LINE_CHARS = 4000

#: ``--retime`` stretches by time_scale × (1 + this): just enough that rounding in the written
#: times cannot leave the result a hair over a limit, while keeping the retimed motion fast.
RETIME_MARGIN = 0.01


@dataclass(frozen=True)
class FileVerdict:
    """One file's outcome: ``outcome`` is an :class:`~dyn_node.core.check.on_demand.CheckOutcome`, or None
    with ``error`` set when the file could not be read."""

    path: str
    trajectory: TrajectoryFile | None
    outcome: Any = None
    error: TrajectoryFileError | None = None
    seconds: float = 0.0

    @property
    def readable(self) -> bool:
        return self.error is None

    @property
    def feasible(self) -> bool:
        return self.outcome is not None and self.outcome.feasible


@dataclass
class Checker:
    """The model, settings and Dynamics every file is checked with (as a node configured so)."""

    model: Any
    settings: Any
    dynamics: Any
    source: str
    overrides: dict

    def check(self, tf: TrajectoryFile) -> Any:
        from dyn_node.core.check import on_demand

        return on_demand.check(self.dynamics, self.settings, tf.joint_names, tf.times, tf.positions,
                               tf.velocities, tf.accelerations)


def make_checker(*, robot_model: str = "", robot_description: str = "", limits: str = "",
                 params_file: str = "") -> Checker:
    """Build the model and settings; raises :class:`CheckError` when there is no usable model."""
    from dyn_node.audit.replay.config import parameters_from_yaml
    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.robot.model_source import build_model
    from dyn_node.core.robot.settings import SPECS, settings_from_mapping

    values: dict[str, Any] = {}
    overrides: dict[str, str] = {}
    if params_file:
        try:
            params = parameters_from_yaml(read_text(params_file, max_bytes=MAX_LIMITS_BYTES))
        except (FileProblem, LoadError) as exc:
            raise CheckError(f"{params_file}: {exc}", code="no_params") from None
        values.update({k: v for k, v in params.items() if k in SPECS})
        overrides["params_file"] = params_file
    if robot_description:
        if not Path(robot_description).is_file():
            raise CheckError(f"{robot_description}: robot description file does not exist", code="no_model")
        values.update(robot_description="", robot_description_file=robot_description, robot_model="")
        overrides["robot_description"] = robot_description
    elif robot_model:
        values.update(robot_description="", robot_description_file="", robot_model=robot_model)
        overrides["robot_model"] = robot_model
    if limits:
        if not Path(limits).exists():
            raise CheckError(f"{escape(limits, 500)}: limits file does not exist", code="no_limits")
        values["limits_file"] = limits
        overrides["limits"] = limits
    try:
        settings = settings_from_mapping(values)
    except DynNodeError as exc:
        raise CheckError(f"{params_file or 'options'}: {exc}", code="bad_parameter") from None
    if not settings.has_model_source:
        raise CheckError("no robot model: pass --robot-model NAME, --robot-description URDF, or a "
                         "--params-file that sets one", code="no_model")
    try:
        model = build_model(settings)
    except DynNodeError as exc:
        raise CheckError(f"robot model unusable: {exc}", code="no_model") from None
    source = ("robot_description_file" if settings.robot_description_file else
              "robot_model" if settings.robot_model else "robot_description")
    dyn = Dynamics(model, DynamicsOptions(include_friction=settings.include_friction))
    return Checker(model, settings, dyn, source, overrides)


def check_file(checker: Checker, path: str, *, max_bytes: int = MAX_TRAJECTORY_BYTES,
               max_points: int = MAX_POINTS) -> FileVerdict:
    t0 = time.perf_counter()
    try:
        tf = read_trajectory(path, max_bytes=max_bytes, max_points=max_points)
    except TrajectoryFileError as exc:
        return FileVerdict(path, None, error=exc)
    outcome = checker.check(tf)
    return FileVerdict(path, tf, outcome, seconds=time.perf_counter() - t0)


# --- output ----------------------------------------------------------------------------------------
def verdict_line(v: FileVerdict) -> str:
    """``FILE: FEASIBLE|INFEASIBLE|REJECTED|UNREADABLE ...`` (the node's message included)."""
    if v.error is not None:
        return f"{v.path}: UNREADABLE: {v.error}"
    o = v.outcome
    if o.result is None:
        return f"{v.path}: REJECTED: {o.statuses[0].message.removeprefix('rejected: ')}"
    r = o.result
    word = "FEASIBLE" if r.feasible else "INFEASIBLE"
    level = {0: "OK", 1: "WARN", 2: "ERROR"}.get(int(r.level), str(r.level))
    return f"{v.path}: {word} ({level}), time_scale {_g(r.time_scale)}: {r.message}"


def _g(x: float) -> str:
    return "inf" if x == math.inf else f"{x:.4g}"


def place_lines(v: FileVerdict) -> list[str]:
    """One row per task place (frame_limits link, robot_limits, base_limits, grasp) of a checked
    file: ``  <place>: <kind> <peak> of <limit> <unit> (<ratio>%) at t = <s> s; …`` (empty when
    no task kind is configured)."""
    from dyn_node.audit.evidence import task_kind_units

    r = v.outcome.result if v.outcome is not None else None
    per_frame = getattr(r, "per_frame", None) or {}
    units = task_kind_units()
    rows = []
    for place, kinds in per_frame.items():
        cells = []
        for kind, e in kinds.items():
            unit = e.get("unit", units.get(kind, ""))
            ratio = e.get("ratio")
            pct = "—" if ratio is None else ("inf" if ratio == math.inf else f"{ratio * 100:.0f}")
            t = e.get("time_s")
            at = f" at t = {t:.2f} s" if isinstance(t, float) and math.isfinite(t) else ""
            cells.append(f"{kind} {_g(e['value'])} of {_g(e['limit'])}{(' ' + unit) if unit else ''} "
                         f"({pct}%){at}")
        rows.append(f"  {place}: " + "; ".join(cells))
    return rows


def evidence_record(checker: Checker, v: FileVerdict, started_utc: str) -> dict:
    """The file's EvidenceRecord (kind ``check``), shaped like the audit's so its report renders."""
    from dyn_node.audit.evidence import EvidenceRecord, task_limits_key, utc_now
    from dyn_node.core.robot.units import joint_units

    model = checker.model
    rec = EvidenceRecord(kind="check", tool="dyn-check")
    rec.started_utc = started_utc
    tf, o = v.trajectory, v.outcome
    entry = _entry(v)
    duration = entry.get("duration_s") if isinstance(entry.get("duration_s"), float) else 0.0
    rec.inputs = {"bag": str(Path(v.path).resolve()), "files": [str(Path(v.path).resolve())],
                  "topics": [{"name": v.path, "type": "trajectory_msgs/msg/JointTrajectory",
                              "count": 1 if tf else 0, "role": "check_trajectory"}],
                  "message_counts": {v.path: 1 if tf else 0},
                  "time_span": {"start_ns": None, "end_ns": None, "duration_s": max(0.0, duration or 0.0)},
                  "format": tf.format if tf else None}
    rec.configuration = {
        "model": {"name": model.name, "source": checker.source, "urdf_sha256": model.urdf_hash,
                  "joint_names": list(model.joint_names), "dof": model.nv,
                  "total_mass_kg": model.total_mass, "payload_mass_kg": model.payload.mass,
                  "gravity_m_s2": list(model.gravity)},
        "limits": model.limits.to_dict(), **task_limits_key(model), "parameters": {},
        "settings_used": _settings_dict(checker), "overrides": dict(checker.overrides)}
    per_joint = []
    for j, name in enumerate(model.joint_names):
        e = o.result.per_joint[name]["effort"] if o is not None and o.result is not None else None
        per_joint.append({"joint": name, "unit": joint_units(model)["effort"][j],
                          "peak_utilisation": None if e is None else e["ratio"],
                          "peak_time_s": None if e is None else e["time_s"],
                          "peak_effort": None if e is None else e["value"], "peak_measured_effort": None,
                          "peak_source": None if e is None else "model",
                          "effort_limit": float(model.limits.effort[j])})
    rec.outputs = {"trajectories": [entry] if tf else [], "trajectories_total": 1 if tf else 0,
                   "trajectories_infeasible_or_rejected": 0 if v.feasible or not tf else 1,
                   "trajectory_counts": RequestTally.of_entries([entry] if tf else []).to_dict(),
                   "effort": {"per_joint": per_joint, "samples": 0}, "violations": [],
                   "controller_states": {}, "recheck": {}, "latency": {}}
    rec.input_quality = {
        "gaps": [], "stale_periods": [], "out_of_order": {"count": 0, "examples": []},
        "invalid_messages": {"count": 0 if v.readable else 1,
                             "by_reason": {} if v.readable else {"unreadable_file": 1},
                             "examples": [] if v.readable else [{"time_s": 0.0, "reason": str(v.error),
                                                                 "code": "unreadable_file"}]},
        "unreadable_ranges": [] if v.readable else [{"start_s": None, "end_s": None,
                                                     "reason": str(v.error), "file": v.path}]}
    if not v.readable:
        rec.add_label(STATE_ERROR)
    elif not v.feasible:
        rec.add_label(entry.get("failure_label") or PLANNING_ERROR)
    code = exit_code(violations=v.readable and not v.feasible, partial=False, unusable=not v.readable)
    result = "unusable" if not v.readable else ("feasible" if v.feasible else "violations")
    rec.verdict = {"result": result, "exit_code": code, "summary": verdict_line(v), "partial": False,
                   "findings": list(o.result.warnings) if o is not None and o.result is not None else []}
    rec.duration_s = v.seconds
    rec.finished_utc = utc_now()
    return rec.to_dict()


def _settings_dict(checker: Checker) -> dict:
    d = checker.settings.to_parameters()
    if d.get("robot_description"):
        d["robot_description"] = f"<URDF, {len(d['robot_description'])} chars>"
    return d


def _entry(v: FileVerdict) -> dict:
    """The trajectory entry of the record, with the audit's keys (and the waypoint torques)."""
    from dyn_node.audit.evidence import add_per_frame

    tf, o = v.trajectory, v.outcome
    entry: dict[str, Any] = {"index": 0, "request": CHECK, "topic": v.path, "time_s": 0.0,
                             "stamp_ns": tf.stamp_ns if tf else 0, "accepted": False, "feasible": False,
                             "failure_label": STATE_ERROR}
    if o is None:
        entry.update(level="ERROR", message=str(v.error), error_code="unreadable_file")
        return entry
    if o.result is None:
        s = o.statuses[0]
        entry.update(level="ERROR", message=s.message, error_code=o.error.code,
                     failure_label=o.error.failure_label, n_points=len(tf.times),
                     duration_s=s.values.get("duration_s", 0.0))
        return entry
    d = o.result.to_dict()
    entry.update(accepted=True, feasible=bool(o.result.feasible), error_code=None)
    for k in ("level", "message", "failure_label", "time_scale", "payload_margin_kg", "worst_joint",
              "worst_constraint", "worst_ratio", "first_violation_time_s", "n_points", "duration_s",
              "interpolation", "binding_joint", "binding_constraint", "violations", "per_joint", "waypoint_effort", "warnings"):
        entry[k] = d[k]
    add_per_frame(entry, o.result, curves=True, result_dict=d)
    entry["failure_label"] = entry["failure_label"] or None
    return entry


def write_evidence(checker: Checker, v: FileVerdict, out_dir: Path, started_utc: str) -> Path:
    import json

    from dyn_node.audit.check_report import write_check_report

    d = out_dir / Path(v.path).stem
    d.mkdir(parents=True, exist_ok=True)
    rec = evidence_record(checker, v, started_utc)
    (d / "evidence.json").write_text(json.dumps(rec, indent=1, ensure_ascii=False, allow_nan=False))
    write_check_report(rec, v, checker, d)  # the trajectory's own report, not the bag report
    return d


# --- retiming ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Retimed:
    """What ``--retime`` did with one file: ``written`` (path or None) and why."""

    path: str
    written: Path | None
    note: str
    factor: float = 1.0
    time_scale_after: float = math.nan


def retime(checker: Checker, v: FileVerdict, dest: Path) -> Retimed:
    """Write ``v``'s trajectory to ``dest`` as it must be timed to be feasible (see module doc)."""
    if v.trajectory is None or v.outcome is None:
        return Retimed(v.path, None, "not written: unreadable")
    r = v.outcome.result
    if r is None:
        return Retimed(v.path, None, f"not written: {v.outcome.statuses[0].message}")
    if r.feasible:
        dest.parent.mkdir(parents=True, exist_ok=True)
        if Path(v.path).resolve() != dest.resolve():
            shutil.copyfile(v.path, dest)
        return Retimed(v.path, dest, "feasible: written unchanged")
    if not math.isfinite(r.time_scale):
        return Retimed(v.path, None, f"not written: no slowdown makes it feasible ({r.message})",
                       factor=math.inf)
    factor = r.time_scale * (1.0 + RETIME_MARGIN)
    text = format_trajectory(v.trajectory.stretched(factor))
    again = checker.check(parse_trajectory(text, v.trajectory.format, str(dest)))
    if again.result is None or not again.result.feasible:
        msg = again.statuses[0].message
        return Retimed(v.path, None, f"not written: stretched × {factor:.6g} it is still not feasible "
                                     f"({msg})", factor=factor)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(text, encoding="utf-8")
    return Retimed(v.path, dest, f"stretched × {factor:.6g} (time_scale {r.time_scale:.6g} × "
                                 f"{1 + RETIME_MARGIN:g}); re-checked: time_scale now "
                                 f"{again.result.time_scale:.6g}", factor, again.result.time_scale)


def retime_destinations(paths: Sequence[str], out: str) -> list[Path]:
    """OUT itself for one input (a file, or a directory that exists); OUT/<name> for several."""
    o = Path(out)
    if len(paths) == 1 and not o.is_dir():
        return [o]
    names = [Path(p).name for p in paths]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CheckError(f"--retime {out}: several inputs are named {dup[0]}", code="bad_option")
    return [o / n for n in names]


# --- command -----------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dyn-check", description="Check trajectory files (YAML, JSON or CSV) for dynamic "
        "feasibility, as dyn_node checks joint_trajectory, with no ROS graph.",
        epilog="exit codes: " + "; ".join(f"{c} {MEANINGS[c]}" for c in (0, 1, 2)) + " (a file that "
               "cannot be read or parsed, or no usable model); with --retime the code is the "
               "retiming's: 0 every file's retiming written (an infeasible or rejected input "
               "included), 1 some file got none. "
               f"--retime-method uniform stretches by time_scale × {1 + RETIME_MARGIN:g}.")
    p.add_argument("trajectories", nargs="+", metavar="TRAJECTORY", help="trajectory files (.yaml, .yml, .json, .csv)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--robot-model", default="", metavar="NAME", help="built-in model (panda, ur5, planar_2link)")
    src.add_argument("--robot-description", default="", metavar="URDF", help="URDF file of the robot")
    p.add_argument("--limits", default="", metavar="FILE", help="joint limits YAML merged over the URDF limits")
    p.add_argument("--params-file", default="", metavar="YAML",
                   help="dyn_node parameters (as for --ros-args --params-file): payload, friction, "
                        "sample_period, effort_warn_ratio, locked_joints ...")
    p.add_argument("--out", default="", metavar="DIR", help="write DIR/<file stem>/evidence.json and report.html")
    p.add_argument("--retime", default="", metavar="OUT",
                   help="write each trajectory timed to be feasible (a file for one input, a directory for several)")
    p.add_argument("--retime-method", default="optimal", choices=("optimal", "uniform"),
                   help="optimal (default): the fastest timing along the same path that passes the "
                        "check (docs/retime.md); uniform: stretch by time_scale")
    p.add_argument("--max-file-mb", type=_positive(float), default=MAX_TRAJECTORY_BYTES / 1e6, metavar="MB",
                   help="refuse a trajectory file larger than this, unread (default: %(default)g MB)")
    p.add_argument("--max-points", type=_positive(int), default=MAX_POINTS, metavar="N",
                   help="refuse a trajectory of more points, before parsing it (default: %(default)d)")
    return p


def _positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not 0 < value < float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number > 0: {text!r}")
        return value
    return parse


def run(args: argparse.Namespace, out: Any = None) -> int:
    from dyn_node.audit.evidence import utc_now

    out = sys.stdout if out is None else out

    started = utc_now()
    checker = make_checker(robot_model=args.robot_model, robot_description=args.robot_description,
                           limits=args.limits, params_file=args.params_file)
    dests = retime_destinations(args.trajectories, args.retime) if args.retime else []
    verdicts, written = [], []
    for i, path in enumerate(args.trajectories):
        v = check_file(checker, path, max_bytes=int(args.max_file_mb * 1e6), max_points=args.max_points)
        verdicts.append(v)
        # an unreadable file's line is an error message: stderr, like every other error
        print(escape(verdict_line(v), LINE_CHARS), file=out if v.readable else sys.stderr, flush=True)
        for row in place_lines(v):
            print(row, file=out)
        if args.out:
            d = write_evidence(checker, v, Path(args.out), started)
            print(f"  evidence: {d / 'evidence.json'}, report: {d / 'report.html'}", file=out)
        if dests:
            written.append(_retime_one(checker, v, dests[i], args, out))
    # with --retime the code is the retiming's (docs/dyn-check.md, "exit code"): 1 when some
    # file got no feasible retiming (nothing written), 0 when each got one, whatever the input
    if dests:
        return exit_code(violations=not all(written), partial=False,
                         unusable=any(not v.readable for v in verdicts))
    return exit_code(violations=any(v.readable and not v.feasible for v in verdicts), partial=False,
                     unusable=any(not v.readable for v in verdicts))


def _retime_one(checker: Checker, v: FileVerdict, dest: Path, args: argparse.Namespace,
                out: Any) -> bool:
    """``--retime`` for one file (its line printed; the plot into ``--out``): written or not."""
    if args.retime_method == "uniform":
        rt = retime(checker, v, dest)
    else:
        from dyn_node.audit import retime_cli
        rt = retime_cli.retime_file(checker, v, dest)
        if args.out and rt.result is not None and rt.written:
            retime_cli.write_outputs(checker, rt, Path(args.out) / Path(v.path).stem)
    print(f"  retime: {rt.note}" + (f" → {rt.written}" if rt.written else ""), file=out)
    return rt.written is not None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except CheckError as exc:
        print(f"dyn-check: error: {escape(str(exc), LINE_CHARS)}", file=sys.stderr)
        return EXIT_UNUSABLE
    except OSError as exc:  # e.g. --out or --retime not writable
        print(f"dyn-check: error: {escape(str(exc), LINE_CHARS)}", file=sys.stderr)
        return EXIT_UNUSABLE
    except (OverflowError, RecursionError, MemoryError) as exc:  # input beyond what was bounded
        print(f"dyn-check: error: input too large or too deep: {type(exc).__name__}: "
              f"{escape(str(exc), 200)}", file=sys.stderr)
        return EXIT_UNUSABLE


if __name__ == "__main__":
    raise SystemExit(main())
