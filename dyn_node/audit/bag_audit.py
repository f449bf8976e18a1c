"""dyn-audit: replay a bag through the node's own core and write an EvidenceRecord and a report.

The bag is streamed (constant memory) through the same Monitor, ControllerTracker and
check_trajectory the node runs, and the node's recorded outputs are recomputed and compared.
Usage, outputs and exit codes: docs/audit.md; batch replay and configuration changes:
docs/BAGS.md.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import yaml

from dyn_node import __version__
from dyn_node.core.live.allocator import retain_freed_memory
from dyn_node.bag.reader import BagMessage, BagReader, MessageDecoder
from dyn_node.bag.metadata import LIMITS_SHA256_KEY, LIMITS_YAML_KEY
from dyn_node.bag.cdr import decode_joint_state, decode_joint_state_batch
from dyn_node.audit.accounting import EXECUTE, INVERSE_DYNAMICS, RequestTally, request_of_role
from dyn_node.audit.cli import add_audit_options, run_command
from dyn_node.errors import (CONTROL_ERROR, EVALUATION_ERROR, PLANNING_ERROR, STATE_ERROR, DynNodeError,
                     InputError, TrajectoryError)
from dyn_node.audit.evidence import (EvidenceRecord, add_per_frame, jsonable, task_limits_key,
                                     task_limits_section, utc_now)
from dyn_node.audit.replay_common import (MAX_PENDING, Pending, Recheck, SeriesBins, output_stamp_ns,
                                          worst_status_difference)
from dyn_node.audit.contact_replay import (CONTACT_ROLES, ContactRecheck, ContactReplay, contact_findings,
                                           contact_role, contact_section)
from dyn_node.core.robot.units import joint_units

from dyn_node.audit.gate_replay import ROLE_GATE, GateReplay, gate_role
from dyn_node.audit.service_replay import ROLE_SERVICE_EVENT, ServiceReplay, service_role
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS, exit_code  # noqa: F401

if TYPE_CHECKING:
    from dyn_node.core.robot.model_source import ModelCache

MAX_EPISODES = 1000      # violation episodes listed (the rest are counted)
MAX_EXAMPLES = 50        # invalid / out-of-order examples and gaps listed
MAX_TRAJECTORIES = 1000  # per-trajectory verdicts listed (the rest are counted)
MIN_BATCH = 16           # shorter runs of joint_states are replayed message by message
MAX_RUN = 2048           # joint_states replayed per batch (bounds memory)
MAX_CURVE_TRAJECTORIES = 50  # trajectory entries that carry per_frame_curves (≤ 400 points each)

ROLE_JOINT_STATES, ROLE_TRAJECTORY = "joint_states", "joint_trajectory"
ROLE_CHECK = "check_trajectory"  # ~/check_trajectory: checked like joint_trajectory, never tracked
ROLE_STATES = "inverse_dynamics_request"  # ~/inverse_dynamics_request: torques for given states
ROLE_GRAVITY, ROLE_ID, ROLE_FEAS = "gravity_torque", "inverse_dynamics", "feasibility"
ROLE_TRAJ_EFFORT, ROLE_CTRL, ROLE_DESC = "trajectory_effort", "controller_status", "robot_description"


class AuditError(DynNodeError):
    """The audit cannot run: unusable bag or no model."""

    failure_label = STATE_ERROR


@dataclass(frozen=True)
class AuditOptions:
    bag: str
    robot_description: str = ""     # URDF file path (overrides the bag)
    robot_model: str = ""           # built-in model name (overrides the bag)
    limits: str = ""                # limits YAML (overrides the bag's limits_file)
    out: str = "audit"
    topics: tuple[str, ...] = ()
    gap_threshold_s: float = 0.05
    progress: bool | None = None    # None: only when stderr is a terminal
    report: bool = True
    # models built earlier in this process (a fleet worker's); None (dyn-audit): built per bag
    model_cache: "ModelCache | None" = field(default=None, compare=False, repr=False)


@dataclass
class AuditResult:
    record: dict
    exit_code: int
    out_dir: Path
    files: list[Path] = field(default_factory=list)
    messages: int = 0
    wall_s: float = 0.0


# --- configuration from the bag ------------------------------------------------------------
def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(tree, dict):
        for k, v in tree.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if isinstance(v, dict):
                out.update(_flatten(v, key))
            else:
                out[key] = v
    return out


def parameters_from_yaml(text: str) -> dict[str, Any]:
    """Node parameters from a --params-file YAML (``{node: {ros__parameters: {...}}}``) or a flat
    mapping; nested keys are joined with '.'."""
    doc = yaml.safe_load(text) if text else None
    if not isinstance(doc, dict):
        return {}
    for v in doc.values():
        if isinstance(v, dict) and "ros__parameters" in v:
            return _flatten(v["ros__parameters"])
    if "ros__parameters" in doc:
        return _flatten(doc["ros__parameters"])
    return _flatten(doc)


def _role(topic: str, schema: str) -> str | None:
    contact = contact_role(topic, schema)  # ~/external_torque, ~/external_wrench, ~/observer_events
    if contact is not None:
        return contact
    if service_role(topic, schema) is not None:  # the question services' events
        return ROLE_SERVICE_EVENT
    if gate_role(topic, schema) is not None:  # the FollowJointTrajectory gate's decisions
        return ROLE_GATE
    last = topic.rstrip("/").rsplit("/", 1)[-1]
    if schema == "sensor_msgs/msg/JointState":
        if last == ROLE_GRAVITY:
            return ROLE_GRAVITY
        if last == ROLE_ID:
            return ROLE_ID
        return ROLE_JOINT_STATES if last == ROLE_JOINT_STATES else None
    if schema == "trajectory_msgs/msg/JointTrajectory":
        if last == ROLE_TRAJ_EFFORT:
            return ROLE_TRAJ_EFFORT
        return last if last in (ROLE_TRAJECTORY, ROLE_CHECK, ROLE_STATES) else None
    if schema == "diagnostic_msgs/msg/DiagnosticArray" and last == ROLE_FEAS:
        return ROLE_FEAS
    if schema == "diagnostic_msgs/msg/DiagnosticStatus" and last == ROLE_CTRL:
        return ROLE_CTRL
    if schema == "std_msgs/msg/String" and last == ROLE_DESC:
        return ROLE_DESC
    return None


# --- streaming aggregates (memory independent of bag length) -------------------------------
class LiveStats:
    """Time bins, per-joint peaks and violation episodes of the accepted joint states.

    Rows are buffered (references to the monitor's result arrays, which are never written after
    they are returned) and processed in vectorised batches; results equal a message-by-message
    update, including the order in which violation episodes close."""

    BATCH = 1024
    KINDS = ("effort", "position", "velocity", "deceleration")

    def __init__(self, nv: int, lo: np.ndarray, hi: np.ndarray, vel: np.ndarray,
                 dec: np.ndarray | None = None):
        # dec: deceleration limits, |q̈̂| where q̇·q̈̂ < 0 as the live monitor checks it
        self.nv, self.lo, self.hi, self.vel = nv, lo, hi, vel
        self.dec = np.full(nv, np.inf) if dec is None else dec
        self.series: SeriesBins | None = None
        self.episodes = Episodes()
        self.peak_util = np.full(nv, -np.inf)
        self.peak_t = np.zeros(nv, dtype=np.int64)
        self.peak_tau = np.zeros(nv)
        self.peak_meas = np.full(nv, np.nan)  # measured effort at the peak (NaN: not measured)
        self.peak_limit = np.full(nv, np.inf)
        self.rows: list[tuple] = []
        self._nan = np.full(nv, np.nan)

    def add(self, t_ns: int, tau, util, limit, q, v, measured, a_hat=None) -> None:
        rows = self.rows
        rows.append((t_ns, tau, util, limit, q, v, measured, a_hat))
        if len(rows) >= self.BATCH:
            self.flush()

    def flush(self) -> None:
        rows = self.rows
        n = len(rows)
        if not n:
            return
        self.rows = []
        nan = self._nan
        T = np.array([r[0] for r in rows], dtype=np.int64)
        TAU = np.array([r[1] for r in rows], dtype=float)
        UTIL = np.array([r[2] for r in rows], dtype=float)
        LIM = np.array([r[3] for r in rows], dtype=float)
        Q = np.array([r[4] for r in rows], dtype=float)
        V = np.array([r[5] for r in rows], dtype=float)
        MEAS = np.array([nan if r[6] is None else r[6] for r in rows], dtype=float)
        A = (np.array([np.zeros(self.nv) if r[7] is None else r[7] for r in rows], dtype=float)
             if np.isfinite(self.dec).any() else None)   # only a deceleration limit reads it
        self._rows(T, TAU, UTIL, LIM, Q, V, MEAS, A)

    def add_arrays(self, T, TAU, UTIL, LIM, Q, V, MEAS, A=None) -> None:
        """N rows of :meth:`add` at once ((N,) int64 log times ns, N×nv arrays; ``MEAS`` NaN
        where not measured; ``A`` the acceleration estimates, None: zero); the same result as
        N calls of :meth:`add`."""
        self.flush()
        self._rows(T, TAU, UTIL, np.ascontiguousarray(LIM), Q, V, MEAS, A)

    def _rows(self, T, TAU, UTIL, LIM, Q, V, MEAS, A) -> None:
        if self.series is None:
            self.series = SeriesBins(self.nv, int(T[0]))
        self.series.add_batch(T, TAU, UTIL, LIM, MEAS)
        k = np.argmax(UTIL, axis=0)  # first occurrence of each joint's batch maximum
        cols = np.arange(self.nv)
        best = UTIL[k, cols]
        better = best > self.peak_util
        if better.any():
            self.peak_util[better] = best[better]
            self.peak_t[better] = T[k[better]]
            self.peak_tau[better] = TAU[k[better], cols[better]]
            self.peak_meas[better] = MEAS[k[better], cols[better]]
            self.peak_limit[better] = LIM[k[better], cols[better]]
        over_e = UTIL > 1.0
        over_p = (Q < self.lo) | (Q > self.hi)
        AV = np.abs(V)
        over_v = AV > self.vel
        # decelerating (|q̇| decreasing) beyond the limit, as Monitor's limits status counts it
        if np.isfinite(self.dec).any() and A is not None:
            self._decel = np.where(V * A < 0, np.abs(A), 0.0)
            over_d = self._decel > self.dec
        else:
            self._decel, over_d = None, np.zeros(np.shape(Q), dtype=bool)
        # the |effort| behind each ratio where a limit is ≤ 0 (elsewhere it is ratio·limit)
        self._effort_value = np.fmax(np.abs(TAU), np.abs(MEAS)) if np.any(LIM <= 0) else None
        if self.episodes.open or over_e.any() or over_p.any() or over_v.any() or over_d.any():
            self._episodes(T, UTIL, LIM, Q, AV, (over_e, over_p, over_v, over_d))

    def _values(self, kind: int, r: int, j: int, UTIL, LIM, Q, AV) -> tuple[float, float, float]:
        """(value, limit, severity) of row r, joint j, as a message-by-message update has them."""
        lo, hi, vel = self.lo, self.hi, self.vel
        if kind == 0:
            u, lim = float(UTIL[r, j]), float(LIM[r, j])
            if lim <= 0 and self._effort_value is not None:
                # a zero (YAML) limit is a real one: u is inf, u·lim would be NaN
                return float(self._effort_value[r, j]), lim, u
            return u * lim, lim, u
        if kind == 1:
            qj = float(Q[r, j])
            below = qj < lo[j]
            return qj, float(lo[j] if below else hi[j]), float(lo[j] - qj if below else qj - hi[j])
        if kind == 3:
            d = float(self._decel[r, j])
            return d, float(self.dec[j]), d - float(self.dec[j])
        return float(AV[r, j]), float(vel[j]), float(AV[r, j] / vel[j])

    def _episodes(self, T, UTIL, LIM, Q, AV, overs) -> None:
        """Episodes of consecutive over-limit rows per (joint, kind), run by run.

        Equal to calling :meth:`Episodes.update` row by row, joint by joint, kind by kind: an
        episode's peak is its earliest sample of largest severity (a NaN first sample stays the
        peak, as ``>`` never replaces it), episodes close on the first row not over the limit, in
        (row, joint, kind) order, and episodes still open keep that order for :meth:`finish`."""
        ep = self.episodes
        n = len(T)
        with np.errstate(divide="ignore", invalid="ignore"):   # a zero (YAML) velocity limit
            sevs = (UTIL, np.where(Q < self.lo, self.lo - Q, Q - self.hi), AV / self.vel,
                    None if self._decel is None else self._decel - self.dec)
        closing: list[tuple[int, int, int, tuple[int, str] | None, dict]] = []
        opening: list[tuple[int, int, int, tuple[int, str], dict]] = []
        for kind_i, kind in enumerate(self.KINDS):
            OVER = overs[kind_i]
            SEV = sevs[kind_i]
            any_col = OVER.any(axis=0)
            for j in range(self.nv):
                key = (j, kind)
                cur = ep.open.get(key)
                if not any_col[j]:
                    if cur is not None:
                        closing.append((0, j, kind_i, key, cur))
                    continue
                o = OVER[:, j]
                starts = np.flatnonzero(np.r_[o[0], o[1:] & ~o[:-1]])
                ends = np.flatnonzero(np.r_[o[:-1] & ~o[1:], o[-1]])  # last row of each run
                sev = SEV[:, j]
                if cur is not None and starts[0] != 0:
                    closing.append((0, j, kind_i, key, cur))
                    cur = None
                for s, e in zip(starts.tolist(), ends.tolist()):
                    seg = sev[s:e + 1]
                    clean = np.where(np.isnan(seg), -np.inf, seg)
                    m = int(np.argmax(clean))
                    if cur is not None:  # the open episode continues from the last batch (s == 0)
                        d = cur
                        d["end"] = int(T[e])
                        d["n"] += e - s + 1
                        if clean[m] > d["sev"]:
                            value, limit, severity = self._values(kind_i, s + m, j, UTIL, LIM, Q, AV)
                            d["peak"], d["peak_t"], d["limit"], d["sev"] = value, int(T[s + m]), limit, severity
                        cur = None
                    else:
                        if math.isnan(seg[0]) or not clean[m] > clean[0]:
                            m = 0
                        value, limit, severity = self._values(kind_i, s + m, j, UTIL, LIM, Q, AV)
                        d = {"j": j, "kind": kind, "start": int(T[s]), "end": int(T[e]),
                             "peak_t": int(T[s + m]), "peak": value, "limit": limit, "n": e - s + 1,
                             "sev": severity}
                        if e == n - 1:
                            opening.append((s, j, kind_i, key, d))
                            continue
                        closing.append((e + 1, j, kind_i, None, d))
                        continue
                    if e != n - 1:
                        closing.append((e + 1, j, kind_i, key, d))
        closing.sort(key=lambda c: c[:3])
        for _r, _j, _k, key, d in closing:
            if key is not None:
                del ep.open[key]
            ep.total += 1
            if len(ep.closed) < MAX_EPISODES:
                ep.closed.append(d)
        opening.sort(key=lambda c: c[:3])
        for _r, _j, _k, key, d in opening:
            ep.open[key] = d

    def finish(self) -> None:
        self.flush()
        self.episodes.finish()


class Histogram:
    """Fixed log-spaced histogram for latency quantiles (1 µs … 100 s, 200 bins per decade)."""

    LO, DECADES, PER = 1e-6, 8, 200

    def __init__(self) -> None:
        self.bins = np.zeros(self.DECADES * self.PER + 2, dtype=np.int64)
        self.n, self.sum, self.min, self.max = 0, 0.0, math.inf, -math.inf

    def add(self, x: float) -> None:
        self.n += 1
        self.sum += x
        self.min = min(self.min, x)
        self.max = max(self.max, x)
        if x <= self.LO:
            self.bins[0] += 1
        else:
            k = int(math.log10(x / self.LO) * self.PER) + 1
            self.bins[min(k, len(self.bins) - 1)] += 1

    def quantile(self, q: float) -> float | None:
        if not self.n:
            return None
        k = int(np.searchsorted(np.cumsum(self.bins), q * self.n, side="left"))
        if k == 0:
            return max(self.min, 0.0) if self.min < self.LO else self.LO
        mid = self.LO * 10 ** ((k - 0.5) / self.PER)
        return float(min(max(mid, self.min), self.max))

    def to_dict(self) -> dict:
        if not self.n:
            return {"count": 0}
        return {"count": self.n, "min": self.min, "max": self.max, "mean": self.sum / self.n,
                "p50": self.quantile(0.5), "p95": self.quantile(0.95), "p99": self.quantile(0.99)}


class Episodes:
    """Consecutive-message violation episodes per (joint, kind)."""

    def __init__(self) -> None:
        self.open: dict[tuple[int, str], dict] = {}
        self.closed: list[dict] = []
        self.total = 0

    def update(self, j: int, kind: str, over: bool, t_ns: int, value: float, limit: float,
               severity: float = 0.0) -> None:
        """``severity`` orders samples within an episode (ratio or excess beyond the limit)."""
        key = (j, kind)
        ep = self.open.get(key)
        if over:
            if ep is None:
                self.open[key] = {"j": j, "kind": kind, "start": t_ns, "end": t_ns, "peak_t": t_ns,
                                  "peak": value, "limit": limit, "n": 1, "sev": severity}
            else:
                ep["end"] = t_ns
                ep["n"] += 1
                if severity > ep["sev"]:
                    ep["peak"], ep["peak_t"], ep["limit"], ep["sev"] = value, t_ns, limit, severity
        elif ep is not None:
            self._close(key)

    def _close(self, key: tuple[int, str]) -> None:
        ep = self.open.pop(key)
        self.total += 1
        if len(self.closed) < MAX_EPISODES:
            self.closed.append(ep)

    def finish(self) -> None:
        for key in list(self.open):
            self._close(key)


@dataclass
class _Config:
    """One configuration of the recording node, as replayed: from ``since_ns`` (log time; None:
    from the start) until the next one. ``not_comparable``: how it differs from the node's."""

    settings: Any
    model: Any
    parameters: dict
    since_ns: int | None
    not_comparable: list[str]


