"""EvidenceRecord: one JSON document per verdict, validated against the shipped JSON Schema.

The record says what went in (inputs), how it was configured (configuration), what came out
(outputs), what was wrong with the inputs (input_quality), what each number means
(metric_definitions), the failure labels raised, timestamps, the tool version and whether any
randomness was used (seed). The schema lives in ``dyn_node/schemas/evidence_record.schema.json``
(draft 2020-12). Non-finite floats are not JSON: ``inf``/``-inf`` become the strings "inf"/"-inf"
(an infinite time scale means no slowdown helps) and NaN becomes null.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dyn_node import __version__
from dyn_node.core.check.kinds import KINDS
from dyn_node.core.check.task_motion import configured
from dyn_node.errors import FAILURE_LABELS, EVALUATION_ERROR, DynNodeError

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "schemas" / "evidence_record.schema.json"
SCHEMA_ID = "dyn_node/evidence_record"
SCHEMA_VERSION = 2  # 2: per-joint effort keys unit-neutral, with the joint's unit

#: What every number in an audit record means, with its unit.
METRIC_DEFINITIONS: dict[str, dict[str, str]] = {
    "time_s": {"unit": "s", "description": "log (receipt) time relative to inputs.time_span.start_ns"},
    "stamp_ns": {"unit": "ns", "description": "message header stamp, ns since the epoch"},
    "utilisation": {"unit": "1", "description": "max(|model torque|, |measured effort|) / effort limit "
                    "at the current speed (torque-speed envelope applied); > 1 is a violation"},
    "peak_utilisation": {"unit": "1", "description": "largest utilisation of the joint over the bag"},
    "gravity_torque_nm": {"unit": "N·m", "description": "g(q): gravity torque at the recorded position"},
    "rnea_torque_nm": {"unit": "N·m", "description": "RNEA(q, q̇, q̈̂) with friction as configured; q̈̂ "
                       "is the monitor's acceleration estimate"},
    "effort_limit": {"unit": "N·m | N", "description": "effort limit (URDF/limits file), min with the "
                     "torque-speed envelope; per joint in its unit (N for a prismatic joint)"},
    "peak_effort": {"unit": "N·m | N", "description": "model effort (RNEA) at the joint's peak "
                    "utilisation, in the per-joint entry's unit"},
    "peak_measured_effort": {"unit": "N·m | N", "description": "measured effort at the joint's peak "
                             "utilisation (null when not measured), in the entry's unit"},
    "violation.peak_value": {"unit": "N·m | rad | rad/s | rad/s² (N | m | m/s | m/s² for a prismatic "
                             "joint: the violation's unit)", "description": "effort: |torque|; "
                             "position: q; velocity: |q̇|; deceleration: |q̈̂| (the acceleration "
                             "estimate) where q̇·q̈̂ < 0, at the peak"},
    "violation.duration_s": {"unit": "s", "description": "time from the first to the last consecutive "
                             "message above the limit"},
    "time_scale": {"unit": "1", "description": "smallest factor k the trajectory's duration must be "
                   "multiplied by to be feasible (k ≤ 1: feasible; 'inf': no slowdown helps)"},
    "payload_margin_kg": {"unit": "kg", "description": "largest extra payload at the payload frame "
                          "for which the trajectory stays feasible at its own timing (negative: "
                          "how much must come off)"},
    "worst_ratio": {"unit": "1", "description": "largest ratio of a checked quantity to its limit"},
    "recheck.max_abs_difference": {"unit": "N·m (torque topics), key units (feasibility)",
                                   "description": "largest |recorded − recomputed| over matched "
                                   "outputs; 0.0 means bit-identical"},
    "latency.stamp_to_output_s": {"unit": "s", "description": "output log time − input header "
                                  "stamp, for outputs matched to inputs by stamp"},
    "latency.receipt_to_output_s": {"unit": "s", "description": "output log time − input log "
                                    "time (recorder receipt times of both)"},
    "latency quantiles": {"unit": "s", "description": "p50/p95/p99 from a fixed log-spaced histogram "
                          "(1 µs … 100 s, 200 bins per decade: ±0.6% resolution); min, max, mean exact"},
    "gap.duration_s": {"unit": "s", "description": "log-time interval between consecutive joint_states "
                       "longer than gap_threshold_s"},
    "stale_period": {"unit": "s", "description": "gap longer than the node's stale_timeout: the node "
                     "reported STALE during it"},
    "out_of_order": {"unit": "count", "description": "joint_states whose header stamp is older than "
                     "the previous accepted one (the node resets its acceleration estimate)"},
    "unreadable_range": {"unit": "s", "description": "log-time range relative to start_ns that could "
                         "not be read (CRC mismatch, damaged or truncated file); end_s null: to the "
                         "end of the recording"},
    "contact.episode": {"unit": "s", "description": "a contact (|τ̂_ext| over contact_threshold × the "
                        "effort limit on some joint for contact_min_duration) or collision (over "
                        "collision_threshold); start_s/end_s: input header stamps relative to "
                        "inputs.time_span.start_ns, from the first sample over the contact threshold to "
                        "the first with every joint below half of it"},
    "contact.peak_force_n": {"unit": "N", "description": "largest |F̂| of the wrench estimate at the contact "
                             "frame during the episode; peak_wrench: that estimate [N, N, N, N·m, N·m, N·m]"},
    "contact.peak_torque": {"unit": "N·m | N", "description": "largest |τ̂_ext| of the joint during the "
                            "episode (momentum observer, friction of the model subtracted)"},
    "contact.resets": {"unit": "s", "description": "observer restarts (recording start, joint_states gap > "
                       "stale_timeout, model or parameter change, invalid input): stamp of the sample"},
    "throughput_msgs_per_s": {"unit": "1/s", "description": "messages read per second of wall time"},
    "request": {"unit": "", "description": "trajectory entry: execute (sent to be executed: infeasible "
                "is a violation of the run) or the kind of question (check, retime, inverse_dynamics: "
                "a 'no' is an answer, not a violation)"},
    "trajectory_counts": {"unit": "requests", "description": "executed trajectories and questions "
                          "apart, each with how many were infeasible or rejected, exact past the "
                          "listed entries; by_request: per request kind"},
    "per_frame": {"unit": "the kind's (entry.unit)", "description": "trajectory entry: place (a "
                  "frame_limits link, robot_limits, base_limits or grasp) → task kind → {ratio, "
                  "time_s, value, limit, unit}: peak value over its limit, at time_s from the "
                  "trajectory start; only the configured kinds of each place"},
    "task_limits": {"unit": "SI (m, m/s, rad/s, m/s², J, N, N·m, kg)", "description": "the limits "
                    "file's task sections as applied (vectors in the named frame's axes, base "
                    "quantities in the URDF root frame); null: section absent or not limited"},
    "frame_speed": {"unit": "m/s", "description": "|v| of the frame_limits point (root axes); "
                    "time-scale law 1/k"},
    "frame_angular_speed": {"unit": "rad/s", "description": "|ω| of the frame; law 1/k"},
    "frame_acceleration": {"unit": "m/s²", "description": "|J·q̈ + J̇·q̇| of the point, gravity "
                           "excluded; law 1/k²"},
    "transferred_energy": {"unit": "J", "description": "½·m_u·|v|² at the point, m_u the effective "
                           "mass along the motion; an upper bound of ISO/TS 15066's transferred "
                           "energy: advisory, not a certification; law 1/k²"},
    "kinetic_energy": {"unit": "J", "description": "½ q̇ᵀM(q)q̇ of the whole robot; law 1/k²"},
    "base_force": {"unit": "N", "description": "|force| of the mounting on the robot at the root "
                   "origin, root axes: |f_static + f_dynamic/k²|"},
    "base_moment": {"unit": "N·m", "description": "|moment| at the root origin, root axes"},
    "tipping": {"unit": "1", "description": "tipping_ratio: centre of pressure's distance from the "
                "support polygon's centroid over the centroid-to-edge distance on that ray (1 on "
                "the edge, inf at lift-off)"},
    "grasp_slip": {"unit": "N", "description": "force the grasp supplies to the payload, component "
                   "perpendicular to the normal axis, against μ·grip_force·faces"},
}

#: The task kinds' units, as the per_frame entries and ~/feasibility messages give them (the
#: kind classes' own ``unit``).
TASK_KIND_UNITS: dict[str, str] = {c.kind: c.unit for c in KINDS if c.scope == "task"}


def task_limits_section(model: Any) -> dict[str, Any] | None:
    """``configuration.task_limits``: the model's TaskLimits as applied (None: none configured)."""
    tl = getattr(model, "task_limits", None)
    if tl is None:
        return None
    return tl.to_dict() if configured(tl) else None


