"""The fleet's rows: the tables' columns, a bag's job and outcome, and the rows made from one
evidence record (all numbers come from it). Executed trajectories and questions are counted
apart (:mod:`dyn_node.audit.accounting`): the worst-of and the trajectory columns are of what
was executed; questions have their own columns.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dyn_node.audit.accounting import counts_of, is_executed
from dyn_node.audit.replay.stats import LiveStats
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS
from dyn_node.core.robot.limits import LIMIT_KINDS

#: Bumped when a row's content changes meaning: --resume then re-audits every bag.
ROW_FORMAT = 2  # 2: trajectories and worst-of are of executed trajectories; questions apart
LIVE_KINDS: tuple[str, ...] = tuple(LiveStats.KINDS)   # live violation kinds of the audit
TRAJ_KINDS: tuple[str, ...] = tuple(LIMIT_KINDS)        # every limit kind the check knows

# exit categories of a row
OK, VIOLATIONS, PARTIAL, UNUSABLE, TIMEOUT, CRASHED = (
    "ok", "violations", "partial", "unusable", "timeout", "crashed")
_CATEGORY = {EXIT_OK: OK, EXIT_VIOLATIONS: VIOLATIONS, EXIT_PARTIAL: PARTIAL, EXIT_UNUSABLE: UNUSABLE}

# --- the tables' columns: (name, Arrow type, unit, meaning), kept as data in
# schemas/fleet_columns.json (docs/fleet.md's table is made of them) ---
COLUMNS_PATH = Path(__file__).resolve().parents[1] / "schemas" / "fleet_columns.json"


def _columns(table: str) -> list[tuple[str, str, str, str]]:
    """A table's columns in order; a per-kind entry gives one column a kind."""
    kinds = {"live_kinds": LIVE_KINDS, "traj_kinds": TRAJ_KINDS}
    out: list[tuple[str, str, str, str]] = []
    for entry in json.loads(COLUMNS_PATH.read_text(encoding="utf-8"))[table]:
        if isinstance(entry, dict):
            out += [tuple(x.format(kind=k) for x in entry["row"]) for k in kinds[entry["each"]]]
        else:
            out.append(tuple(entry))
    return out


ROW_COLUMNS: list[tuple[str, str, str, str]] = _columns("bags")
JOINT_COLUMNS: list[tuple[str, str, str, str]] = _columns("joints")


# --- configuration and jobs ------------------------------------------------------------------
@dataclass(frozen=True)
class FleetConfig:
    """What every bag is audited with (the part of dyn-audit's options shared by the fleet)."""

    robot_model: str = ""
    robot_description: str = ""
    limits: str = ""
    gap_threshold_s: float = 0.05
    topics: tuple[str, ...] = ()
    report: bool = True


@dataclass(frozen=True)
class BagJob:
    path: str
    bag_id: str
    out_root: str          # DIR
    config: FleetConfig
    config_hash: str
    resume: bool = False

    @property
    def out_dir(self) -> Path:
        return Path(self.out_root) / "bags" / self.bag_id


@dataclass
class BagOutcome:
    """One bag's row (ROW_COLUMNS) and joint rows (JOINT_COLUMNS)."""

    row: dict
    joints: list[dict] = field(default_factory=list)


def _nan(x: Any) -> float:
    """A number of the evidence record as a float: its non-finite strings ("inf", "-inf") as
    such, null and anything else as NaN."""
    if isinstance(x, str) and x in ("inf", "-inf"):
        return float(x)
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else math.nan


def _executed(out: dict) -> list[dict]:
    """The record's executed trajectory entries (a question's answer is no violation of the run)."""
    return [t for t in out["trajectories"] if is_executed(t)]


def _blank_row(job: BagJob) -> dict:
    row: dict[str, Any] = {name: None for name, *_ in ROW_COLUMNS}
    row.update(bag_id=job.bag_id, path=job.path, content_hash="", config_hash=job.config_hash,
               robot="", dof=0, error="", error_code="", resumed=False, partial=False,
               evidence="", report="", node="", worst_joint="", worst_constraint="", worst_source="",
               worst_ratio=math.nan, worst_time_s=math.nan, worst_time_scale=math.nan,
               recording_duration_s=math.nan, audit_s=0.0, audited_utc="")
    for name, typ, *_ in ROW_COLUMNS:
        if row[name] is None and typ.startswith("int"):
            row[name] = 0
    row["recording_start_ns"] = None
    return row


def error_outcome(job: BagJob, category: str, code: str, message: str, **extra: Any) -> BagOutcome:
    """The row of a bag that was not audited: its error and exit category; exit code 2."""
    row = _blank_row(job)
    row.update(verdict="error", exit_code=EXIT_UNUSABLE, exit_category=category,
               error=message.strip().splitlines()[0] if message.strip() else category,
               error_code=code, **extra)
    return BagOutcome(row)


def _worst(rec: dict) -> tuple[str, str, float, str, float]:
    """(joint, constraint, ratio, source, time) of the largest limit ratio in the record."""
    best = ("", "", -math.inf, "", math.nan)
    out = rec["outputs"]
    for pj in out["effort"]["per_joint"]:
        r = _nan(pj.get("peak_utilisation"))
        if r > best[2]:
            best = (pj["joint"], "effort", r, "live", _nan(pj.get("peak_time_s")))
    for v in out["violations"]:
        r = _nan(v.get("peak_ratio"))
        if r > best[2]:
            best = (v["joint"], v["kind"], r, "live", _nan(v.get("peak_time_s")))
    for t in _executed(out):
        r = _nan(t.get("worst_ratio"))
        if t.get("accepted") and r > best[2]:
            best = (t.get("worst_joint") or "", t.get("worst_constraint") or "", r, "trajectory",
                    _nan(t.get("time_s")))
    return best if best[2] > -math.inf else ("", "", math.nan, "", math.nan)