def recorded_limits(meta: dict, path: str, findings: list[str]) -> str:
    """The limits text a metadata record carries (the node's model was built from it); a
    finding when its sha256 does not match the record's or the file at ``path`` differs."""
    from dyn_node.core.robot.limits_file import limits_sha256

    text = meta[LIMITS_YAML_KEY]
    sha = limits_sha256(text)
    if meta.get(LIMITS_SHA256_KEY, sha) != sha:
        findings.append(f"the bag's limits text has sha256 {sha}, its record says "
                        f"{meta[LIMITS_SHA256_KEY]}: the text is used")
    try:
        disk = limits_sha256(Path(path).read_bytes()) if path else sha
    except OSError:  # moved or deleted since: the recorded text is all that is needed
        disk = sha
    if disk != sha:
        findings.append(f"the limits file {path} on this machine (sha256 {disk}) differs from the "
                        f"text the node read (sha256 {sha}): the bag's recorded text is used")
    return text


def limits_source(settings: Any, overrides: dict[str, Any], recorded: bool, missing: str) -> str:
    """Where the replayed limits come from, as the evidence's configuration.model names it."""
    if "limits" in overrides:
        return f"override:{overrides['limits']}"
    if recorded:
        return "bag:limits_yaml"
    if missing:
        return f"urdf ({missing} not recorded, not on this machine)"
    if settings.limits_file:
        return f"file:{settings.limits_file} (not recorded: older recorder)"
    return "urdf"


def task_limits_differences(recorded: Any, used: Any) -> list[str]:
    """The task sections (frame_limits, …, grasp) that differ between the two models' limits."""
    a, b = task_limits_section(recorded) or {}, task_limits_section(used) or {}
    changed = sorted(k for k in set(a) | set(b) if k != "unused_keys"
                     and jsonable(a.get(k)) != jsonable(b.get(k)))
    return ["task limits: " + ", ".join(changed)] if changed else []


