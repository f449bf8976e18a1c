"""dyn-audit's stages 4 and 5: the EvidenceRecord's sections (inputs, configuration, outputs,
input quality; times in seconds from the bag's first log time) from the replay and the re-check,
then its failure labels, findings and verdict. Keys: docs/audit.md."""
from __future__ import annotations

import math
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from dyn_node.audit.evidence import EvidenceRecord, task_limits_key
from dyn_node.audit.exit_codes import exit_code
from dyn_node.audit.options import AuditError, AuditOptions
from dyn_node.audit.replay.config import AuditSource
from dyn_node.audit.replay.contact import contact_findings, contact_section
from dyn_node.audit.replay.inputs import ReplayResult
from dyn_node.audit.replay.recheck import RecheckResult
from dyn_node.audit.replay.roles import Roles
from dyn_node.audit.replay.stats import Episodes, LiveStats
from dyn_node.bag.reader import BagReader
from dyn_node.core.robot.units import joint_units
from dyn_node.errors import CONTROL_ERROR, EVALUATION_ERROR, STATE_ERROR


# --- stage 4: evidence --------------------------------------------------------------------
def require_inputs(bag: str, reader: BagReader, r: ReplayResult, model: Any) -> None:
    """AuditError when the bag gave nothing to audit (``model``: the first configuration's)."""
    stats = reader.stats
    if reader.readable_files == 0:
        raise AuditError(f"bag {bag} is unreadable: "
                         + "; ".join(u.reason for u in reader.unreadable[:3]), code="bag_unreadable")
    n_traj = r.trajectories.total + sum(q["requests"] for q in r.questions.values()) + r.gate.get("requests", 0)
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
        "gate": replay.gate,  # the gate's decisions; its goals are counted as executed
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



def _changed(before: dict, after: dict) -> dict:
    """The parameters whose value differs, with their new value (None: no longer set)."""
    return {k: after.get(k) for k in sorted(set(before) | set(after)) if before.get(k) != after.get(k)}


def _fmt_s(x: float | None) -> str:
    return "end of recording" if x is None else f"{x:.3f} s"