def task_limits_key(model: Any) -> dict[str, Any]:
    """``{"task_limits": …}`` for a configuration section when the model has task limits."""
    tl = task_limits_section(model)
    return {} if tl is None else {"task_limits": tl}


def per_frame_curves(result: Any, max_points: int = 400) -> dict[str, Any] | None:
    """A trajectory entry's ``per_frame_curves``: place → kind → {t_s, value} per sample at the
    given timing (the result's ``task_curves``), at most ``max_points`` kept per curve by each
    bin's largest value so the peak survives (None: none available)."""
    curves = getattr(result, "task_curves", None)
    if not curves:
        return None
    out: dict[str, Any] = {}
    for place, kinds in curves.items():
        for kind, (t, v) in kinds.items():
            t, v = np.asarray(t, dtype=float), np.asarray(v, dtype=float)
            if t.size > max_points:
                edges = np.linspace(0, t.size, max_points + 1).astype(int)
                pick = np.array([a + int(np.nanargmax(v[a:b])) if np.isfinite(v[a:b]).any() else a
                                 for a, b in zip(edges[:-1], edges[1:])])
                t, v = t[pick], v[pick]
            out.setdefault(place, {})[kind] = {"t_s": t, "value": v}
    return out


def per_frame_section(result_dict: Mapping[str, Any]) -> dict[str, Any] | None:
    """A trajectory entry's ``per_frame`` from ``FeasibilityResult.to_dict()`` (None: no task
    kind configured), each entry with its unit."""
    pf = result_dict.get("per_frame")
    if not pf:
        return None
    return {place: {kind: {"unit": TASK_KIND_UNITS.get(kind, ""), **dict(e)}
                    for kind, e in kinds.items()} for place, kinds in pf.items()}


