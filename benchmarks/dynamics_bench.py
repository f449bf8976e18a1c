"""Section "dynamics": inverse dynamics per call and over a batch of states, dyn_node vs peers.

Every implementation first computes τ on the same seeded states and is compared with dyn_node's
batched path; one that differs by more than 1e-9 N·m is reported as disagreeing and not timed.
dyn_node runs with friction off here: the peers compute rigid-body RNEA only (Panda's URDF carries
0.003 N·m·s/rad damping that pinocchio.rnea, KDL and mj_inverse-with-damping-zeroed do not add).
"""
from __future__ import annotations

import json
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.robot.model import load_model

from .common import SYSTEM_PYTHON, NotAvailable, median_time, progress, system_pykdl
from .mujoco_ref import MujocoInverse
from .numpy_rnea import NumpyRNEA

TOLERANCE = 1e-9  # N·m
ROBOTS = ("panda", "ur5", "planar_2link")


def random_states(model, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n seeded states: q inside the position limits (±π where unlimited), |v| ≤ 2, |a| ≤ 5."""
    rng = np.random.default_rng(seed)
    lim = model.limits
    lo = np.where(np.isfinite(lim.position_lower), lim.position_lower, -np.pi)
    hi = np.where(np.isfinite(lim.position_upper), lim.position_upper, np.pi)
    nv = model.nv
    return (rng.uniform(lo, hi, (n, nv)), rng.uniform(-2, 2, (n, nv)), rng.uniform(-5, 5, (n, nv)))


def _loop(fn, Q, V, A) -> np.ndarray:
    return np.array([fn(Q[i], V[i], A[i]) for i in range(len(Q))])


class _PinParallel:
    def __init__(self, pm, threads: int):
        self.pm, self.threads = pm, threads
        self.pool = pin.ModelPool(pm, threads)

    def batch(self, Q, V, A):
        out = np.empty((self.pm.nv, len(Q)), order="F")
        pin.rneaInParallel(self.threads, self.pool, np.ascontiguousarray(Q).T,
                           np.ascontiguousarray(V).T, np.ascontiguousarray(A).T, out)
        return out.T


def _kdl(model, Q, V, A, repeats: int) -> tuple[np.ndarray, float]:
    ok, why = system_pykdl()
    if not ok:
        raise NotAvailable(f"skipped: not installed: {why}")
    job = dict(urdf=model.urdf, joint_names=list(model.joint_names), locked=dict(model.locked_joints),
               gravity=[float(g) for g in model.pin_model.gravity.linear],
               Q=Q.tolist(), V=V.tolist(), A=A.tolist(), repeats=repeats)
    p = subprocess.run([SYSTEM_PYTHON, str(Path(__file__).with_name("kdl_worker.py"))],
                       input=json.dumps(job), capture_output=True, text=True,
                       env={"PATH": "/usr/bin:/bin"}, timeout=300)
    if p.returncode != 0:
        raise NotAvailable(f"KDL worker failed: {p.stderr.strip().splitlines()[-1:]}")
    r = json.loads(p.stdout)
    return np.array(r["tau"]), float(np.median(r["loop_s"]))


def run(quick: bool = False, smoke: bool = False) -> dict:
    """``quick``: 1,000 states; ``smoke``: 50 states, one repeat (tests only, figures meaningless)."""
    n_batch = 50 if smoke else 1000 if quick else 10_000
    n_call = 20 if smoke else 300 if quick else 2000
    repeats = 1 if smoke else 3 if quick else 7
    rows = []
    for robot in ROBOTS:
        model = load_model(builtin=robot)
        pm = model.pin_model
        dyn = Dynamics(model, DynamicsOptions(include_friction=False, include_armature=True))
        Q, V, A = random_states(model, n_batch)
        Qc, Vc, Ac = Q[:n_call], V[:n_call], A[:n_call]
        ref = dyn.rnea_batch(Q, V, A)
        pdata = pm.createData()
        npr = NumpyRNEA(pm)

        def pin_call(q, v, a, pm=pm, d=pdata):
            return pin.rnea(pm, d, q, v, a)

        # name, what it measures, single-call fn or None, batch fn (all states) or None
        subjects: list[tuple[str, str, object, object]] = [
            ("dyn_node Dynamics.rnea_batch", "dyn_node's batched path (rneaInParallel on all cores + "
             "friction/armature terms)", None, lambda: dyn.rnea_batch(Q, V, A)),
            ("dyn_node Dynamics.rnea", "dyn_node's single-state call; batch = Python loop over it",
             dyn.rnea, lambda: _loop(dyn.rnea, Q, V, A)),
            ("pinocchio.rnea Python loop", "plain Python loop calling pinocchio.rnea per state",
             pin_call, lambda: _loop(pin_call, Q, V, A)),
        ]
        for threads in (1, 2):
            par = _PinParallel(pm, threads)
            subjects.append((f"pinocchio rneaInParallel ({threads} thread{'s' if threads > 1 else ''})",
                             "Pinocchio's own C++ batch over all states", None,
                             lambda par=par: par.batch(Q, V, A)))
        try:
            mj = MujocoInverse(model)
            subjects.append(("MuJoCo mj_inverse", f"mj_inverse per state from Python ({mj.source}; "
                             "damping, armature, contacts, constraints off)",
                             mj.rnea, lambda mj=mj: _loop(mj.rnea, Q, V, A)))
        except Exception as exc:  # MuJoCo refusing the URDF is a row, not a crash
            rows.append(dict(robot=robot, impl="MuJoCo mj_inverse", status=f"not available: {exc}"))
        subjects.append(("NumPy textbook RNEA", "benchmarks/numpy_rnea.py, vectorised over states; "
                         "per call = batch of one", npr.rnea, lambda: npr.rnea_batch(Q, V, A)))

        jobs: list[tuple[dict, str, object, int]] = []  # (row, key, fn, states per run)
        for name, what, call, batch in subjects:
            progress("dynamics", f"{robot}: {name}: agreement check")
            row = dict(robot=robot, impl=name, what=what, nv=model.nv, n_batch=n_batch, n_call=n_call)
            out = batch() if batch is not None else _loop(call, Q, V, A)
            row["max_abs_diff_Nm"] = float(np.max(np.abs(out - ref)))
            rows.append(row)
            if not row["max_abs_diff_Nm"] <= TOLERANCE:
                row["status"] = f"DISAGREES with dyn_node by {row['max_abs_diff_Nm']:.3g} N·m: not timed"
                continue
            row["status"] = "ok"
            if call is not None:
                # Slow single calls (the NumPy baseline, ~1 ms) get fewer calls per repeat so a
                # repeat stays near 0.2 s; fast ones use all n_call.
                t20, _ = median_time(lambda call=call: [call(Qc[i], Vc[i], Ac[i]) for i in range(20)], 1)
                m = int(min(n_call, max(20, 0.2 / max(t20 / 20, 1e-9))))
                row["n_call"] = m
                jobs.append((row, "per_call", lambda call=call, m=m: [call(Qc[i], Vc[i], Ac[i])
                                                                   for i in range(m)], m))
            if batch is not None:
                jobs.append((row, "batch", batch, n_batch))
        # Round-robin repeats: load from other processes drifts over seconds, and interleaving
        # spreads it over every implementation alike instead of penalising whichever ran then.
        progress("dynamics", f"{robot}: timing {len(jobs)} measurements × {repeats} repeats, interleaved")
        samples: list[list[float]] = [[] for _ in jobs]
        for _, _, fn, _ in jobs:
            fn()  # warm-up
        for _ in range(repeats):
            for k, (_, _, fn, _) in enumerate(jobs):
                t0 = time.perf_counter()
                fn()
                samples[k].append(time.perf_counter() - t0)
        for (row, key, _, n), ts in zip(jobs, samples):
            t = statistics.median(ts)
            if key == "per_call":
                row["per_call_us"] = t / n * 1e6
            else:
                row["batch_s"] = t
                row["batch_per_state_us"] = t / n * 1e6

        progress("dynamics", f"{robot}: PyKDL ChainIdSolver_RNE")
        row = dict(robot=robot, impl="PyKDL ChainIdSolver_RNE",
                   what="Debian python3-pykdl under /usr/bin/python3 (subprocess), chain built from "
                        "the URDF here; Python loop per state incl. JntArray filling",
                   nv=model.nv, n_batch=n_batch, n_call=n_batch)
        try:
            tau, loop_s = _kdl(model, Q, V, A, repeats)
            row["max_abs_diff_Nm"] = float(np.max(np.abs(tau - ref)))
            if row["max_abs_diff_Nm"] <= TOLERANCE:
                row.update(status="ok", batch_s=loop_s, batch_per_state_us=loop_s / n_batch * 1e6,
                           per_call_us=loop_s / n_batch * 1e6)
            else:
                row["status"] = f"DISAGREES with dyn_node by {row['max_abs_diff_Nm']:.3g} N·m: not timed"
        except NotAvailable as exc:
            row["status"] = str(exc)
        rows.append(row)

        # Ratios against the plain Python pinocchio loop, measured in this run.
        base = next(r for r in rows if r["robot"] == robot and r["impl"] == "pinocchio.rnea Python loop")
        for r in rows:
            if r["robot"] != robot:
                continue
            if "batch_s" in r and "batch_s" in base:
                r["batch_vs_pin_loop"] = r["batch_s"] / base["batch_s"]
            if "per_call_us" in r and "per_call_us" in base:
                r["per_call_vs_pin_call"] = r["per_call_us"] / base["per_call_us"]
    return dict(rows=rows, n_batch=n_batch, n_call=n_call, repeats=repeats, tolerance_Nm=TOLERANCE,
                interleaved=True,
                note="dyn_node with friction off (rigid-body RNEA, as the peers compute); states "
                     "seeded, q within limits, |v| ≤ 2 rad/s, |a| ≤ 5 rad/s²")
