"""What was observed per trajectory (Outcome), the summary table and the acceptance checks."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

from dyn_node.ros.demo.trajectories import TRACKING_TOLERANCE


@dataclass
class Outcome:
    """What was observed for one trajectory."""

    name: str
    description: str
    duration_s: float
    verdict: str = "n/a"
    verdict_source: str = "unavailable"
    worst_joint: str = ""
    worst_constraint: str = ""
    worst_ratio: float = math.nan
    time_scale: float = math.nan
    message: str = ""
    verdict_lead_s: float = math.nan
    states: list[str] = field(default_factory=list)
    transitions: int = 0
    tracking_error_rad: float = math.nan
    saturated_samples: int = 0
    residual_rms_nm: float = math.nan
    residual_max_nm: float = math.nan
    residual_samples: int = 0
    check_verdict: str = "n/a"            # the answer on ~/check_trajectory, asked before sending
    check_feasible: bool | None = None


LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def figure(x: float, fmt: str = ".3g") -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def states_text(states: Sequence[str]) -> str:
    """Distinct controller states in order of first appearance, and how many changes."""
    if not states:
        return "—"
    distinct = list(dict.fromkeys(states))
    return ", ".join(distinct) + (f" ({len(states) - 1} changes)" if len(states) > 1 else "")


def summary_table(outcomes: Sequence[Outcome]) -> str:
    cols = ["trajectory", "dur s", "verdict", "worst joint (constraint)", "ratio", "time_scale",
            "controller states seen", "track err rad", "residual RMS/max N·m"]
    rows = []
    for o in outcomes:
        res = ("—" if math.isnan(o.residual_rms_nm) else
               f"{o.residual_rms_nm:.3f}/{o.residual_max_nm:.3f}")
        worst = f"{o.worst_joint} ({o.worst_constraint})" if o.worst_joint else "—"
        rows.append([o.name, f"{o.duration_s:.2f}", o.verdict, worst, figure(o.worst_ratio),
                     figure(o.time_scale), states_text(o.states), figure(o.tracking_error_rad),
                     res])
    w = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(cols), "  ".join("-" * x for x in w)] + [line(r) for r in rows])


def status_number(values: dict[str, str], key: str) -> float:
    try:
        return float(values.get(key, "nan"))
    except ValueError:
        return math.nan



def acceptance(outcomes: Sequence[Outcome]) -> list[tuple[bool, str]]:
    """The issue's acceptance criteria, evaluated on what was observed."""
    by = {o.name: o for o in outcomes}
    checks: list[tuple[bool, str]] = []
    asked = [o for o in outcomes if o.verdict_source == "dyn_node"]
    if asked:
        same = [o for o in asked if o.check_feasible is not None
                and o.check_feasible == (o.verdict in ("OK", "WARN"))]
        checks.append((len(same) == len(asked),
                       f"every trajectory checked on ~/check_trajectory before it was sent, with "
                       f"the verdict joint_trajectory then got ({len(same)} of {len(asked)}: "
                       + ", ".join(f"{o.name} {o.check_verdict}" for o in asked) + ")"))
    if "comfortable" in by:
        o = by["comfortable"]
        checks.append((o.verdict in ("OK", "WARN") and o.tracking_error_rad <= TRACKING_TOLERANCE,
                       f"comfortable: feasible ({o.verdict}) and tracked within "
                       f"{TRACKING_TOLERANCE} rad ({figure(o.tracking_error_rad)} rad)"))
    if "aggressive" in by:
        o = by["aggressive"]
        checks.append((o.verdict == "ERROR" and o.verdict_lead_s > 0,
                       f"aggressive: ERROR on ~/feasibility before execution "
                       f"({o.verdict}, {figure(o.verdict_lead_s)} s before start)"))
        checks.append((o.saturated_samples > 0 and bool({"saturated", "deviating"} & set(o.states)),
                       f"aggressive: the simulator saturates ({o.saturated_samples} samples) and "
                       f"~/controller_status reports saturated or deviating "
                       f"({states_text(o.states) if o.states else 'nothing'})"))
    if "slowed" in by:
        o = by["slowed"]
        checks.append((o.verdict in ("OK", "WARN") and o.tracking_error_rad <= TRACKING_TOLERANCE,
                       f"slowed: feasible ({o.verdict}) and tracked within {TRACKING_TOLERANCE} rad "
                       f"({figure(o.tracking_error_rad)} rad)"))
    return checks
