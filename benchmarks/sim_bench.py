"""dyn_sim's controller panel (issue 37): every example-robot-data arm the URDF loader takes ×
seeded poses inside the limits, a gentle goal from each, run by the simulator core as dyn_sim
runs it (default controller, RK4 at 1 ms unless the URDF's damping needs implicitfast); and the
retimed demo goals at each ``retime.limit_margin`` executed by that controller (saturation).

Per case: the goal is a rest-to-rest quintic of ``dq`` rad on every joint (towards the inside of
its range) over ``duration`` s; it must end SUCCESSFUL by joint_trajectory_controller's rules
(goal tolerance 0.01 rad, stopped velocity 0.01 rad/s) within duration + 0.5 s, with
|q − q_ref| ≤ 0.01 rad at every step (MuJoCo's own state, unfiltered), no joint faster than
2 × the reference's peak + 0.05 rad/s, nothing non-finite and no physics fault.

``run()`` returns the JSON-able figures; ``python -m benchmarks.sim_bench`` prints them;
``test/test_sim_control.py`` runs a shorter panel with the same :func:`panel_case`.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

#: (name, built-in, path under example-robot-data's robots/)
ARMS = (("panda", "panda", ""), ("ur3", "", "ur_description/urdf/ur3_robot.urdf"),
        ("ur5", "ur5", ""), ("ur10", "", "ur_description/urdf/ur10_robot.urdf"),
        ("kinova", "", "kinova_description/robots/kinova.urdf"),
        ("xarm7", "", "xarm_description/urdf/xarm7.urdf"), ("z1", "", "z1_description/urdf/z1.urdf"),
        ("so100", "", "so_arm_description/urdf/so100.urdf"))
TRACK_TOL = 0.01
SPEED_SLACK = 0.05
SETTLE_S = 0.5
GOAL_TOL = 0.01


def load_arm(name: str) -> Any:
    from dyn_node.core.robot.model import example_robot_data_dir, model_from_source

    _, builtin, rel = next(a for a in ARMS if a[0] == name)
    return model_from_source("", str(example_robot_data_dir() / rel) if rel else "", builtin)


def poses(model: Any, n: int, seed: int = 37) -> np.ndarray:
    """n start poses: the simulator's default (mid-range: Panda's q2 = 0) then seeded uniform
    draws inside the limits (continuous joints within ±π)."""
    from dyn_node.sim.simulator import default_initial_positions

    lo = np.where(np.isfinite(model.limits.position_lower), model.limits.position_lower, -math.pi)
    hi = np.where(np.isfinite(model.limits.position_upper), model.limits.position_upper, math.pi)
    rng = np.random.default_rng(seed)
    out = [default_initial_positions(model)]
    while len(out) < n:
        out.append(rng.uniform(lo, hi))
    return np.array(out)


@dataclass(frozen=True)
class CaseResult:
    arm: str
    pose: int
    integrator: str
    succeeded_s: float        # simulation s after the goal's start; NaN: never within the window
    max_error_rad: float      # max over steps and joints of |q − q_ref|
    max_speed_rad_s: float    # max |q̇| of any joint
    speed_bound_rad_s: float  # 2 × the reference's peak + 0.05
    finite: bool
    fault: str
    step_us: float            # wall time per simulator step (a shared machine: not a timing claim)

    @property
    def passed(self) -> bool:
        return (self.succeeded_s <= 1e9 and self.max_error_rad <= TRACK_TOL and self.finite
                and self.max_speed_rad_s <= self.speed_bound_rad_s and not self.fault)


def panel_case(model: Any, name: str, index: int, q0: np.ndarray, *, dq: float = 0.2,
               duration: float = 3.0) -> CaseResult:
    """One gentle goal from q0, executed and judged (see the module docstring)."""
    from dyn_node.sim import jtc
    from dyn_node.sim.simulator import SimConfig, Simulator

    sim = Simulator(model, SimConfig(initial_positions=tuple(q0)))
    hi = model.limits.position_upper
    goal = q0 + np.where(q0 + dq <= hi, dq, -dq)
    z = [[0.0] * model.nv] * 2
    sim.execute(model.joint_names, [0.0, duration], [q0, goal], z, z)
    peak = 1.875 * dq / duration  # a rest-to-rest quintic's peak speed
    tol = jtc.default_tolerances(model.nv, goal=GOAL_TOL, stopped_velocity=0.01)
    err = speed = 0.0
    finite, succeeded = True, math.nan
    n = int(round((duration + SETTLE_S) / sim.config.timestep))
    t0 = time.perf_counter()
    for _ in range(n):
        st = sim.step()
        finite &= bool(np.all(np.isfinite(st.q)) and np.all(np.isfinite(st.v)))
        err = max(err, float(np.abs(st.q - st.q_ref).max()))
        speed = max(speed, float(np.abs(st.v).max()))
        if math.isnan(succeeded):
            out = jtc.monitor(st.t, duration, st.q_ref - st.q, st.v_ref - st.v, tol, model.joint_names)
            if out is not None and out.code == jtc.SUCCESSFUL:
                succeeded = st.t
    step_us = (time.perf_counter() - t0) / n * 1e6
    return CaseResult(name, index, sim.integrator, succeeded, err, speed, 2 * peak + SPEED_SLACK, finite,
                      sim.fault.text if sim.fault else "", step_us)


def panel(n_poses: int = 5, duration: float = 3.0, arms: tuple[str, ...] | None = None) -> list[CaseResult]:
    out = []
    for name, _, _ in ARMS:
        if arms is not None and name not in arms:
            continue
        model = load_arm(name)
        for i, q0 in enumerate(poses(model, n_poses)):
            out.append(panel_case(model, name, i, q0, duration=duration))
    return out


def margin_table(margins: tuple[float, ...] = (0.995, 0.95, 0.9, 0.85)) -> list[dict]:
    """The demo's shake and gate goal retimed from READY at rest at each margin (the node's
    default options), executed by dyn_sim's default controller: saturation and peak |τ|/limit."""
    from dyn_node.core.check import on_demand
    from dyn_node.core.check.start_segment import StartState
    from dyn_node.core.check.trajectory import Trajectory
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.retime import retime
    from dyn_node.ros.demo.trajectories import READY, demo_trajectories
    from dyn_node.ros.fjt_client import quintic
    from dyn_node.sim.simulator import SimConfig, Simulator

    model = load_model(builtin="panda")
    dyn, opts = Dynamics(model), on_demand.options_for(Settings())
    ready = np.array(READY)
    shake = demo_trajectories()[1].validated(model.joint_names)
    g = quintic(list(ready), list(ready + np.eye(7)[0] * 0.5), 0.15)  # the demo gate's retimed goal
    gate = Trajectory(times=np.array(g["times"]), positions=np.array(g["points"]),
                      velocities=np.array(g["velocities"]), accelerations=np.array(g["accelerations"]))
    rows = []
    for goal, traj in (("shake", shake), ("gate", gate)):
        for m in margins:
            res = retime(dyn, traj, start=StartState(ready.copy(), np.zeros(7), 0.0), feasibility=opts,
                         limit_margin=m)
            sim = Simulator(model, SimConfig(initial_positions=READY))
            sim.execute_trajectory(res.trajectory, None)
            sat, peak = np.zeros(7, int), 0.0
            for _ in range(int(round((res.duration_out + 0.3) / sim.config.timestep))):
                st = sim.step()
                sat += st.saturated
                peak = max(peak, float((np.abs(st.effort) / sim.effort_limit).max()))
            rows.append(dict(goal=goal, margin=m, method=res.method, duration_s=res.duration_out,
                             planned_worst_ratio=res.check.worst_ratio, planned_worst=f"{res.check.worst_constraint} "
                             f"{res.check.worst_joint}", peak_effort_ratio=peak, saturated_ms=int(sat.max())))
    return rows


