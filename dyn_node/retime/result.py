"""What a retiming answers."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from dyn_node.core.check.feasibility import FeasibilityResult
from dyn_node.core.check.trajectory import Trajectory


@dataclass(frozen=True)
class RetimeResult:
    """``trajectory``: the retimed motion (model order, positions, velocities and accelerations
    at every point) or None; it is returned only when ``check`` (the exact check of it with the
    controller's interpolation) passed. Durations in s: ``duration_in`` the input's (0 for
    untimed waypoints), ``duration_out`` the output's, ``duration_uniform`` the input stretched
    by the check's time scale (NaN when none applies), ``lower_bound`` T*: a lower bound on the
    duration of any motion along the path within the first- and second-order kinds, certified
    against a grid of ``bound_steps`` stages (dyn_node/retime/bound.py), and ``grid_optimum``
    TOPP-RA's optimum on its own grid (what T* was before: not a bound). ``blocked``: the
    check's reason when no slowdown helps, else "". ``method``: "optimal" (TOPP-RA, then the
    check-driven smoothing and local slowdown), "uniform" (the fallback) or "unchanged"."""

    feasible: bool
    trajectory: Trajectory | None
    duration_in: float
    duration_out: float
    duration_uniform: float
    lower_bound: float
    message: str
    blocked: str = ""
    check: FeasibilityResult | None = None
    input_check: FeasibilityResult | None = None
    method: str = ""
    rounds: int = 0
    smoothing_s: float = 0.0
    path_deviation: float = math.nan
    #: the input as the check saw it (None for untimed waypoints), for plots beside the output
    source: Trajectory | None = None
    #: TOPP-RA's optimum on its grid (≥ T*; not a bound between the grid points)
    grid_optimum: float = math.nan
    #: the stages of the grid T* is certified against (its grid refined where the law bends)
    bound_steps: int = 0

    @property
    def gap(self) -> float:
        """duration_out / T* (NaN without both)."""
        if not (self.feasible and self.lower_bound > 0 and math.isfinite(self.lower_bound)):
            return math.nan
        return self.duration_out / self.lower_bound

    def summary(self) -> dict[str, Any]:
        return {"feasible": self.feasible, "duration_in_s": self.duration_in,
                "duration_out_s": self.duration_out, "duration_uniform_s": self.duration_uniform,
                "lower_bound_s": self.lower_bound, "bound_steps": self.bound_steps,
                "grid_optimum_s": self.grid_optimum, "gap": self.gap, "method": self.method,
                "rounds": self.rounds, "smoothing_s": self.smoothing_s,
                "path_deviation": self.path_deviation, "blocked": self.blocked,
                "message": self.message}