def model_differences(recorded: Any, used: Any) -> list[str]:
    """What differs between the model the node used and the one the audit uses (empty: none)."""
    out = []
    rj, uj = list(recorded.joint_names), list(used.joint_names)
    if rj != uj:
        extra = [n for n in uj if n not in rj]
        gone = [n for n in rj if n not in uj]
        out.append(f"joints: {len(rj)} recorded, {len(uj)} here"
                   + (f" (here only: {', '.join(extra)})" if extra else "")
                   + (f" (recorded only: {', '.join(gone)})" if gone else ""))
    if dict(recorded.locked_joints) != dict(used.locked_joints):
        out.append(f"locked joints: recorded {', '.join(recorded.locked_joints) or 'none'}; "
                   f"here {', '.join(used.locked_joints) or 'none'}")
    if recorded.urdf_hash != used.urdf_hash:
        out.append(f"URDF: recorded sha256 {recorded.urdf_hash[:12]}, here {used.urdf_hash[:12]}")
    if rj == uj:  # limits are per joint: with other joints, every one differs
        a, b = recorded.limits.to_dict(), used.limits.to_dict()
        changed = sorted(k for k in set(a) | set(b) if jsonable(a.get(k)) != jsonable(b.get(k)))
        if changed:
            out.append("limits: " + ", ".join(changed))
    out += task_limits_differences(recorded, used)
    if recorded.payload.mass != used.payload.mass:
        out.append(f"payload mass: recorded {recorded.payload.mass:g} kg, here {used.payload.mass:g} kg")
    if list(recorded.gravity) != list(used.gravity):
        out.append("gravity")
    return out


# --- the audit ----------------------------------------------------------------------------
class Audit:
    """One pass over a bag, in stages: :meth:`read` (the bag and its configurations),
    :class:`Replay` (the inputs through the node's core), :class:`Rechecker` (the recorded outputs
    against the replayed ones), :func:`build_evidence`, :func:`add_verdict`. :meth:`run` chains
    them and returns the EvidenceRecord dict, the exit code and the plot series."""

    def __init__(self, opts: AuditOptions):
        self.opts = opts
        self.findings: list[str] = []
        self.decoder = MessageDecoder()

    # configuration -------------------------------------------------------------------------
    def _configure(self, reader: BagReader) -> None:
        """The configurations to replay: the first ``dyn_node`` metadata record's, then each
        later one from the log time it took effect (``effective_log_time_ns``)."""
        records = reader.metadata_records("dyn_node")
        if not records:
            # Every record damaged (reported as unreadable when streamed): its fields that still
            # decode are the only trace of the node's parameters; a description that does not
            # decode comes from the /robot_description copy instead.
            for good, bad in reader.damaged_metadata_records("dyn_node")[:1]:
                records = [good]
                self.findings.append("the dyn_node metadata record is damaged (not UTF-8: "
                                     + ", ".join(bad) + "): its other fields are used"
                                     + (", the description from /robot_description"
                                        if "robot_description" in bad else ""))
        meta = records[0] if records else {}
        self.bag_metadata_version = meta.get("version")
        topic_desc = ""
        if not meta.get("robot_description", ""):
            m = self._peek_description(reader)
            if m is not None:
                try:
                    topic_desc = self.decoder.decode(m.channel, m.data).data
                except Exception:  # noqa: BLE001 - an undecodable description is simply absent
                    topic_desc = ""
        first = self._resolve(meta, topic_desc, first=True)
        self.settings, self.model, self.parameters = first.settings, first.model, first.parameters
        self.configurations = [first] + self._changes(records[1:], meta, topic_desc, first)

    def _changes(self, records: list[dict], first_meta: dict, topic_desc: str,
                 first: "_Config") -> list["_Config"]:
        """Later configurations in the order they took effect. Each new ``effective_log_time_ns``
        is a core the node rebuilt (even for a value set to what it was: the monitor's state
        starts afresh); the same time again (a split file's copy, or parameters the node does not
        use) is the same core. A record without the time (older recorders) cannot be placed."""
        first_since = _effective_ns(first_meta)
        timed: dict[int, dict] = {}
        untimed = 0
        prev = first_meta
        for meta in records:
            keys = ("parameters", "robot_description", LIMITS_YAML_KEY)
            changed = tuple(map(meta.get, keys)) != tuple(map(prev.get, keys))
            prev = meta
            since = _effective_ns(meta)
            if since is None:
                untimed += changed
            elif since != first_since:
                timed[since] = meta  # the last record for a moment is the complete snapshot
        out: list[_Config] = []
        for since in sorted(timed):
            cfg = self._resolve(timed[since], topic_desc, first=False, since_ns=since)
            if cfg.model.joint_names != first.model.joint_names:
                first.not_comparable.append(f"the model's joints change at log time {since} ns "
                                            "(not replayed: the first configuration is kept)")
                self.findings.append(f"configuration at log time {since} ns changes the model's "
                                     "joints: not replayed")
                continue
            out.append(cfg)
        if untimed:
            first.not_comparable.append(f"{untimed} configuration change(s) recorded without the "
                                        "time they took effect (older recorder): not replayed")
            self.findings.append(f"{untimed} configuration change(s) in the bag carry no "
                                 "effective_log_time_ns: replayed with the first configuration")
        return out

    def _bag_settings(self, meta: dict, topic_desc: str, findings: list[str], *,
                      overrides_on: bool) -> tuple[Any, dict[str, Any], str, str | None]:
        """(settings, overrides applied, the bag's limits_file when it is not on this machine,
        the limits text the record carries) for one metadata record; ``overrides_on=False``:
        what the node itself used."""
        from dataclasses import replace

        from dyn_node.errors import SettingsError
        from dyn_node.core.robot.settings import SPECS, Settings, settings_from_mapping

        params = parameters_from_yaml(meta.get("parameters", ""))
        known = {k: v for k, v in params.items() if k in SPECS}
        try:
            settings = settings_from_mapping(known)
        except SettingsError as exc:
            findings.append(f"bag parameters rejected ({exc}); defaults used")
            settings = Settings()
        overrides: dict[str, Any] = {}
        desc_in_bag = meta.get("robot_description", "")
        if overrides_on and self.opts.robot_description:
            p = Path(self.opts.robot_description)
            if not p.is_file():
                raise AuditError(f"robot description file {p} does not exist", code="no_model")
            settings = replace(settings, robot_description=p.read_text(), robot_description_file="",
                               robot_model="")
            overrides["robot_description"] = str(p)
        elif overrides_on and self.opts.robot_model:
            settings = replace(settings, robot_description="", robot_description_file="",
                               robot_model=self.opts.robot_model)
            overrides["robot_model"] = self.opts.robot_model
        elif settings.robot_model and not settings.robot_description:
            # A built-in model ships with the package; check it is the one the bag recorded.
            from dyn_node.core.robot.model import BUILTIN_MODELS, builtin_urdf, urdf_hash

            name = settings.robot_model
            desc = desc_in_bag or topic_desc
            if name in BUILTIN_MODELS and desc and urdf_hash(builtin_urdf(name)) != urdf_hash(desc):
                findings.append(f"built-in model '{name}' differs from the description in the "
                                "bag: the bag's description is used")
                locks = dict(BUILTIN_MODELS[name][1])
                locks.update(dict(settings.locked_joints))
                settings = replace(settings, robot_description=desc, robot_model="",
                                   locked_joints=tuple(locks.items()))
        elif desc_in_bag or topic_desc:
            # The URDF the node was using travels in the bag: it wins over file paths that may not
            # exist on this machine.
            settings = replace(settings, robot_description=desc_in_bag or topic_desc,
                               robot_description_file="", robot_model="")
        missing = ""
        if overrides_on and self.opts.limits:
            if not Path(self.opts.limits).is_file():
                raise AuditError(f"limits file {self.opts.limits} does not exist", code="no_limits")
            settings = replace(settings, limits_file=self.opts.limits)
            overrides["limits"] = self.opts.limits
        elif LIMITS_YAML_KEY in meta:  # the text the node's model was built from
            return settings, overrides, missing, recorded_limits(meta, settings.limits_file, findings)
        elif settings.limits_file and not Path(settings.limits_file).is_file():
            findings.append(f"the bag's limits_file {settings.limits_file} is not on this "
                            "machine: URDF limits used (pass --limits)")
            missing = settings.limits_file
            settings = replace(settings, limits_file="")
        elif settings.limits_file:
            findings.append(f"the bag does not record the limits file's text (older recorder): "
                            f"{settings.limits_file} as it is on this machine is used")
        return settings, overrides, missing, None

    def _resolve(self, meta: dict, topic_desc: str, *, first: bool,
                 since_ns: int | None = None) -> "_Config":
        """The configuration of one metadata record, and how it differs from the node's."""
        from dyn_node.core.robot.model_source import build_model

        findings: list[str] = []
        settings, overrides, missing, limits = self._bag_settings(meta, topic_desc, findings,
                                                                  overrides_on=True)
        if not settings.has_model_source:
            raise AuditError("no robot model: the bag has no robot description (no dyn_node "
                             "metadata, no /robot_description); pass --robot-model or "
                             "--robot-description", code="no_model")
        try:
            model = build_model(settings, cache=self.opts.model_cache, limits_yaml=limits)
        except DynNodeError as exc:
            raise AuditError(f"robot model unusable: {exc}", code="no_model") from None
        differs: list[str] = []
        if missing and not overrides.get("limits"):
            differs.append(f"limits: the node read {missing}, which is not on this machine "
                           "(URDF limits used here)")
        if overrides:
            node_settings, _, node_missing, node_limits = self._bag_settings(
                meta, topic_desc, [], overrides_on=False)
            if node_settings.has_model_source and not node_missing:
                try:
                    differs += model_differences(build_model(
                        node_settings, cache=self.opts.model_cache, limits_yaml=node_limits), model)
                except DynNodeError as exc:
                    differs.append(f"the recorded model cannot be rebuilt here ({exc})")
        for f in findings:
            if f not in self.findings:
                self.findings.append(f)
        cfg = _Config(settings, model, parameters_from_yaml(meta.get("parameters", "")), since_ns,
                      differs)
        if first:
            self.overrides = overrides
            desc_in_bag = meta.get("robot_description", "")
            if "robot_description" in overrides or "robot_model" in overrides:
                self.model_source = "override:" + ("robot_description" if "robot_description" in overrides
                                                   else "robot_model")
            elif settings.robot_description and settings.robot_description in (desc_in_bag, topic_desc):
                self.model_source = "bag:metadata" if settings.robot_description == desc_in_bag else "bag:topic"
            else:
                self.model_source = "bag:parameters"
            self.limits_source = limits_source(settings, overrides, limits is not None, missing)
        return cfg

    def _peek_description(self, reader: BagReader) -> BagMessage | None:
        for topic in ("/robot_description", "robot_description"):
            m = reader.peek_first(topic)
            if m is not None:
                return m
        return None

    # the stages ----------------------------------------------------------------------------
    def read(self) -> "AuditSource":
        """Stage 1: open the bag and resolve the configurations to replay under."""
        reader = open_bag(self.opts.bag)
        self._configure(reader)
        return AuditSource(reader, self.configurations, self.overrides, self.model_source,
                           self.bag_metadata_version, self.findings, self.limits_source)

    def run(self) -> tuple[dict, int, "SeriesBins | None"]:
        """read → replay (with the re-check of the recorded outputs alongside) → evidence →
        verdict; returns the EvidenceRecord dict, the exit code and the plot series."""
        opts = self.opts
        started = utc_now()
        wall0 = time.perf_counter()
        source = self.read()
        reader = source.reader
        recheck = Rechecker(reader.known_topics(), self.decoder)
        replay = Replay(source.configurations, gap_threshold_s=opts.gap_threshold_s,
                        decoder=self.decoder, sink=recheck)
        if source.model_source == "bag:topic" and len(source.configurations) > 1:
            replay.contact.without_model()  # the node's first core came with a later configuration
        roles = Roles(opts.topics)
        self.n_msgs = stream(reader, roles, replay, recheck, _Progress(reader, opts.progress))
        result = replay.finish()
        self.settings, self.model = result.settings, result.model
        self.contact_series = result.contact.series if result.contact is not None else None
        require_inputs(opts.bag, reader, result, source.first.model)
        rec = build_evidence(opts, source, roles, result, recheck.result())
        rec.started_utc = started
        code = add_verdict(rec, source, result, gap_threshold_s=opts.gap_threshold_s)
        rec.duration_s = time.perf_counter() - wall0
        rec.finished_utc = utc_now()
        return rec.to_dict(), code, result.live.series