def run(quick: bool = False, smoke: bool = False) -> dict:
    from .common import progress

    n_poses = 1 if smoke else 2 if quick else 5
    progress("sim", f"panel: {len(ARMS)} arms × {n_poses} poses")
    cases = panel(n_poses, duration=1.5 if smoke else 3.0)
    progress("sim", "margins")
    margins = margin_table((0.995, 0.9) if smoke else (0.995, 0.95, 0.9, 0.85))
    return dict(cases=[{**asdict(c), "passed": c.passed} for c in cases],
                passed=sum(c.passed for c in cases), total=len(cases),
                max_error_rad=max(c.max_error_rad for c in cases),
                step_us_median=float(np.median([c.step_us for c in cases])), margins=margins)


def render_md(d: dict) -> str:
    rows = []
    for arm in dict.fromkeys(c["arm"] for c in d["cases"]):
        cs = [c for c in d["cases"] if c["arm"] == arm]
        rows.append([arm, cs[0]["integrator"], f"{sum(c['passed'] for c in cs)}/{len(cs)}",
                     f"{max(c['max_error_rad'] for c in cs):.2e}",
                     f"{max(c['max_speed_rad_s'] for c in cs):.3f} (≤ {cs[0]['speed_bound_rad_s']:.3f})",
                     f"{max(c['succeeded_s'] for c in cs):.3f}", f"{np.median([c['step_us'] for c in cs]):.0f}"])
    head = ["arm", "integrator", "passed", "max |q − q_ref| (rad)", "max |q̇| (rad/s)",
            "SUCCEEDED at (s, worst)", "µs per step (median)"]
    mrows = [[r["goal"], f"{r['margin']:g}", r["method"], f"{r['duration_s']:.3f}",
              f"{r['planned_worst']} {r['planned_worst_ratio']:.3f}", f"{r['peak_effort_ratio']:.3f}",
              str(r["saturated_ms"])] for r in d["margins"]]
    return (f"dyn_sim's controller panel (benchmarks/sim_bench.py): {d['passed']}/{d['total']} cases pass "
            f"(gentle 0.2 rad goal per joint; tracking ≤ 0.01 rad throughout, SUCCEEDED within the "
            f"duration + 0.5 s); worst tracking error {d['max_error_rad']:.2e} rad; a simulator step "
            f"(controller + MuJoCo) {d['step_us_median']:.0f} µs at the median.\n\n" + _table(head, rows)
            + "\n\nThe demo's goals retimed at each `retime.limit_margin`, executed by that controller:\n\n"
            + _table(["goal", "margin", "method", "answer (s)", "planned worst ratio", "peak |τ|/limit",
                      "saturated (ms)"], mrows))


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows])


if __name__ == "__main__":
    out = run(quick="--quick" in sys.argv, smoke="--smoke" in sys.argv)
    json.dump(out, sys.stdout, indent=1, default=float)
    print("\n" + render_md(out))