def row_from_record(job: BagJob, rec: dict, code: int, digest: str) -> BagOutcome:
    """The fleet row and joint rows of one evidence record (all numbers come from it)."""
    row = _blank_row(job)
    out, iq, inp = rec["outputs"], rec["input_quality"], rec["inputs"]
    model = rec["configuration"]["model"]
    wj, wc, wr, ws, wt = _worst(rec)
    scales = [_nan(t.get("time_scale")) for t in _executed(out) if t.get("accepted")]
    counts = counts_of(out)
    scales = [s for s in scales if not math.isnan(s)]
    row.update(
        content_hash=digest, robot=model["name"], dof=int(model["dof"]),
        recording_start_ns=inp["time_span"]["start_ns"],
        recording_duration_s=float(inp["time_span"]["duration_s"]),
        messages=int(sum(inp["message_counts"].values())),
        joint_states=int(out["monitor_counts"]["received"]),
        joint_states_accepted=int(out["monitor_counts"]["accepted"]),
        trajectories=counts["executed"], trajectories_bad=counts["executed_bad"],
        questions=counts["questions"], questions_infeasible=counts["questions_no"],
        verdict=rec["verdict"]["result"], exit_code=int(code), exit_category=_CATEGORY[code],
        partial=bool(rec["verdict"]["partial"]),
        worst_joint=wj, worst_constraint=wc, worst_ratio=wr, worst_source=ws, worst_time_s=wt,
        worst_time_scale=max(scales) if scales else math.nan,
        live_episodes_total=int(out["violation_episodes_total"]),
        invalid_messages=int(iq["invalid_messages"]["count"]),
        out_of_order_messages=int(iq["out_of_order"]["count"]),
        zero_stamp_messages=int(iq["zero_stamp_messages"]),
        gaps=int(iq["gaps_total"]), stale_periods=int(iq["stale_periods_total"]),
        unreadable_ranges=len(iq["unreadable_ranges"]), chunks_damaged=int(iq["chunks_damaged"]),
        audited_utc=rec["timestamps"]["finished_utc"],
        evidence=f"bags/{job.bag_id}/evidence.json",
        report=f"bags/{job.bag_id}/report.html" if job.config.report else "",
    )
    for k in LIVE_KINDS:
        row[f"live_{k}_episodes"] = sum(1 for v in out["violations"] if v["kind"] == k)
    for k in TRAJ_KINDS:
        row[f"traj_{k}_violations"] = sum(
            1 for t in _executed(out) for kinds in (t.get("per_joint") or {}).values()
            if _nan((kinds.get(k) or {}).get("ratio")) > 1.0)
    return BagOutcome(row, _joint_rows(job, rec, row))


def _joint_rows(job: BagJob, rec: dict, row: dict) -> list[dict]:
    out = rec["outputs"]
    rows = []
    for j, name in enumerate(rec["configuration"]["model"]["joint_names"]):
        pj = out["effort"]["per_joint"][j]
        jr: dict[str, Any] = {
            "bag_id": job.bag_id, "robot": row["robot"], "joint": name, "joint_index": j,
            "recording_start_ns": row["recording_start_ns"],
            "live_effort_peak": _nan(pj.get("peak_utilisation")),
            "live_effort_peak_time_s": _nan(pj.get("peak_time_s")),
            "effort_limit": _nan(pj.get("effort_limit")),
        }
        eps = [v for v in out["violations"] if v["joint"] == name]
        for k in LIVE_KINDS:
            jr[f"live_{k}_over_s"] = float(sum(v["duration_s"] for v in eps if v["kind"] == k))
        jr["live_episodes"] = len(eps)
        for k in TRAJ_KINDS:
            ratios = [_nan(((t.get("per_joint") or {}).get(name, {}).get(k) or {}).get("ratio"))
                      for t in _executed(out)]
            ratios = [r for r in ratios if not math.isnan(r)]
            jr[f"traj_{k}_peak"] = max(ratios) if ratios else math.nan
        jr["traj_over_limit_s"] = float(sum(
            _nan(v.get("duration_s")) for t in _executed(out) for v in (t.get("violations") or [])
            if isinstance(v, dict) and v.get("joint") == name and not math.isnan(_nan(v.get("duration_s")))))
        rows.append(jr)
    return rows


def partial_note(rows: list[dict]) -> str:
    """`` (1 partial: data lost)`` when bags were only partly readable, whatever their exit
    category (violations win the exit code; the lost data must still be said), else ``""``."""
    k = sum(bool(r.get("partial")) for r in rows)
    return f" ({k} partial: data lost)" if k else ""


def trajectories_line(rows: list[dict]) -> str:
    """``trajectories: 4 of 16 executed infeasible or rejected; questions: 8 of 20 answered
    infeasible or rejected (not violations)``, over the audited bags."""
    def total(k: str) -> int:
        return sum(int(r.get(k) or 0) for r in rows)
    return (f"trajectories: {total('trajectories_bad')} of {total('trajectories')} executed infeasible or "
            f"rejected; questions: {total('questions_infeasible')} of {total('questions')} answered "
            "infeasible or rejected (not violations)")