# --- stage 1: read ------------------------------------------------------------------------
@dataclass
class AuditSource:
    """The bag and how its node was configured: the first configuration, then each change."""

    reader: BagReader
    configurations: list[_Config]
    overrides: dict[str, Any]
    model_source: str
    bag_metadata_version: Any
    findings: list[str]  # shared with the later stages, which append theirs
    limits_source: str = ""  # where the first configuration's limits came from (limits_source)

    @property
    def first(self) -> _Config:
        return self.configurations[0]


def open_bag(bag: str) -> BagReader:
    """A streaming reader of the bag; AuditError when none of its files is an MCAP file."""
    reader = BagReader(bag, topics=None)
    bad = []
    for f in reader.files:
        with open(f, "rb") as fh:
            if fh.read(8) != b"\x89MCAP0\r\n":
                bad.append(f.name)
    if len(bad) == len(reader.files):
        raise AuditError(f"bag {bag} is unreadable: {', '.join(bad)} is not an MCAP file",
                         code="bag_unreadable")
    return reader


class Roles:
    """Each topic's role (by type and name; None: not used), restricted to ``wanted`` if given."""

    def __init__(self, wanted: Sequence[str] = ()):
        self.wanted = set(wanted)
        self.seen: dict[str, str | None] = {}

    def of(self, m: BagMessage) -> str | None:
        role = self.seen.get(m.topic, "?")
        if role == "?":
            role = _role(m.topic, m.channel.schema_name)
            if self.wanted and m.topic not in self.wanted:
                role = None
            self.seen[m.topic] = role
        return role


def stream(reader: BagReader, roles: Roles, replay: "Replay", recheck: "Rechecker | None",
           progress: "_Progress | None" = None) -> int:
    """Every message of the bag in file order to the stage that takes its role; the number of
    messages read. The replay goes first: it answers an output's input before the output."""
    n_msgs = 0
    for m in reader.messages():
        n_msgs += 1
        if progress is not None and n_msgs & 1023 == 0:
            progress.update(n_msgs)
        role = roles.of(m)
        if role is None:
            continue
        if replay.feed(role, m) or recheck is None:
            continue
        recheck.output(role, m, replay.model)
    if progress is not None:
        progress.done(n_msgs)
    return n_msgs


# --- stage 2: replay ----------------------------------------------------------------------
class Capped:
    """A count, and the first ``cap`` items for the record."""

    def __init__(self, cap: int):
        self.cap = cap
        self.items: list[dict] = []
        self.total = 0

    def add(self, item: dict) -> None:
        self.total += 1
        if len(self.items) < self.cap:
            self.items.append(item)


class ControllerTimeline:
    """The replayed controller states: transitions (the first MAX_EPISODES), time in each state,
    and the states the node recorded on ~/controller_status (informational)."""

    def __init__(self) -> None:
        self.transitions: list[dict] = []
        self.time_in_state: dict[str, float] = {}
        self.last: tuple[str, int] | None = None
        self.recorded: dict[str, int] = {}

    def enter(self, state: str, t_ns: int) -> None:
        self.close(t_ns)
        self.last = (state, t_ns)
        if len(self.transitions) < MAX_EPISODES:
            self.transitions.append({"t_ns": t_ns, "state": state})

    def close(self, t_ns: int | None) -> None:
        """The time in the current state until ``t_ns``."""
        if self.last is not None and t_ns is not None:
            st, since = self.last
            self.time_in_state[st] = self.time_in_state.get(st, 0.0) + (t_ns - since) * 1e-9


@dataclass
class ReplayResult:
    """What replaying the inputs gave: the live statistics, the input quality, the trajectory
    verdicts and the controller timeline, under the last configuration replayed."""

    live: LiveStats
    counts: Any                 # Monitor counts, carried across configurations as in the node
    model: Any                  # the last configuration's model and settings
    settings: Any
    js_topics: set[str]
    last_log_ns: int | None     # latest joint_states log time
    gaps: Capped
    stale: Capped
    invalid: Capped
    invalid_by_reason: dict[str, int]
    out_of_order: list[dict]
    trajectories: Capped
    trajectories_bad: int       # executed trajectories infeasible or rejected
    trajectory_failure_labels: set[str]
    controller: ControllerTimeline
    contact: Any = None         # audit.contact_replay.ContactResult
    tally: RequestTally = field(default_factory=RequestTally)  # executed vs questions, exact
    questions: dict = field(default_factory=dict)  # service questions answered, per service


