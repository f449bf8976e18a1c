"""Issue 18's row of the "feasibility" section: the check with every joint kind and every task
kind configured, beside the same pinocchio.rnea loop on the same samples.

The task sections follow the README's keys: two frames with speed, acceleration and energy
limits, the robot's kinetic energy, a task wrench, base force and moment with tipping, and a
grasp holding a 1 kg payload. Limits are generous, as for the joint kinds, so the check runs to
the end and computes every share of the time scale instead of stopping at a violation.
"""
from __future__ import annotations

from typing import Any, Callable

from dyn_node.core.robot.model import Payload, load_model

#: the kinds issue 18 names, each of which the row must see in the result
TASK_KINDS = ("frame_speed", "frame_angular_speed", "frame_acceleration", "transferred_energy",
              "kinetic_energy", "base_force", "base_moment", "tipping", "grasp_slip")
FRAME_KINDS = TASK_KINDS[:4]
PAYLOAD = Payload(mass=1.0, com=(0.0, 0.0, 0.05), frame="panda_hand")
WHAT = ("check_trajectory on one thread with every joint kind AND every issue-18 kind (frames "
        "panda_link8 at 0.1 m and panda_link4: speed, angular speed, acceleration, transferred "
        "energy; kinetic energy; a 20 N task wrench; base force, moment and tipping; a grasp "
        "holding 1 kg at panda_hand; all within their limits) vs the same Python pinocchio.rnea loop on the same samples")


def task_sections() -> dict[str, Any]:
    """The limits-file sections beside ``joint_limits``: the README's example values, except a
    1 m/s frame speed (the trajectory's flange reaches about 0.6 m/s, over ISO 10218's 0.25)."""
    frame = dict(max_linear_speed=1.0, max_angular_speed=3.0, max_linear_acceleration=10.0,
                 max_transferred_energy=2.0)
    return {
        "frame_limits": {"panda_link8": dict(point=[0.0, 0.0, 0.1], **frame),
                         "panda_link4": dict(frame)},
        "robot_limits": {"max_kinetic_energy": 5.0},
        "task_wrench": {"frame": "panda_link8", "force": [0.0, 0.0, 20.0],
                        "torque": [0.0, 0.0, 0.0]},
        "base_limits": {"max_force": 400.0, "max_moment": 150.0, "base_mass": 20.0,
                        "base_com": [0.0, 0.0, 0.1],
                        "support_polygon": [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]},
        "grasp": {"frame": "panda_hand", "normal_axis": [0.0, 1.0, 0.0],
                  "friction_coefficient": 0.5, "grip_force": 40.0, "faces": 2},
    }


def expected_places() -> dict[str, set[str]]:
    """Place → kinds the result's ``per_frame`` must hold for the row to measure them all."""
    return {"panda_link8": set(FRAME_KINDS), "panda_link4": set(FRAME_KINDS),
            "robot_limits": {"kinetic_energy"},
            "base_limits": {"base_force", "base_moment", "tipping"}, "grasp": {"grasp_slip"}}


def setup(F, joint_limits: dict[str, Any], traj, options: dict[str, Any]):
    """(Dynamics of the Panda with every kind, the subjects by name) or a str: why not."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.errors import DynNodeError

    try:
        model = load_model(builtin="panda", limits_yaml={**joint_limits, **task_sections()},
                           payload=PAYLOAD)
    except DynNodeError as exc:
        return f"the limits file with the task sections is refused: {exc}"
    dyn = Dynamics(model)
    subjects: dict[str, Callable[[], object]] = {
        "check_task": lambda: F.check_trajectory(dyn, traj, options["check"]),
        "check_task_nm": lambda: F.check_trajectory(dyn, traj, options["check_nm"])}
    return dyn, subjects


def coverage_gap(result) -> str | None:
    """What the result lacks of :func:`expected_places` (None: every kind was checked)."""
    per_frame = result.per_frame
    gaps = [f"{place}: {', '.join(sorted(kinds - set(per_frame.get(place, {}))))}"
            for place, kinds in expected_places().items()
            if kinds - set(per_frame.get(place, {}))]
    return f"the check did not report {'; '.join(gaps)}" if gaps else None


def row(runs: list[dict], result, reason: str | None) -> dict[str, Any]:
    """The bench.json entry: medians over the measuring processes, or why not available."""
    import statistics

    if reason:
        return dict(status=f"not available: {reason}", what=WHAT)

    def med(key: str, table: str) -> float:
        return statistics.median(r[table][key] for r in runs)

    worst = max(((p, k, float(e["ratio"])) for p, kinds in result.per_frame.items()
                 for k, e in kinds.items()), key=lambda x: x[2])
    return dict(status="ok", what=WHAT, target="≤ 2.0× (issue 18)",
                check_s=med("check_task", "median_s"), ratio=med("check_task", "ratio"),
                check_no_margin_s=med("check_task_nm", "median_s"),
                ratio_no_margin=med("check_task_nm", "ratio"),
                ratio_no_margin_by_process=[r["ratio"]["check_task_nm"] for r in runs],
                ratio_by_process=[r["ratio"]["check_task"] for r in runs],
                joint_kinds_ratio_no_margin=med("check_nm", "ratio"),
                feasible=bool(result.feasible), time_scale=float(result.time_scale),
                worst_task=dict(place=worst[0], kind=worst[1], ratio=worst[2]))
