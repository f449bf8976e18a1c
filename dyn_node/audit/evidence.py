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
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dyn_node import __version__
from dyn_node.errors import FAILURE_LABELS, EVALUATION_ERROR, DynNodeError
from dyn_node.io.jsonable import json_scalar

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "schemas" / "evidence_record.schema.json"
SCHEMA_ID = "dyn_node/evidence_record"
SCHEMA_VERSION = 2  # 2: per-joint effort keys unit-neutral, with the joint's unit

#: What every number of a record means, with its unit, per kind of record ("audit": dyn-audit's
#: and dyn-check's, "physics": dyn_sim --check-physics'): reference data kept beside the schema.
METRICS_PATH = SCHEMA_PATH.with_name("metric_definitions.json")


@lru_cache(maxsize=1)
def _metric_tables() -> dict[str, dict[str, dict[str, str]]]:
    return json.loads(METRICS_PATH.read_text(encoding="utf-8"))


def metric_definitions(kind: str = "audit") -> dict[str, dict[str, str]]:
    """A record's ``metric_definitions`` for ``kind`` ("audit" or "physics"): a fresh copy."""
    return {name: dict(d) for name, d in _metric_tables()[kind].items()}


@lru_cache(maxsize=1)
def task_kind_units() -> dict[str, str]:
    """The task kinds' units, as the per_frame entries and ~/feasibility messages give them (the
    kind classes' own ``unit``). Read when first asked: the kinds are the check's whole stack,
    which an audit of a bag without trajectories does not load."""
    from dyn_node.core.check.kinds import KINDS

    return {c.kind: c.unit for c in KINDS if c.scope == "task"}


def task_limits_section(model: Any) -> dict[str, Any] | None:
    """``configuration.task_limits``: the model's TaskLimits as applied (None: none configured)."""
    tl = getattr(model, "task_limits", None)
    if tl is None:
        return None
    from dyn_node.core.check.task_motion import configured

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
    units = task_kind_units()
    return {place: {kind: {"unit": units.get(kind, ""), **dict(e)}
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
    if isinstance(x, (bool, np.bool_, int, np.integer, float, np.floating)):
        return json_scalar(x)
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
    metric_definitions: dict[str, dict[str, str]] = field(default_factory=metric_definitions)
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