class Replay:
    """Stage 2: joint_states through the node's Monitor and ControllerTracker, trajectories
    through check_trajectory, a new core from each configuration change on. The values the node
    would have published go to ``sink`` (the re-check; None: not kept)."""

    def __init__(self, configurations: Sequence[_Config], *, gap_threshold_s: float = 0.05,
                 decoder: MessageDecoder | None = None, sink: "Rechecker | None" = None):
        first = configurations[0]
        self.changes = list(configurations[1:])
        lim = first.model.limits
        self.live = LiveStats(first.model.nv, lim.position_lower, lim.position_upper, lim.velocity,
                              lim.deceleration)
        self.monitor: Any = None
        self.tracker: Any = None
        self.contact: ContactReplay | None = None
        self._use(first)
        self.decoder = decoder or MessageDecoder()
        self.sink = sink
        self.gap_ns = gap_threshold_s * 1e9
        # (model, log time ns, q, q̇) of the last accepted joint_states: a trajectory whose first
        # point lies ahead starts from it, as in the node (feasibility.current_state)
        self.last_state: tuple[Any, int, np.ndarray, np.ndarray] | None = None
        self.prev_log: int | None = None
        self.js_topics: set[str] = set()
        self.gaps, self.stale, self.invalid = Capped(MAX_EXAMPLES), Capped(MAX_EXAMPLES), Capped(MAX_EXAMPLES)
        self.invalid_by_reason: dict[str, int] = {}
        self.out_of_order: list[dict] = []
        self.trajectories = Capped(MAX_TRAJECTORIES)
        self.trajectories_bad = 0
        self.tally = RequestTally()
        self.trajectory_failure_labels: set[str] = set()
        self.controller = ControllerTimeline()
        # Consecutive joint_states of one topic with one byte layout and no gap are queued as a
        # run and replayed in one batch (decoded at once, Monitor.process_batch); anything else,
        # and any run the batch path declines, goes message by message. Both give the same numbers.
        self._run_topic, self._run_len, self._run_t, self._run_d = "", -1, [], []
        self.contact = ContactReplay(first, self.monitor.dynamics, sink=sink.contact if sink is not None else None)
        # the question services' request/response pairs, counted in the same tally
        self.services = ServiceReplay(sink, tally=self.tally)
        self.gates = GateReplay(sink)  # the gate's decisions, decided again

    def feed(self, role: str, m: BagMessage) -> bool:
        """Replay one message; False when its role is not an input (a recorded output)."""
        t_ns = m.log_time_ns
        if self.changes and t_ns >= self.changes[0].since_ns:
            self.flush()  # the queued joint_states were taken under the configuration before
            while self.changes and t_ns >= self.changes[0].since_ns:
                cfg = self.changes.pop(0)
            self._switch(cfg)
        if role == ROLE_JOINT_STATES:
            self._queue(m.topic, t_ns, m.data)
            return True
        self.flush()
        if role in (ROLE_TRAJECTORY, ROLE_CHECK):
            self._trajectory_request(role, m)
        elif role == ROLE_STATES:
            self._states_request(m)
        elif role == ROLE_SERVICE_EVENT:
            self.services.feed(m, self.decoder, self.traj_dynamics, self.settings)
        elif role == ROLE_GATE:
            self.gates.feed(m, self.decoder, self.traj_dynamics, self.settings)
        elif role == ROLE_CTRL:
            self._recorded_status(m)
        elif role in CONTACT_ROLES:
            self.contact.recorded_output(role, m, self.decoder)
            return False  # a recorded output: the re-check compares it
        else:
            return False
        return True

    def finish(self) -> ReplayResult:
        self.flush()
        self.live.finish()
        self.controller.close(self.prev_log)
        return ReplayResult(self.live, self.monitor.counts, self.model, self.settings,
                            self.js_topics, self.prev_log, self.gaps, self.stale, self.invalid,
                            self.invalid_by_reason, self.out_of_order, self.trajectories,
                            self.trajectories_bad, self.trajectory_failure_labels, self.controller,
                            contact=self.contact.finish(), tally=self.tally,
                            questions={**self.services.finish(), **self.gates.finish()})

    def _switch(self, cfg: _Config) -> None:
        """What the node does when a parameter is set: a new core from now on."""
        self.live.flush()
        self._use(cfg)

    def _use(self, cfg: _Config) -> None:
        """A core (monitor, tracker, dynamics, live limits) for ``cfg``; a previous core's
        counts and the plan it was tracking carry over."""
        from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
        from dyn_node.core.live.monitor import Monitor
        from dyn_node.core.live.tracker import ControllerTracker

        self.settings, self.model = cfg.settings, cfg.model
        self.monitor = Monitor(cfg.model, cfg.settings,
                               self.monitor.counts if self.monitor is not None else None)
        tracker = ControllerTracker(cfg.model, cfg.settings)
        if self.tracker is not None:
            tracker._plan = self.tracker._plan
        self.tracker = tracker
        self.traj_dynamics = Dynamics(cfg.model, DynamicsOptions(
            include_friction=cfg.settings.include_friction))
        cl = cfg.model.limits
        live = self.live
        live.lo, live.hi, live.vel = cl.position_lower, cl.position_upper, cl.velocity
        live.dec = cl.deceleration
        if self.contact is not None:
            self.contact.use(cfg, self.monitor.dynamics)

    # joint_states --------------------------------------------------------------------------
    def _queue(self, topic: str, t_ns: int, data: bytes) -> None:
        run_t = self._run_t
        if (topic == self._run_topic and len(data) == self._run_len and self._run_d
                and 0 <= t_ns - run_t[-1] <= self.gap_ns and len(self._run_d) < MAX_RUN):
            run_t.append(t_ns)
            self._run_d.append(data)
            return
        self.flush()
        self._gap_check(topic, t_ns)
        self._run_topic, self._run_len, self._run_t, self._run_d = topic, len(data), [t_ns], [data]

    def flush(self) -> None:
        """Replay the queued run of joint_states: in one batch, or message by message."""
        if not self._run_d:
            return
        ts, datas = self._run_t, self._run_d
        self._run_t, self._run_d = [], []
        if len(datas) < MIN_BATCH or not self._js_batch(ts, datas):
            for t, d in zip(ts, datas):
                self._js_one(self._run_topic, t, d)
        self.prev_log = max(self.prev_log, ts[-1])

    def _gap_check(self, topic: str, t_ns: int) -> None:
        self.js_topics.add(topic)
        prev_log = self.prev_log
        if prev_log is not None and t_ns - prev_log > self.gap_ns:
            g = {"start_ns": prev_log, "end_ns": t_ns}
            # nothing is known about the limits during a gap: a violation episode ends at
            # its last sample before it, and one after it is a new episode
            self.live.finish()
            self.gaps.add(g)
            if t_ns - prev_log > self.settings.stale_timeout * 1e9:
                self.stale.add(g)
                # The node's controller-status timer sees the silence: stale just after
                # stale_timeout (its timer period is not replayed).
                stale_ns = prev_log + int(self.settings.stale_timeout * 1e9) + 1000
                if self.tracker.tick(stale_ns * 1e-9):
                    self.controller.enter(self.tracker.state, stale_ns)
        self.prev_log = t_ns if prev_log is None or t_ns > prev_log else prev_log

    def _js_one(self, topic: str, t_ns: int, data: bytes) -> None:
        receipt_s = t_ns * 1e-9
        try:
            js = decode_joint_state(data)
        except ValueError as exc:  # counted and tracked as the node does (Monitor.reject_message)
            r = self.monitor.reject_message(InputError(str(exc), code="undecodable"), receipt_s)
        else:
            stamp_s = js.sec + js.nanosec * 1e-9
            r = self.monitor.process(js.names, js.position, js.velocity, js.effort, stamp_s, receipt_s)
        if self.tracker.update(r, receipt_s) or self.controller.last is None:
            self.controller.enter(self.tracker.state, t_ns)
        if not r.accepted:
            code = r.error.code
            self.invalid_by_reason[code] = self.invalid_by_reason.get(code, 0) + 1
            self.invalid.add({"t_ns": t_ns, "reason": str(r.error), "code": code, "topic": topic})
            return
        self.last_state = (self.model, t_ns, r.q, r.v)
        if r.out_of_order and len(self.out_of_order) < MAX_EXAMPLES:
            self.out_of_order.append({"t_ns": t_ns, "stamp_ns": js.stamp_ns})
        if self.sink is not None:
            stamp_key = output_stamp_ns(r.stamp_s) if r.zero_stamp else js.stamp_ns
            self.sink.expect_state(stamp_key, t_ns, r.gravity, r.tau)
        tau = r.tau
        self.contact.sample_result(t_ns, js, r, self.monitor.last_inputs)
        self.live.add(t_ns, tau, r.utilisation, r.effort_limit, r.q, r.v,
                      None if r.residual is None else r.residual + tau, r.a_hat)

    def _js_batch(self, ts: list[int], datas: list[bytes]) -> bool:
        jb = decode_joint_state_batch(datas)
        if jb is None or jb.position is None:
            return False
        stamp_s = jb.sec.astype(float) + jb.nanosec.astype(float) * 1e-9
        T = np.array(ts, dtype=np.int64)
        receipt = T.astype(float) * 1e-9
        b = self.monitor.process_batch(jb.names, jb.position, jb.velocity, jb.effort, stamp_s, receipt)
        if b is None:
            return False
        self.last_state = (self.model, ts[-1], b.q[-1], b.v[-1])  # every row was accepted
        before = self.tracker.state
        changes = self.tracker.update_batch(b, receipt)
        if self.controller.last is None and (not changes or changes[0][0] != 0):
            changes.insert(0, (0, before))  # row 0 left the state as it was
        for k, st in changes:
            self.controller.enter(st, ts[k])
        ooo = self.out_of_order
        if len(ooo) < MAX_EXAMPLES and b.out_of_order.any():
            for k in np.flatnonzero(b.out_of_order)[:MAX_EXAMPLES - len(ooo)].tolist():
                ooo.append({"t_ns": ts[k], "stamp_ns": int(jb.stamp_ns[k])})
        if self.sink is not None and self.sink.wants_states:
            keys = jb.stamp_ns.tolist()
            for k in np.flatnonzero(b.zero_stamp).tolist():
                keys[k] = output_stamp_ns(float(b.stamp_s[k]))
            for k, key in enumerate(keys):
                self.sink.expect_state(key, ts[k], b.gravity[k], b.tau[k])
        meas = (b.residual + b.tau if b.residual is not None
                else np.full(b.tau.shape, np.nan))
        self.contact.sample_batch(ts, jb, b)
        self.live.add_arrays(T, b.tau, b.utilisation, b.effort_limit, b.q, b.v, meas, b.a_hat)
        return True

    # trajectories and requests -------------------------------------------------------------
    def _trajectory_request(self, role: str, m: BagMessage) -> None:
        entry, ok_traj, res = self._trajectory(m, self.trajectories.total)
        entry["request"] = request_of_role(role)
        execute = entry["request"] == EXECUTE
        self.tally.add(entry["request"], answered_yes=entry["feasible"])
        # a check-only request is a question: its "no" is listed, not a violation of the run
        if entry.get("failure_label") and execute:
            self.trajectory_failure_labels.add(entry["failure_label"])
        if not entry["feasible"] and execute:
            self.trajectories_bad += 1
        self.trajectories.add(entry)
        if ok_traj is not None and execute:
            start = entry["stamp_ns"] * 1e-9 if entry["stamp_ns"] else m.log_time_ns * 1e-9
            self.tracker.set_trajectory(ok_traj, start)
        if self.sink is not None:
            # answers are matched by the whole header the node echoes (stamp and frame_id)
            key = (entry["stamp_ns"], entry.get("frame_id", ""))
            self.sink.expect_verdict(key, res if res is not None else entry)
            if res is not None:
                self.sink.expect_efforts(key, res.waypoint_effort)

    def _trajectory(self, m: BagMessage, index: int):
        from dyn_node.core.check.feasibility import NO_CURRENT_STATE, FeasibilityOptions, check_trajectory, current_state
        from dyn_node.core.check.trajectory import validate_trajectory

        entry: dict[str, Any] = {"index": index, "topic": m.topic, "time_s": 0.0, "t_ns": m.log_time_ns,
                                 "stamp_ns": 0, "accepted": False, "feasible": False}
        n_points = 0
        traj = None
        try:
            msg = self.decoder.decode(m.channel, m.data)
            st = msg.header.stamp
            entry["stamp_ns"] = int(st.sec) * 1_000_000_000 + int(st.nanosec)
            entry["frame_id"] = msg.header.frame_id
            pts = msg.points
            n_points = len(pts)
            # as the node does (ros_convert.trajectory_arrays, DynNode._check_trajectory): a
            # single point is tracked but not checked
            times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
            args = (self.model.joint_names, list(msg.joint_names), times, [p.positions for p in pts],
                    [p.velocities for p in pts], [p.accelerations for p in pts])
            # the effort lists only validated (joint_trajectory_controller's rule), as the node does
            traj = validate_trajectory(*args, min_points=1, efforts=[p.effort for p in pts])
            if traj.n_points < 2:
                validate_trajectory(*args, min_points=2)
        except TrajectoryError as exc:
            dur = float(times[-1]) if times and all(map(math.isfinite, times)) else 0.0
            entry.update(level="ERROR", message=f"rejected: {exc}", error_code=exc.code,
                         failure_label=PLANNING_ERROR, n_points=n_points, duration_s=dur)
            return entry, traj, None
        except Exception as exc:  # noqa: BLE001 - undecodable bytes are a finding, not a crash
            entry.update(level="ERROR", message=f"undecodable trajectory message: {exc}",
                         error_code="undecodable", failure_label=STATE_ERROR)
            return entry, None, None
        last, start = self.last_state, None
        if last is not None and last[0].joint_names == self.model.joint_names:
            start = current_state(last[1:], m.log_time_ns, self.settings.stale_timeout)
        try:
            res = check_trajectory(self.traj_dynamics, traj,
                                   FeasibilityOptions(sample_period=self.settings.sample_period,
                                                      effort_warn_ratio=self.settings.effort_warn_ratio),
                                   start=start, start_unknown=NO_CURRENT_STATE)
        except TrajectoryError as exc:  # e.g. torques that overflow: the node publishes "rejected"
            entry.update(level="ERROR", message=f"rejected: {exc}", error_code=exc.code,
                         failure_label=PLANNING_ERROR, n_points=n_points,
                         duration_s=float(times[-1]))
            return entry, traj, None
        return _verdict_entry(entry, res), traj, res

    def _states_request(self, m: BagMessage) -> None:
        """Recompute the node's answer to an ~/inverse_dynamics_request (torques, or the rejected
        verdict), keyed by the request's header like the node's answer."""
        from dyn_node.core.check import on_demand

        try:
            msg = self.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001 - undecodable: the node could not answer it either
            return
        st = msg.header.stamp
        key = (int(st.sec) * 1_000_000_000 + int(st.nanosec), msg.header.frame_id)
        pts = msg.points
        try:
            Q, V, A = on_demand.states(self.model.joint_names, list(msg.joint_names),
                                       [p.positions for p in pts], [p.velocities for p in pts],
                                       [p.accelerations for p in pts])
            tau = on_demand.inverse_dynamics(self.traj_dynamics, Q, V, A)
        except TrajectoryError as exc:
            self.tally.add(INVERSE_DYNAMICS, answered_yes=False)
            if self.sink is not None:
                self.sink.expect_verdict(key, {"message": f"rejected: {exc}", "error_code": exc.code,
                                               "n_points": len(pts), "duration_s": math.nan})
            return
        self.tally.add(INVERSE_DYNAMICS, answered_yes=True)
        if self.sink is not None:
            self.sink.expect_efforts(key, tau)

    def _recorded_status(self, m: BagMessage) -> None:
        try:
            st = self.decoder.decode(m.channel, m.data)
            state = next((kv.value for kv in st.values if kv.key == "state"), None)
            if state:
                rec = self.controller.recorded
                rec[state] = rec.get(state, 0) + 1
        except Exception:  # noqa: BLE001 - recorded status is informational only
            pass