def add_per_frame(entry: dict[str, Any], result: Any, *, curves: bool,
                  result_dict: Mapping[str, Any] | None = None) -> None:
    """Sets a trajectory entry's ``per_frame`` (and, when ``curves``, its ``per_frame_curves``)
    from a FeasibilityResult; nothing when no task kind is configured. ``result_dict``: the
    result's ``to_dict()`` when the caller has it already."""
    per_frame = per_frame_section(result.to_dict() if result_dict is None else result_dict)
    if not per_frame:
        return
    entry["per_frame"] = per_frame
    c = per_frame_curves(result) if curves else None
    if c:
        entry["per_frame_curves"] = c


class EvidenceError(DynNodeError):
    failure_label = EVALUATION_ERROR


def jsonable(x: Any) -> Any:
    """Plain JSON types: NumPy to Python, inf → "inf", NaN → None, tuples → lists."""
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isnan(x):
            return None
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return x
    if x is None or isinstance(x, str):
        return x
    if hasattr(x, "to_dict"):
        return jsonable(x.to_dict())
    return str(x)


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@lru_cache(maxsize=1)
def schema() -> dict:
    return json.loads(SCHEMA_PATH.read_text())


def validate(record: Mapping[str, Any]) -> None:
    """Raise :class:`EvidenceError` naming the first schema violation (path and reason)."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema())
    errors = sorted(validator.iter_errors(record), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = "/".join(str(p) for p in e.absolute_path) or "(root)"
        raise EvidenceError(f"evidence record invalid at {where}: {e.message}", code="schema")


@dataclass
class EvidenceRecord:
    """Builder: fill the sections, then :meth:`to_dict` (validated) or :meth:`write`."""

    kind: str
    tool: str
    inputs: dict[str, Any] = field(default_factory=dict)
    configuration: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, Any] = field(default_factory=dict)
    input_quality: dict[str, Any] = field(default_factory=dict)
    verdict: dict[str, Any] = field(default_factory=dict)
    failure_labels: list[str] = field(default_factory=list)
    metric_definitions: dict[str, dict[str, str]] = field(default_factory=lambda: dict(METRIC_DEFINITIONS))
    started_utc: str = field(default_factory=utc_now)
    finished_utc: str = ""
    duration_s: float = 0.0
    seed: dict[str, Any] = field(default_factory=lambda: {
        "used": False, "value": None, "note": "no randomness is used: the same bag and "
        "configuration give identical numbers"})
    #: headline numbers of a check (top-level ``figures``; omitted when empty)
    figures: dict[str, float] = field(default_factory=dict)

    def add_label(self, label: str) -> None:
        if label not in FAILURE_LABELS:
            raise EvidenceError(f"unknown failure label '{label}'", code="bad_label")
        if label not in self.failure_labels:
            self.failure_labels.append(label)

    def to_dict(self) -> dict[str, Any]:
        rec = jsonable({
            "schema": SCHEMA_ID, "schema_version": SCHEMA_VERSION, "kind": self.kind,
            "tool": {"name": self.tool, "version": __version__},
            "verdict": self.verdict, "inputs": self.inputs, "configuration": self.configuration,
            "outputs": self.outputs, "input_quality": self.input_quality,
            "metric_definitions": self.metric_definitions, "failure_labels": self.failure_labels,
            "timestamps": {"started_utc": self.started_utc,
                           "finished_utc": self.finished_utc or utc_now(),
                           "duration_s": self.duration_s},
            "seed": self.seed,
            **({"figures": self.figures} if self.figures else {}),
        })
        validate(rec)
        return rec

    def write(self, path: str | Path) -> dict[str, Any]:
        rec = self.to_dict()
        p = Path(path)
        tmp = p.with_suffix(p.suffix + ".tmp")
        tmp.write_text(json.dumps(rec, indent=1, ensure_ascii=False, allow_nan=False))
        tmp.replace(p)
        return rec
