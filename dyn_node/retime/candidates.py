"""What every candidate answer of the retimer passes before it may be returned, and the uniform
stretch candidate.

:func:`judge`: the exact check (:func:`~dyn_node.core.check.feasibility.check_trajectory`, the
retimer's options and start) and :func:`inside`, a screen of each output segment *between* its
points: the controller's quintic (cubic) evaluated at interior fractions, its velocity,
acceleration and jerk, and the RNEA torque and its rate there, against the limits. Until the
check evaluates every piece's extrema exactly, a segment whose polynomial swings between two
points that both pass (a velocity reversal inside 125 µs) would otherwise be answered.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from dyn_node.core.check.constraints import Violation
from dyn_node.core.check.feasibility import FeasibilityOptions, FeasibilityResult, check_trajectory
from dyn_node.core.check.trajectory import Trajectory, interpolate
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import TrajectoryError
from dyn_node.retime import timing
from dyn_node.retime.path import Path

#: interior fractions of each segment the screen evaluates (its ends are the check's points)
FRACTIONS = np.array([0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875])
#: how far over a limit an interior sample may be (the sums' rounding), relative
SLACK = 1e-6
#: the unit field of the screen's violations (they are ratios, found between points)
BETWEEN = "between points"
#: the stretch's factors over the check's time scale, tried in turn (docs/retime.md: every
#: answer ≤ 1.005 × the time scale × the input's duration)
STRETCH_PADS = (1.001, 1.005)


def inside(dynamics: Dynamics, out: Trajectory, share: float = 1.0) -> list[Violation]:
    """Interior samples of ``out``'s segments over ``share`` × (1 + :data:`SLACK`) of a joint
    limit (velocity, acceleration, jerk, effort, effort rate): one :class:`Violation` per joint
    and kind at its worst sample."""
    pp = interpolate(out, out.jtc_interpolation)
    dt = np.diff(out.times)
    f = np.concatenate(([0.0], FRACTIONS, [1.0]))
    r = dt[:, None] * f[None, :]
    seg = np.repeat(np.arange(len(dt)), len(f))
    c = pp.coeffs[seg]                                   # M × (deg+1) × nv
    x = r.ravel()[:, None]
    deg = c.shape[1] - 1
    vals = []
    for d in range(4):
        acc = np.zeros((len(x), c.shape[2]))
        for k in range(deg, d - 1, -1):
            fac = float(np.prod(np.arange(k - d + 1, k + 1))) if d else 1.0
            acc = acc * x + fac * c[:, k, :]
        vals.append(acc)
    Q, V, A, J = vals
    lim = dynamics.model.limits
    t = (out.times[:-1, None] + r).ravel()
    found = []
    for kind, value, limit in (("velocity", V, lim.velocity), ("acceleration", A, lim.acceleration),
                               ("jerk", J, lim.jerk)):
        found += _worst(kind, value, limit, t, lim.names, share)
    if np.any(np.isfinite(lim.effort)) or np.any(np.isfinite(lim.effort_rate)):
        tau = dynamics.rnea_batch(Q, V, A)
        if dynamics.model.task_limits.task_wrench is not None:
            from dyn_node.core.check import task_motion

            task = task_motion.build(dynamics, Q, V, A)
            if task is not None and task.task_torque is not None:
                tau = tau + task.task_torque   # a task wrench's torque: the check's effort has it
        found += _worst("effort", tau, lim.effort, t, lim.names, share)
        per = tau.reshape(len(dt), len(f), -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rate = np.diff(per, axis=1) / (dt[:, None, None] * np.diff(f)[None, :, None])
        tm = (out.times[:-1, None] + dt[:, None] * (0.5 * (f[1:] + f[:-1]))[None, :]).ravel()
        found += _worst("effort_rate", rate.reshape(-1, rate.shape[-1]), lim.effort_rate, tm,
                        lim.names, share)
    return found


def _worst(kind: str, value: np.ndarray, limit: np.ndarray, t: np.ndarray, names, share: float
           ) -> list[Violation]:
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(value) / limit
    ratio = np.where(np.isfinite(limit) & (limit > 0), ratio, 0.0)
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)
    out = []
    for j in np.flatnonzero(np.max(ratio, axis=0) > share * (1 + SLACK)):
        n = int(np.argmax(ratio[:, j]))
        out.append(Violation(joint=names[j], kind=kind, first_time_s=float(t[n]),
                             peak_time_s=float(t[n]), peak_value=float(ratio[n, j] * limit[j]),
                             limit=float(limit[j]), duration_s=0.0, unit=BETWEEN))
    return out


def judge(dynamics: Dynamics, out: Trajectory, options: FeasibilityOptions,
          start) -> tuple[FeasibilityResult, list[Violation]]:
    """The exact check of ``out`` and, when it passes, :func:`inside`: (the check, what is
    over between points); the answer may be returned only when the list is empty and the check
    feasible."""
    res = check_trajectory(dynamics, out, options, start=start)
    if not res.feasible:
        return res, list(res.violations)
    return res, inside(dynamics, out)


def describe(found: list[Violation]) -> str:
    v = max(found, key=lambda v: abs(v.peak_value) / v.limit)
    return (f"between points: {v.joint} {v.kind} {abs(v.peak_value) / v.limit:.3g}× its limit "
            f"at t = {v.peak_time_s:.4g} s")


def stretch(dynamics: Dynamics, path: Path, traj: Trajectory, k: float,
            options: FeasibilityOptions, start, period: float, moving_start: bool,
            dense) -> dict | None:
    """The input stretched by the check's time scale × :data:`STRETCH_PADS`: resampled as
    quintic points on the path (s = t/k; positions, velocities, accelerations), else, when the
    path's acceleration jumps at a knot (cubic points) so that no quintic follows it, the
    input's own points stretched (their interpolation is the one the check's k is of); each
    judged (:func:`judge`). With a moving start state the input's own points only."""
    from dyn_node.core.check.start_segment import stretched

    k = max(k, 1e-9) if k > 0 else 1.0
    tries = [(pad, False) for pad in STRETCH_PADS] if not moving_start else []
    if traj.velocities is not None:
        tries += [(pad, True) for pad in STRETCH_PADS]
    for pad, own in tries:
        kk = k * pad
        if own:
            out, dev = stretched(traj, kk), 0.0
        else:
            grid = np.linspace(path.pp.breaks[0], path.pp.breaks[-1], 2)
            lw = timing.law(grid, np.full(2, 1.0 / kk**2))
            out, dev = dense(path, lw, 0.0, period)
            if out is None:
                continue
        try:
            res, over = judge(dynamics, out, options, start)
        except TrajectoryError:
            continue
        if res.feasible and not over:
            return dict(trajectory=out, check=res, method="uniform", deviation=dev)
    return None


def plain(options: FeasibilityOptions) -> FeasibilityOptions:
    """``options`` without the payload margin (it does not decide feasibility)."""
    return replace(options, compute_payload_margin=False)

