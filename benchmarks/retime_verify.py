"""Independent verification of a retimed trajectory and the bench's waypoint and hard paths.

:func:`verify` interpolates the output's points as joint_trajectory_controller does (SciPy's
``BPoly.from_derivatives``: quintic with accelerations, cubic with velocities only) and samples
every segment inside, not only at its ends; torques by Pinocchio's own ``rnea`` (plus the URDF's
friction) one sample at a time: nothing of the check's interpolation, peaks or compiled kernels.
"""
from __future__ import annotations

import numpy as np

#: samples per output segment (both ends included)
PER_SEGMENT = 17
#: libfranka's acceleration and jerk maxima (rad/s², rad/s³)
PANDA_ACC = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
PANDA_JERK = [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]


def panda(effort_share: float = 0.4, effort_rate: float = 1000.0):
    """The built-in Panda with libfranka's acceleration and jerk limits, effort at
    ``effort_share`` of the URDF's and the given effort rate (N·m/s)."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model

    m = load_model(builtin="panda")
    lim = {j: {"has_acceleration_limits": True, "max_acceleration": a, "has_jerk_limits": True,
               "max_jerk": jk, "has_effort_limits": True, "max_effort": effort_share * float(e),
               "max_effort_rate": effort_rate}
           for j, a, jk, e in zip(m.limits.names, PANDA_ACC, PANDA_JERK, m.limits.effort)}
    return Dynamics(m.with_limits({"joint_limits": lim}))


def catmull_rom(times: np.ndarray, P: np.ndarray):
    """Waypoints passed at speed: velocities (P[i+1] − P[i−1]) / (t[i+1] − t[i−1]) inside, rest
    at both ends (a planner's cubic points)."""
    from dyn_node.core.check.trajectory import Trajectory

    V = np.zeros_like(P)
    V[1:-1] = (P[2:] - P[:-2]) / (times[2:] - times[:-2])[:, None]
    return Trajectory(times=np.asarray(times, float), positions=P, velocities=V)


def waypoint_path(dyn, rng, n: int, segment_s: float | None = None, spread: float = 0.7,
                  step: float | None = None):
    """``n`` waypoints in the middle ``spread`` of each joint's range (15–85 %), gravity under 80 % of the effort limit
    at each, timed 1.2× the slowest joint's velocity-limited step (or ``segment_s`` a step),
    Catmull-Rom velocities."""
    from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory

    lim = dyn.model.limits
    for _ in range(1000):
        P = _draw(dyn, rng, n, spread, step)
        if segment_s is None:
            steps = np.max(np.abs(np.diff(P, axis=0)) / lim.velocity, axis=1) * 1.2
        else:
            steps = np.full(n - 1, segment_s)
        tr = catmull_rom(np.concatenate(([0.0], np.cumsum(steps))), P)
        # a curve some slowdown makes feasible (its cubic may overshoot a position limit)
        k = check_trajectory(dyn, tr, FeasibilityOptions(compute_payload_margin=False)).time_scale
        if np.isfinite(k):
            return tr
    raise RuntimeError("no waypoint path some slowdown makes feasible in 1000 draws")


def _draw(dyn, rng, n: int, spread: float, step: float | None) -> np.ndarray:
    """``n`` waypoints, each drawn until gravity there is under 80 % of the effort limits:
    uniform in the middle ``spread`` of each range, or (``step``) each a uniform step of at
    most ``step`` rad per joint from the previous one, kept in that middle."""
    lim = dyn.model.limits
    lo, hi = lim.position_lower, lim.position_upper
    a, b = lo + (hi - lo) * (1 - spread) / 2, hi - (hi - lo) * (1 - spread) / 2
    P = []
    while len(P) < n:
        if step is None or not P:
            q = a + (b - a) * rng.random(dyn.model.nv)
        else:
            q = np.clip(P[-1] + step * (2 * rng.random(dyn.model.nv) - 1), a, b)
        if np.all(np.abs(dyn.gravity_batch(q[None, :])[0]) < 0.8 * lim.effort):
            P.append(q)
    return np.array(P)


def verify(dyn, out) -> dict[str, float]:
    """Worst |value| ÷ limit per kind (position: distance beyond the range, rad) over the
    controller's interpolation of ``out`` sampled :data:`PER_SEGMENT` times per segment."""
    import pinocchio as pin
    from scipy.interpolate import BPoly

    cols = [out.positions, out.velocities]
    if out.accelerations is not None:
        cols.append(out.accelerations)
    pp = BPoly.from_derivatives(out.times, np.stack(cols, axis=1))
    frac = np.linspace(0.0, 1.0, PER_SEGMENT)
    t0, dt = out.times[:-1], np.diff(out.times)
    t = (t0[:, None] + dt[:, None] * frac[None, :]).ravel()
    # at a segment's end the next segment's polynomial would be used: step back by rounding
    t = np.minimum(t, np.repeat(out.times[1:], PER_SEGMENT) * (1 - 1e-15))
    Q, V, A = pp(t), pp(t, 1), pp(t, 2)
    J = pp(t, 3)
    pm = dyn.model.pin_model
    data = pm.createData()
    damp, coul = np.asarray(pm.damping), np.asarray(pm.friction)
    tau = np.array([pin.rnea(pm, data, q, v, a) + damp * v + coul * np.sign(v)
                    for q, v, a in zip(Q, V, A)])
    seg_tau = tau.reshape(len(dt), PER_SEGMENT, -1)
    rate = np.diff(seg_tau, axis=1) / (dt[:, None, None] / (PER_SEGMENT - 1))
    lim = dyn.model.limits

    def worst(x, limit):
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(x) / limit
        r = np.where(np.isfinite(limit), r, 0.0)
        return float(np.nanmax(r)) if r.size else 0.0

    beyond = np.maximum(Q - lim.position_upper, lim.position_lower - Q)
    return {"position": float(max(0.0, np.max(beyond))),
            "velocity": worst(V, lim.velocity), "acceleration": worst(A, lim.acceleration),
            "jerk": worst(J, lim.jerk), "effort": worst(tau, lim.effort),
            "effort_rate": worst(rate.reshape(-1, rate.shape[-1]), lim.effort_rate),
            "shortest_segment_s": float(np.min(dt))}


def passes(report: dict[str, float], rel: float = 1e-3) -> bool:
    """Every kind within its limit (× 1 + ``rel``: the finite differences' and sums' rounding),
    nothing beyond the position range by more than 1e-9 rad."""
    return report["position"] <= 1e-9 and all(
        v <= 1.0 + rel for k, v in report.items() if k not in ("position", "shortest_segment_s"))