def _verdict_entry(entry: dict[str, Any], res: Any) -> dict[str, Any]:
    """The trajectory's entry in the record, completed from its FeasibilityResult."""
    d = res.to_dict()
    entry.update(accepted=True, feasible=bool(res.feasible), error_code=None)
    for k in ("level", "message", "failure_label", "time_scale", "payload_margin_kg", "worst_joint",
              "worst_constraint", "worst_ratio", "first_violation_time_s", "n_points", "duration_s",
              "interpolation", "binding_joint", "binding_constraint", "start_segment", "start_state_age_s"):
        if k in d:
            entry[k] = d[k]
    entry["failure_label"] = entry.get("failure_label") or None  # "" (feasible) → null
    if "violations" in d:
        entry["violations"] = d["violations"][:50] if isinstance(d["violations"], list) else d["violations"]
    if "per_joint" in d:
        entry["per_joint"] = d["per_joint"]
    # curves for the report's plot; only the first trajectories', to keep the record small
    add_per_frame(entry, res, curves=entry["index"] < MAX_CURVE_TRAJECTORIES, result_dict=d)
    if not isinstance(entry.get("level"), str):
        from dyn_node.core.robot.status import LEVEL_NAMES
        entry["level"] = LEVEL_NAMES.get(entry.get("level"), str(entry.get("level")))
    return entry


# --- stage 3: re-check --------------------------------------------------------------------
OUTPUT_ROLES = (ROLE_GRAVITY, ROLE_ID, ROLE_FEAS, ROLE_TRAJ_EFFORT)


@dataclass
class RecheckResult:
    """Per output role: the comparison, the recomputed values never answered, the topic; and
    the latency of the recorded gravity_torque (from the input's stamp, from its receipt)."""

    checks: dict[str, Recheck]
    unanswered: dict[str, int]
    topics: dict[str, str]
    latency_stamp: Histogram
    latency_receipt: Histogram


class Rechecker:
    """Stage 3: the node's recorded outputs against what the replay recomputed for the same
    input (matched by header stamp). Recomputed values are kept only for the output roles whose
    topics the bag may hold (``known_topics``; None: unknown, all kept)."""

    def __init__(self, known_topics: Any = None, decoder: MessageDecoder | None = None):
        self.want = {r: known_topics is None
                     or any(t.rstrip("/").rsplit("/", 1)[-1] == r for t in known_topics)
                     for r in OUTPUT_ROLES}
        self.decoder = decoder or MessageDecoder()
        self.pending = {r: Pending() for r in OUTPUT_ROLES}
        self.checks = {r: Recheck() for r in OUTPUT_ROLES}
        self.topics: dict[str, str] = {}
        self.lat_stamp, self.lat_receipt = Histogram(), Histogram()
        self.input_log: OrderedDict[int, int] = OrderedDict()  # stamp → input log time (for latency)
        self.known_topics = known_topics
        self.contact = ContactRecheck(self)  # its roles join want/pending/checks above

    # what the replay recomputed ------------------------------------------------------------
    @property
    def wants_states(self) -> bool:
        return self.want[ROLE_GRAVITY] or self.want[ROLE_ID]

    def expect_state(self, key: int, t_ns: int, gravity: np.ndarray, tau: np.ndarray) -> None:
        if self.want[ROLE_GRAVITY]:
            self.pending[ROLE_GRAVITY].put(key, gravity)
            self.input_log[key] = t_ns
            if len(self.input_log) > MAX_PENDING:
                self.input_log.popitem(last=False)
        if self.want[ROLE_ID]:
            self.pending[ROLE_ID].put(key, tau)

    def expect_verdict(self, key: tuple[int, str], value: Any) -> None:
        """A FeasibilityResult, or the rejected entry, for a ~/feasibility answer."""
        if self.want[ROLE_FEAS]:
            self.pending[ROLE_FEAS].put(key, value)

    def expect_efforts(self, key: tuple[int, str], tau: np.ndarray) -> None:
        if self.want[ROLE_TRAJ_EFFORT]:
            self.pending[ROLE_TRAJ_EFFORT].put(key, tau)

    # what the node recorded ----------------------------------------------------------------
    def output(self, role: str, m: BagMessage, model: Any) -> None:
        """Compare one recorded output with its recomputed value (``model``: the one replayed)."""
        if role in CONTACT_ROLES:
            self.contact.output(role, m, model)
            return
        if role not in OUTPUT_ROLES:
            return
        self.topics[role] = m.topic
        if role == ROLE_TRAJ_EFFORT:
            self._traj_effort(m, model)
        elif role == ROLE_FEAS:
            self._feasibility(m, model)
        else:
            self._torques(role, m, model)

    def result(self) -> RecheckResult:
        return RecheckResult(self.checks, {r: p.left() for r, p in self.pending.items()},
                             self.topics, self.lat_stamp, self.lat_receipt)

    def _torques(self, role: str, m: BagMessage, model: Any) -> None:
        chk = self.checks[role]
        try:
            out = decode_joint_state(m.data)
        except ValueError:
            chk.unmatched += 1
            return
        want = self.pending[role].take(out.stamp_ns)
        if want is None:
            chk.unmatched += 1
            return
        names = model.joint_names
        got = out.effort
        if out.names != names and set(out.names) == set(names):
            got = got[[out.names.index(n) for n in names]]
        d = float(np.max(np.abs(got - want))) if got.shape == want.shape else math.inf
        t_ns = m.log_time_ns
        chk.diff(d, {"stamp_ns": out.stamp_ns, "t_ns": t_ns})
        if role == ROLE_GRAVITY:
            src = self.input_log.get(out.stamp_ns)
            self.lat_stamp.add((t_ns - out.stamp_ns) * 1e-9)
            if src is not None:
                self.lat_receipt.add((t_ns - src) * 1e-9)

    def _recorded_and_recomputed(self, m: BagMessage, role: str) -> tuple[Any, int, Any] | None:
        """(recorded output, its header stamp in ns, the value recomputed for that stamp), or None
        (counted as unmatched) when the output cannot be decoded or has no recomputed input."""
        try:
            msg = self.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001 - a damaged output is a finding, not a crash
            self.checks[role].unmatched += 1
            return None
        key = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        want = self.pending[role].take((key, msg.header.frame_id))
        if want is None:
            self.checks[role].unmatched += 1
            return None
        return msg, key, want

    def _feasibility(self, m: BagMessage, model: Any) -> None:
        found = self._recorded_and_recomputed(m, ROLE_FEAS)
        if found is None:
            return
        arr, key, res = found
        if any(st.message.startswith(("rejected: busy", "rejected: no robot model yet")) for st in arr.status):
            return  # a request the node could not take (queue full, no model yet): nothing to compare
        worst, where, mismatched = worst_status_difference(arr.status, _statuses(res, model.name))
        chk = self.checks[ROLE_FEAS]
        chk.mismatched_values += mismatched
        chk.diff(worst, {"stamp_ns": key, "t_ns": m.log_time_ns, **(where or {})})

    def _traj_effort(self, m: BagMessage, model: Any) -> None:
        found = self._recorded_and_recomputed(m, ROLE_TRAJ_EFFORT)
        if found is None:
            return
        msg, key, want = found
        try:
            order = [list(msg.joint_names).index(n) for n in model.joint_names]
            got = np.array([[p.effort[i] for i in order] for p in msg.points], dtype=float)
            d = float(np.max(np.abs(got - want))) if got.shape == want.shape else math.inf
        except (ValueError, IndexError):
            d = math.inf
        self.checks[ROLE_TRAJ_EFFORT].diff(d, {"stamp_ns": key, "t_ns": m.log_time_ns})


