"""Self-test of a loaded model: dynamics identities at seeded random states, and its limits.

Checks (each one :class:`~dyn_node.core.robot.status.Status` with its figures):
- ``rnea_identity``: rnea(q, v, a) = M(q)·a + h(q, v), max |difference| over the states (N·m);
- ``gravity_identity``: gravity(q) = rnea(q, 0, 0) (N·m);
- ``mass_matrix``: M(q) built column by column from RNEA (M e_j = rnea(q, 0, e_j) − g(q)) equals
  the CRBA mass matrix, is symmetric, and its smallest eigenvalue is positive (kg·m²);
- ``limits``: the model's limits are consistent (lower ≤ upper, positive maxima; see
  :func:`dyn_node.core.robot.limits.check_limits`).
Tolerances are relative to the torque scale of the model, so the test is unit-independent.
"""
from __future__ import annotations

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import EVALUATION_ERROR
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status
from dyn_node.core.robot.units import joint_units

SELF_TEST = NAME_PREFIX + "self_test"
REL_TOL = 1e-9


def random_states(model: RobotModel, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n seeded (q, v, a) states: q inside the position limits (±π where unlimited), v and a in ±2."""
    rng = np.random.default_rng(seed)
    lim = model.limits
    lo = np.where(np.isfinite(lim.position_lower), lim.position_lower, -np.pi)
    hi = np.where(np.isfinite(lim.position_upper), lim.position_upper, np.pi)
    hi = np.maximum(hi, lo)
    return (rng.uniform(lo, hi, (n, model.nv)), rng.uniform(-2, 2, (n, model.nv)),
            rng.uniform(-2, 2, (n, model.nv)))


def _status(check: str, ok: bool, message: str, hid: str, vals: dict, level_bad: int = ERROR) -> Status:
    if not ok:
        vals["failure_label"] = EVALUATION_ERROR
    return Status(f"{SELF_TEST}/{check}", OK if ok else level_bad, message, hid, vals)


def run_self_test(model: RobotModel, include_friction: bool = True, n_states: int = 16,
                  seed: int = 0, hardware_id: str = "") -> tuple[bool, list[Status]]:
    """Run every check; returns (all passed, one status per check). WARN counts as passed."""
    dyn = Dynamics(model, DynamicsOptions(include_friction=include_friction))
    Q, V, A = random_states(model, n_states, seed)
    scale = 1.0
    err_id = err_g = err_m = asym = 0.0
    min_eig = np.inf
    for q, v, a in zip(Q, V, A):
        tau = dyn.rnea(q, v, a)
        M = dyn.mass_matrix(q)
        scale = max(scale, float(np.max(np.abs(tau))))
        err_id = max(err_id, float(np.max(np.abs(tau - (M @ a + dyn.bias(q, v))))))
        g = dyn.gravity(q)
        g_rnea = dyn.rnea(q, np.zeros(model.nv), np.zeros(model.nv))
        err_g = max(err_g, float(np.max(np.abs(g - g_rnea))))
        cols = np.column_stack([dyn.rnea(q, np.zeros(model.nv), e) - g_rnea for e in np.eye(model.nv)])
        err_m = max(err_m, float(np.max(np.abs(cols - M))))
        asym = max(asym, float(np.max(np.abs(cols - cols.T))))
        min_eig = min(min_eig, float(np.min(np.linalg.eigvalsh(M))))
    tol = REL_TOL * scale
    common = {"states": n_states, "seed": seed, "tolerance_nm": tol}
    # figures over all joints, in their units: "N·m", "N" (prismatic only) or "N·m or N"
    units = joint_units(model)
    eff, inertia = (" or ".join(dict.fromkeys(units[k])) for k in ("effort", "inertia"))
    out = [
        _status("rnea_identity", err_id <= tol,
                f"rnea = M·q̈ + h within {err_id:.3g} {eff} over {n_states} states",
                hardware_id, {**common, "max_error_nm": err_id}),
        _status("gravity_identity", err_g <= tol,
                f"gravity = rnea(q, 0, 0) within {err_g:.3g} {eff} over {n_states} states",
                hardware_id, {**common, "max_error_nm": err_g}),
        _status("mass_matrix", err_m <= tol and asym <= tol and min_eig > 0,
                f"M(q) symmetric positive definite: smallest eigenvalue {min_eig:.4g} {inertia}, "
                f"asymmetry {asym:.3g}, CRBA vs RNEA columns {err_m:.3g}",
                hardware_id, {**common, "min_eigenvalue_kg_m2": min_eig, "max_asymmetry": asym,
                              "max_crba_vs_rnea": err_m}),
    ]
    warnings = model.limits.warnings
    lim = model.limits
    inverted = int(np.sum(lim.position_lower > lim.position_upper) + np.sum(lim.soft_lower > lim.soft_upper))
    lvals = {"warnings": len(warnings), "inverted_ranges": inverted,
             "joints_with_effort_limit": int(np.sum(np.isfinite(lim.effort))),
             "joints_with_velocity_limit": int(np.sum(np.isfinite(lim.velocity)))}
    for i, w in enumerate(warnings, 1):
        lvals[f"warning_{i}"] = w
    if inverted:
        out.append(_status("limits", False, warnings[0] if warnings else "inverted limit range", hardware_id, lvals))
    elif warnings:
        out.append(_status("limits", False, f"check the limits: {warnings[0]}", hardware_id, lvals, WARN))
    else:
        out.append(_status("limits", True, f"limits consistent for {model.nv} joints", hardware_id, lvals))
    return all(s.level in (OK, WARN) for s in out), out
