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
    "throughput_msgs_per_s": {"unit": "1/s", "description": "messages read per second of wall time"},
}


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