def _statuses(res: Any, model_name: str) -> dict[str, dict[str, str]]:
    """The ~/feasibility statuses the node publishes for a result (or a rejected entry), by name,
    with their values formatted as the node formats them."""
    from dyn_node.core.robot.status import format_value

    if isinstance(res, dict):  # rejected: the node published rejected_statuses
        from dyn_node.core.check.feasibility import rejected_statuses

        err = TrajectoryError(res["message"].removeprefix("rejected: "), code=res["error_code"] or "error")
        statuses = rejected_statuses(err, model_name, res.get("n_points", 0), res.get("duration_s", 0.0))
    else:
        statuses = res.statuses(model_name)
    return {s.name: {k: format_value(v) for k, v in s.values.items()} for s in statuses}


# --- stage 4: evidence --------------------------------------------------------------------
def require_inputs(bag: str, reader: BagReader, r: ReplayResult, model: Any) -> None:
    """AuditError when the bag gave nothing to audit (``model``: the first configuration's)."""
    stats = reader.stats
    if reader.readable_files == 0:
        raise AuditError(f"bag {bag} is unreadable: "
                         + "; ".join(u.reason for u in reader.unreadable[:3]), code="bag_unreadable")
    n_traj = r.trajectories.total + sum(q["requests"] for q in r.questions.values())
    if not r.js_topics and n_traj == 0:
        raise AuditError(f"bag {bag} has no joint_states or joint_trajectory messages "
                         f"(topics: {', '.join(sorted(stats.message_counts)) or 'none'})",
                         code="no_inputs")
    if r.js_topics and r.counts.accepted == 0 and n_traj == 0 and r.invalid.items:
        raise AuditError(f"none of the {r.invalid.total} joint_states fits the model "
                         f"{model.name} ({', '.join(model.joint_names)}): {r.invalid.items[0]['reason']}",
                         code="no_valid_inputs")


def _time_span(reader: BagReader) -> tuple[int | None, int | None]:
    """First and last log time (ns) of the bag, unreadable ranges included."""
    start_ns, end_ns = reader.stats.first_ns, reader.stats.last_ns
    for u in reader.unreadable:
        for t in (u.start_ns, u.end_ns):
            if t is not None:
                start_ns = t if start_ns is None else min(start_ns, t)
                end_ns = t if end_ns is None else max(end_ns, t)
    return start_ns, end_ns


def _rel(s0: int, t: int | None) -> float | None:
    return None if t is None else (t - s0) * 1e-9


def build_evidence(opts: AuditOptions, source: AuditSource, roles: Roles, replay: ReplayResult,
                   recheck: RecheckResult) -> EvidenceRecord:
    """Stage 4: the EvidenceRecord's inputs, configuration, outputs and input quality (times in
    seconds from the bag's first log time)."""
    start_ns, end_ns = _time_span(source.reader)
    rel = partial(_rel, start_ns or 0)
    rec = EvidenceRecord(kind="audit", tool="dyn-audit")
    rec.inputs = _inputs_section(opts.bag, source.reader, roles, start_ns, end_ns)
    rec.configuration = _configuration_section(opts, source, replay, rel)
    rec.outputs = _outputs_section(source, replay, recheck, rel)
    contact = contact_section(replay.contact, start_ns or 0)
    if contact is not None:
        rec.outputs["contact"] = contact
    rec.input_quality = _input_quality_section(source.reader, replay, source.first.settings, rel)
    return rec


def _inputs_section(bag: str, reader: BagReader, roles: Roles, start_ns: int | None,
                    end_ns: int | None) -> dict:
    stats = reader.stats
    topic_types = {c.topic: c.schema_name for c in reader.channels.values()}
    return {
        "bag": str(Path(bag).resolve()), "files": [str(f) for f in reader.files],
        "topics": [{"name": t, "type": topic_types.get(t, ""), "count": n,
                    "role": roles.seen.get(t) or "ignored"}
                   for t, n in sorted(stats.message_counts.items())],
        "message_counts": dict(sorted(stats.message_counts.items())),
        "time_span": {"start_ns": start_ns, "end_ns": end_ns,
                      "duration_s": ((end_ns - start_ns) * 1e-9) if start_ns is not None else 0.0},
        "bytes_read": stats.bytes_read, "chunks": stats.chunks,
        "rosbag2_metadata": bool(reader.info),
    }


def _configuration_section(opts: AuditOptions, source: AuditSource, replay: ReplayResult,
                           rel: Any) -> dict:
    model, cfgs = source.first.model, source.configurations
    return {
        "model": {"name": model.name, "source": source.model_source, "urdf_sha256": model.urdf_hash,
                  "joint_names": list(model.joint_names), "dof": model.nv,
                  "total_mass_kg": model.total_mass, "payload_mass_kg": model.payload.mass,
                  "gravity_m_s2": list(model.gravity), "limits_source": source.limits_source},
        "limits": model.limits.to_dict(),
        **task_limits_key(model),
        "parameters": source.first.parameters,
        "settings_used": _settings_dict(replay.settings, replay.model),
        "overrides": source.overrides,
        "bag_dyn_node_version": source.bag_metadata_version,
        "gap_threshold_s": opts.gap_threshold_s,
        "changes": [{"time_s": rel(c.since_ns), "effective_log_time_ns": c.since_ns,
                     "parameters": _changed(prev.parameters, c.parameters),
                     "payload_mass_kg": c.model.payload.mass, **task_limits_key(c.model)}
                    for prev, c in zip(cfgs, cfgs[1:])],
    }

def _settings_dict(settings: Any, model: Any) -> dict:
    d = settings.to_parameters()
    if d.get("robot_description"):
        d["robot_description"] = f"<URDF, {len(d['robot_description'])} chars, sha256 {model.urdf_hash[:16]}>"
    return d


def _joint_peak(live: LiveStats, model: Any, units: dict, rel: Any, j: int) -> dict:
    n = model.joint_names[j]
    if not live.peak_util[j] > -np.inf:  # no accepted message
        return {"joint": n, "unit": units["effort"][j], "peak_utilisation": None,
                "peak_time_s": None, "peak_effort": None, "peak_measured_effort": None,
                "peak_source": None, "effort_limit": float(model.limits.effort[j])}
    meas = float(live.peak_meas[j]) if np.isfinite(live.peak_meas[j]) else None
    # utilisation is the larger of |model| and |measured| over the limit: say which
    source = "measured" if meas is not None and abs(meas) > abs(live.peak_tau[j]) else "model"
    return {"joint": n, "unit": units["effort"][j], "peak_utilisation": float(live.peak_util[j]),
            "peak_time_s": rel(int(live.peak_t[j])), "peak_effort": float(live.peak_tau[j]),
            "peak_measured_effort": meas, "peak_source": source,
            "effort_limit": float(live.peak_limit[j])}


def _violations(episodes: Episodes, names: Sequence[str], units: dict, rel: Any) -> list[dict]:
    return [{"joint": names[e["j"]], "kind": e["kind"], "start_s": rel(e["start"]),
             "end_s": rel(e["end"]), "peak_time_s": rel(e["peak_t"]),
             "peak_value": e["peak"], "limit": e["limit"],
             "unit": units[e["kind"]][e["j"]],
             "peak_ratio": (abs(e["peak"]) / e["limit"] if e["kind"] != "position"
                            and e["limit"] not in (0.0, math.inf) else None),
             "duration_s": (e["end"] - e["start"]) * 1e-9, "messages": e["n"],
             "failure_label": CONTROL_ERROR}
            for e in sorted(episodes.closed, key=lambda e: (e["start"], e["j"], e["kind"]))]


def not_comparable(source: AuditSource) -> list[str]:
    """Why the re-check does not measure the node (the configuration replayed differs)."""
    return list(dict.fromkeys(x for c in source.configurations for x in c.not_comparable))


def _recheck_section(recheck: RecheckResult, differs: list[str], rel: Any) -> dict:
    rc = {}
    for role, chk in recheck.checks.items():
        if not (chk.matched or chk.unmatched):
            continue
        d = chk.to_dict(recheck.unanswered[role])
        d["topic"] = recheck.topics.get(role, "")
        if chk.worst and "t_ns" in chk.worst:
            d["worst"] = {"stamp_ns": chk.worst.get("stamp_ns"), "time_s": rel(chk.worst["t_ns"]),
                          **{k: v for k, v in chk.worst.items() if k not in ("t_ns", "stamp_ns")}}
        if differs:  # a difference would only measure the other configuration
            d.update(comparable=False, identical=False, max_abs_difference=None,
                     not_comparable="not comparable: " + "; ".join(differs))
            d.pop("worst", None)
        rc[recheck.topics.get(role, role)] = d
    return rc


def _outputs_section(source: AuditSource, replay: ReplayResult, recheck: RecheckResult,
                     rel: Any) -> dict:
    model = source.first.model
    units = joint_units(model)  # each joint's own: N·m, or N for a prismatic joint
    latency = {}
    if recheck.latency_stamp.n:
        latency["stamp_to_output_s"] = recheck.latency_stamp.to_dict()
    if recheck.latency_receipt.n:
        latency["receipt_to_output_s"] = recheck.latency_receipt.to_dict()
    trajectories = replay.trajectories.items
    for e in trajectories:
        e["time_s"] = rel(e.pop("t_ns"))
    ctrl, counts = replay.controller, replay.counts
    return {
        "trajectories": trajectories, "trajectories_total": replay.trajectories.total,
        "trajectories_infeasible_or_rejected": replay.trajectories_bad,
        "trajectory_counts": replay.tally.to_dict(),
        "effort": {"per_joint": [_joint_peak(replay.live, model, units, rel, j)
                                 for j in range(len(model.joint_names))],
                   "samples": int(counts.accepted)},
        "violations": _violations(replay.live.episodes, model.joint_names, units, rel),
        "violation_episodes_total": replay.live.episodes.total,
        "controller_states": {"replayed_transitions": [{"time_s": rel(c["t_ns"]), "state": c["state"]}
                                                       for c in ctrl.transitions],
                              "replayed_time_in_state_s": ctrl.time_in_state,
                              "states_seen": sorted(ctrl.time_in_state)
                              or sorted({c["state"] for c in ctrl.transitions}),
                              "recorded_status_counts": ctrl.recorded},
        "recheck": _recheck_section(recheck, not_comparable(source), rel), "latency": latency,
        "questions": replay.questions,  # service questions: answered, never violations
        "monitor_counts": {"received": counts.received, "accepted": counts.accepted,
                           "invalid": counts.invalid, "out_of_order": counts.out_of_order,
                           "zero_stamp": counts.zero_stamp,
                           "ignored_joint_values": counts.ignored_joint_values},
    }


def _periods(gs: list[dict], rel: Any) -> list[dict]:
    return [{"start_s": rel(g["start_ns"]), "end_s": rel(g["end_ns"]),
             "duration_s": (g["end_ns"] - g["start_ns"]) * 1e-9} for g in gs]


def _input_quality_section(reader: BagReader, replay: ReplayResult, settings: Any, rel: Any) -> dict:
    stats = reader.stats
    return {
        "gaps": _periods(replay.gaps.items, rel), "gaps_total": replay.gaps.total,
        "stale_periods": _periods(replay.stale.items, rel),
        "stale_periods_total": replay.stale.total, "stale_timeout_s": settings.stale_timeout,
        "invalid_messages": {"count": replay.invalid.total, "by_reason": replay.invalid_by_reason,
                             "examples": [{"time_s": rel(e["t_ns"]), "reason": e["reason"],
                                           "code": e["code"], "topic": e["topic"]}
                                          for e in replay.invalid.items]},
        "out_of_order": {"count": replay.counts.out_of_order,
                         "examples": [{"time_s": rel(e["t_ns"]), "stamp_ns": e["stamp_ns"]}
                                      for e in replay.out_of_order]},
        "zero_stamp_messages": replay.counts.zero_stamp,
        "unreadable_ranges": [{"start_s": rel(u.start_ns), "end_s": rel(u.end_ns), "reason": u.reason,
                               "file": u.file} for u in reader.unreadable],
        "data_crc": stats.data_crc, "chunks_damaged": stats.chunks_bad,
        "chunks_crc_checked": stats.crc_checked_chunks,
        "undecodable_messages": stats.undecodable_messages,
        "notes": list(stats.notes),
    }


# --- stage 5: verdict ---------------------------------------------------------------------
def add_verdict(rec: EvidenceRecord, source: AuditSource, replay: ReplayResult, *,
                gap_threshold_s: float) -> int:
    """Stage 5: the failure labels, the findings and the verdict of an evidence record whose
    other sections are filled; returns the exit code."""
    out, quality = rec.outputs, rec.input_quality
    violations, rc, unreadable = out["violations"], out["recheck"], quality["unreadable_ranges"]
    episodes_total, n_traj_bad = out["violation_episodes_total"], replay.trajectories_bad
    findings, differs = source.findings, not_comparable(source)
    if violations or episodes_total:
        rec.add_label(CONTROL_ERROR)
    for lbl in sorted(replay.trajectory_failure_labels):
        if n_traj_bad:
            rec.add_label(lbl)
    if replay.invalid.total or replay.stale.total or unreadable:
        rec.add_label(STATE_ERROR)
    if rc and differs:
        findings.append("re-check not comparable: " + "; ".join(differs))
    mism = [t for t, d in rc.items() if d["matched"] and not d["identical"] and d.get("comparable", True)]
    if mism:
        rec.add_label(EVALUATION_ERROR)
        findings.append("re-check differs from the recorded outputs on " + ", ".join(mism))
    bad = bool(episodes_total or n_traj_bad)
    code = exit_code(violations=bad, partial=bool(unreadable))
    findings += _quality_findings(replay, unreadable, gap_threshold_s)
    findings += contact_findings(out.get("contact"))
    rec.verdict = {"result": "violations" if bad else "feasible", "exit_code": code,
                   "summary": "; ".join(_summary(replay, violations, episodes_total, unreadable)),
                   "partial": bool(unreadable), "findings": findings}
    return code


def _summary(replay: ReplayResult, violations: list[dict], episodes_total: int,
             unreadable: list[dict]) -> list[str]:
    n_traj_bad, accepted, tally = replay.trajectories_bad, replay.counts.accepted, replay.tally
    parts = []
    if episodes_total:
        rated = [v for v in violations if isinstance(v["peak_ratio"], float)]
        worst = max(rated, key=lambda v: v["peak_ratio"]) if rated else (violations or [None])[0]
        parts.append(f"{episodes_total} live limit violation episode(s)"
                     + (f", worst {worst['joint']} {worst['kind']} at t = {worst['peak_time_s']:.3f} s"
                        if worst else ""))
    if n_traj_bad:
        parts.append(tally.sentence())  # each count over its own total: executed, questions
    if not (episodes_total or n_traj_bad):
        parts.append(f"all feasible: {accepted} joint states, {tally.executed_text()}; "
                     f"peak utilisation {np.max(replay.live.peak_util) * 100:.0f}%" if accepted
                     else f"all feasible: {tally.executed_text()}")
    if tally.questions and not n_traj_bad:
        parts.append(tally.questions_sentence())
    if unreadable:
        parts.append(f"PARTIAL: {len(unreadable)} unreadable range(s)")
    return parts


def _quality_findings(replay: ReplayResult, unreadable: list[dict], gap_threshold_s: float) -> list[str]:
    out = []
    if unreadable:
        out.append("could not read: " + "; ".join(
            f"{_fmt_s(u['start_s'])} – {_fmt_s(u['end_s'])} ({u['reason']})" for u in unreadable))
    if replay.invalid.total:
        out.append(f"{replay.invalid.total} invalid joint_states ("
                   + ", ".join(f"{k}: {v}" for k, v in sorted(replay.invalid_by_reason.items())) + ")")
    if replay.gaps.total:
        out.append(f"{replay.gaps.total} gap(s) in joint_states longer than {gap_threshold_s:g} s"
                   + (f", {replay.stale.total} longer than stale_timeout" if replay.stale.total else ""))
    if replay.counts.out_of_order:
        out.append(f"{replay.counts.out_of_order} out-of-order joint_states stamps")
    return out


def _effective_ns(meta: dict) -> int | None:
    """The log time from which a ``dyn_node`` metadata record applies (None: not recorded)."""
    try:
        return int(meta["effective_log_time_ns"])
    except (KeyError, ValueError, TypeError):
        return None


def _changed(before: dict, after: dict) -> dict:
    """The parameters whose value differs, with their new value (None: no longer set)."""
    return {k: after.get(k) for k in sorted(set(before) | set(after)) if before.get(k) != after.get(k)}


def _fmt_s(x: float | None) -> str:
    return "end of recording" if x is None else f"{x:.3f} s"


class _Progress:
    """A one-line progress bar on stderr, only when stderr is a terminal (plain \\r updates)."""

    def __init__(self, reader: BagReader, enabled: bool | None):
        self.on = sys.stderr.isatty() if enabled is None else enabled
        self.reader = reader
        self.total = sum(f.stat().st_size for f in reader.files if f.exists()) or 1
        self.last = 0.0
        self.t0 = time.monotonic()

    def update(self, n: int, final: bool = False) -> None:
        if not self.on:
            return
        now = time.monotonic()
        if now - self.last < 0.2 and not final:
            return
        self.last = now
        # the summary section at the end of each file is not streamed: at the end, 100 %
        frac = 1.0 if final else min(self.reader.stats.bytes_read / self.total, 1.0)
        bar = "#" * int(frac * 30)
        rate = n / max(now - self.t0, 1e-9)
        sys.stderr.write(f"\rdyn-audit [{bar:<30}] {frac * 100:5.1f}%  {n} msgs  {rate:,.0f} msg/s")
        sys.stderr.flush()

    def done(self, n: int) -> None:
        if self.on:
            self.update(n, final=True)
            sys.stderr.write("\n")
            sys.stderr.flush()


def run_audit(opts: AuditOptions) -> AuditResult:
    """Run the audit and write evidence.json (+ report.html and PNGs) into ``opts.out``.
    Raises :class:`AuditError` / :class:`BagError` for unusable input."""
    import json

    wall0 = time.perf_counter()
    audit = Audit(opts)
    record, code, series = audit.run()
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    ev = out / "evidence.json"
    tmp = ev.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False, allow_nan=False))
    tmp.replace(ev)
    files = [ev]
    if opts.report:
        from dyn_node.audit.report import write_report

        files += write_report(record, series, audit.model, out, contact_series=audit.contact_series)
    return AuditResult(record, code, out, files, audit.n_msgs, time.perf_counter() - wall0)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dyn-audit", description="Replay a bag through dyn_node's core; write evidence.json and "
        "report.html. Exit 0: all feasible, 1: violations found, 2: unusable input, "
        "3: partial (parts of the bag unreadable, no violations in the rest).")
    p.add_argument("bag", help="bag directory (rosbag2 layout), or a single .mcap file")
    p.add_argument("--out", metavar="DIR", default="audit", help="output directory (default: ./audit)")
    add_audit_options(p)
    p.add_argument("--version", action="version", version=f"dyn-audit {__version__}")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    retain_freed_memory()     # each trajectory re-checked reuses the last one's pages
    opts = AuditOptions(bag=args.bag, robot_description=args.robot_description,
                        robot_model=args.robot_model, limits=args.limits, out=args.out,
                        topics=tuple(args.topics), gap_threshold_s=args.gap_threshold,
                        report=not args.no_report)
    return run_command("dyn-audit", partial(run_audit, opts), partial(_print_result, opts))


def _print_result(opts: AuditOptions, res: AuditResult) -> int:
    v = res.record["verdict"]
    print(f"{v['result'].upper()}: {v['summary']}")
    for f in v.get("findings", []):
        print(f"  - {f}")
    print(f"evidence: {res.out_dir / 'evidence.json'}")
    if opts.report:
        print(f"report:   {res.out_dir / 'report.html'}")
    return res.exit_code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
