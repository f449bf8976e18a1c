"""``dyn_sim --check-physics --out DIR``: the free-motion and the contact test of the simulator.

Free motion: the robot released at rest from the start pose with the controller off, no
damping, no friction, joint limits and contacts off; E = kinetic + potential energy from MuJoCo
(mjENBL_ENERGY); ``energy_error_rel`` = max|E(t) − E(0)| ÷ the peak kinetic energy, for every
(integrator, timestep) of the grid; the nominal run is dyn_sim's (RK4, 1 ms). Contact: the
Panda's hand pressed on the table of the press scene and held; the largest penetration, the
normal force and its variation over the held last second (chatter), and the static balance
Σ Jᵀ·W + τ = g(q) (Pinocchio), for the nominal solver settings and perturbed ones (stiffness,
timestep, no-slip, integrator). Each writes an EvidenceRecord and a plot. Exit 0 both hold, 1 one fails,
2 bad input. Method and thresholds: docs/SIMULATOR.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import mujoco
import numpy as np

from dyn_node.core.robot.model import RobotModel, model_from_source
from dyn_node.audit.evidence import utc_now
from dyn_node.errors import DynNodeError
from dyn_node.sim.mujoco_model import mujoco_from_model
from dyn_node.sim.press import PRESS_SCENE, READY, plan_press, static_balance
from dyn_node.sim.scene import INTEGRATORS, SolverSettings
from dyn_node.sim.simulator import DEFAULT_TIMESTEP, SimConfig, Simulator, default_initial_positions

ENERGY_TOL = 1e-2
PENETRATION_TOL_M = 5e-3
CHATTER_TOL = 0.05      # (max − min) ÷ mean of the normal force over the held second
BALANCE_TOL = 1e-3      # max|Σ Jᵀ·W + τ − g| ÷ max|g|
FREE_DURATION_S = 3.0
HOLD_S = 1.0
SETTLE_S = 2.0
FREE_GRID = (("euler", 0.002), ("euler", 0.001), ("euler", 0.0005), ("euler", 0.00025),
             ("rk4", 0.002), ("rk4", 0.001), ("rk4", 0.0005))
NOMINAL = (SolverSettings().integrator, DEFAULT_TIMESTEP)  # dyn_sim's own defaults
#: the timesteps dyn_sim takes (its ``timestep`` parameter's range): 1e-300 s would never end
MIN_TIMESTEP, MAX_TIMESTEP = 1e-4, 0.01


def free_motion_run(model: RobotModel, q0: np.ndarray, *, integrator: str, timestep: float,
                    duration: float = FREE_DURATION_S) -> dict[str, Any]:
    """One free-motion run: time, q, v and MuJoCo's energies sampled every step (after it)."""
    robot = mujoco_from_model(model, damping=False, armature=True, frictionloss=False,
                              contacts=False, joint_limits=False, timestep=timestep)
    mj = robot.model
    SolverSettings(integrator=integrator).apply(mj)
    mj.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    d = mujoco.MjData(mj)
    robot.set_state(d, q0)
    n = int(round(duration / timestep))
    E = np.empty((n, 2))
    Q, V = np.empty((n, model.nv)), np.empty((n, model.nv))
    for k in range(n):
        Q[k], V[k] = robot.get_q(d), robot.get_v(d)
        # the energy of this very state (after an RK4 step data.energy is a later stage's)
        mujoco.mj_forward(mj, d)
        E[k] = d.energy
        mujoco.mj_step(mj, d)
    total = E.sum(axis=1)
    peak_ke = float(E[:, 1].max())
    return {"integrator": integrator, "timestep_s": timestep, "t": np.arange(n) * timestep,
            "q": Q, "v": V, "potential": E[:, 0], "kinetic": E[:, 1],
            "energy_error_rel": float(np.abs(total - total[0]).max() / max(peak_ke, 1e-12)),
            "peak_kinetic_j": peak_ke, "finite": bool(np.all(np.isfinite(total)))}


def free_motion(model: RobotModel, q0: np.ndarray, *, nominal: tuple[str, float] = NOMINAL,
                duration: float = FREE_DURATION_S) -> dict[str, Any]:
    """The grid of runs (plus ``nominal`` if not in it), the nominal one's figure and the error
    ratio per timestep halving."""
    grid = FREE_GRID if nominal in FREE_GRID else (*FREE_GRID, nominal)
    runs = [free_motion_run(model, q0, integrator=i, timestep=h, duration=duration) for i, h in grid]
    nominal = next(r for r in runs if (r["integrator"], r["timestep_s"]) == nominal)
    halving = []
    for a, b in zip(runs, runs[1:]):
        if a["integrator"] == b["integrator"]:
            halving.append({"integrator": a["integrator"], "timestep_s": b["timestep_s"],
                            "error_ratio": a["energy_error_rel"] / max(b["energy_error_rel"], 1e-300)})
    ok = nominal["finite"] and nominal["energy_error_rel"] < ENERGY_TOL
    return {"nominal": nominal, "runs": runs, "halving": halving, "passed": ok, "tolerance": ENERGY_TOL}


def contact_run(model: RobotModel, *, solver: SolverSettings, timestep: float, label: str) -> dict[str, Any]:
    """The held press: normal force, penetration and balance sampled every step of the last second."""
    sim = Simulator(model, SimConfig(timestep=timestep, initial_positions=READY, scene=PRESS_SCENE,
                                     solver=solver, energy=True))
    plan = plan_press(sim)
    sim.execute(list(model.joint_names), *plan.waypoints())
    steps_before = int(round((plan.t_press + SETTLE_S) / timestep))
    first_contact = None
    max_pen = 0.0
    fn_all = np.zeros(steps_before)  # the whole press, for the plot
    for k in range(steps_before):
        sim.step()
        truth = sim.contact_truth()
        if truth.active and first_contact is None:
            first_contact = sim.time
        max_pen = max(max_pen, truth.max_penetration_m)
        fn_all[k] = truth.normal_force_n
    n_hold = int(round(HOLD_S / timestep))
    fn, pen, ncon = np.empty(n_hold), np.empty(n_hold), np.empty(n_hold, dtype=int)
    for k in range(n_hold):
        sim.step()
        truth = sim.contact_truth()
        fn[k], pen[k], ncon[k] = truth.normal_force_n, truth.max_penetration_m, len(truth.contacts)
    max_pen = max(max_pen, float(pen.max()))
    balance = static_balance(model, sim.q, sim.state().effort, truth)
    mean = float(fn.mean())
    chatter = float((fn.max() - fn.min()) / mean) if mean > 0 else float("inf")
    return {"label": label, "timestep_s": timestep, "solver": solver.to_dict(),
            "max_penetration_m": max_pen, "normal_force_n": mean, "normal_force_variation_rel": chatter,
            "contacts_min": int(ncon.min()), "contacts_max": int(ncon.max()),
            "balance_residual_rel": balance.residual_rel, "first_contact_s": first_contact,
            "max_speed_rad_s": float(np.abs(sim.v).max()), "t_hold": sim.time - HOLD_S + np.arange(1, n_hold + 1) * timestep,
            "normal_force": fn, "t_press": np.arange(1, steps_before + 1) * timestep, "normal_force_press": fn_all,
            "plan": {"q_press": plan.q_press, "q_approach": plan.q_approach,
                                         "t_approach_s": plan.t_approach, "t_press_s": plan.t_press}}


def contact_failures(run: dict[str, Any]) -> list[str]:
    """What a contact run fails, one phrase each (empty: it holds)."""
    out = []
    if not run["max_penetration_m"] < PENETRATION_TOL_M:
        out.append(f"penetration {run['max_penetration_m'] * 1e3:.3g} mm ≥ {PENETRATION_TOL_M * 1e3:g} mm")
    if not run["normal_force_n"] > 0:
        out.append("no normal force during the hold")
    if not run["normal_force_variation_rel"] < CHATTER_TOL:
        out.append(f"normal force varies {run['normal_force_variation_rel']:.3g} (chatter) over the held second")
    if not run["balance_residual_rel"] < BALANCE_TOL:
        out.append(f"static balance off by {run['balance_residual_rel']:.3g} of max|g|")
    return out


def contact(model: RobotModel) -> dict[str, Any]:
    """Nominal press plus perturbed stiffness (solref time constant ×½, ×2), timestep ½, no-slip
    off and the Euler integrator."""
    base = SolverSettings()
    nominal = contact_run(model, solver=base, timestep=NOMINAL[1], label="nominal")
    perturbed = [
        contact_run(model, solver=dataclasses.replace(base, solref=(0.01, 1.0)), timestep=NOMINAL[1],
                    label="stiffer (solref 0.01 s)"),
        contact_run(model, solver=dataclasses.replace(base, solref=(0.04, 1.0)), timestep=NOMINAL[1],
                    label="softer (solref 0.04 s)"),
        contact_run(model, solver=base, timestep=NOMINAL[1] / 2, label="timestep 0.5 ms"),
        contact_run(model, solver=dataclasses.replace(base, noslip_iterations=0), timestep=NOMINAL[1],
                    label="no-slip off (MuJoCo default)"),
        contact_run(model, solver=dataclasses.replace(base, integrator="euler"), timestep=NOMINAL[1],
                    label="integrator euler (MuJoCo default)"),
    ]
    return {"nominal": nominal, "perturbed": perturbed, "failures": contact_failures(nominal),
            "passed": not contact_failures(nominal), "q0": READY,
            "scene": [dataclasses.asdict(o) for o in PRESS_SCENE.objects],
            "tolerances": {"max_penetration_m": PENETRATION_TOL_M, "normal_force_variation_rel": CHATTER_TOL,
                           "balance_residual_rel": BALANCE_TOL}}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dyn_sim --check-physics",
        description="The simulator's free-motion and contact tests; evidence and plots in --out.")
    p.add_argument("--out", required=True, help="output directory (free_motion/, contact/)")
    p.add_argument("--robot-model", default="panda",
                   help="built-in robot for free motion (the contact test is the Panda's press)")
    p.add_argument("--integrator", default=NOMINAL[0], choices=sorted(INTEGRATORS),
                   help=f"integrator of the nominal free-motion run (dyn_sim's default: {NOMINAL[0]})")
    p.add_argument("--timestep", type=float, default=NOMINAL[1], help="its timestep (s)")
    p.add_argument("--only", choices=("free_motion", "contact"), help="run one check")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Exit 0: every check run holds; 1: one fails; 2: bad input."""
    parser = _parser()
    try:
        a = parser.parse_args(argv)
    except SystemExit as exc:
        return 0 if exc.code == 0 else 2
    out = Path(a.out)
    try:
        if not (MIN_TIMESTEP <= a.timestep <= MAX_TIMESTEP):  # NaN fails too
            raise DynNodeError(f"--timestep must be in [{MIN_TIMESTEP:g}, {MAX_TIMESTEP:g}] s (dyn_sim's "
                               f"range), got {a.timestep:g}", code="bad_timestep")
        out.mkdir(parents=True, exist_ok=True)
        model = model_from_source("", "", a.robot_model)
        panda = model if model.name == "panda" else model_from_source("", "", "panda")
    except (DynNodeError, OSError) as exc:
        print(f"dyn_sim --check-physics: {exc}", file=sys.stderr)
        return 2
    try:
        passed = _run(a, model, panda, out)
    except OSError as exc:  # a full disk, a read-only --out: one line, bad input
        print(f"dyn_sim --check-physics: cannot write the evidence in {out}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    return 0 if all(passed) else 1


def _run(a: argparse.Namespace, model: RobotModel, panda: RobotModel, out: Path) -> list[bool]:
    """The checks asked for, each writing its evidence under ``out``: whether each holds."""
    from dyn_node.sim.physics_report import write_contact, write_free_motion

    passed = []
    if a.only in (None, "free_motion"):
        q0 = np.asarray(READY) if model.name == "panda" else default_initial_positions(model)
        started, t0 = utc_now(), time.monotonic()
        fm = free_motion(model, q0, nominal=(a.integrator, a.timestep))
        write_free_motion(out / "free_motion", model, fm, q0=q0, started=started, seconds=time.monotonic() - t0)
        n = fm["nominal"]
        print(f"free motion: energy_error_rel {n['energy_error_rel']:.3g} ({n['integrator']}, "
              f"{n['timestep_s'] * 1e3:g} ms) {'OK' if fm['passed'] else 'FAIL'} (< {ENERGY_TOL:g})")
        passed.append(fm["passed"])
    if a.only in (None, "contact"):
        started, t0 = utc_now(), time.monotonic()
        ct = contact(panda)
        write_contact(out / "contact", panda, ct, started=started, seconds=time.monotonic() - t0)
        n = ct["nominal"]
        print(f"contact: max_penetration_m {n['max_penetration_m']:.3g}, normal_force_n "
              f"{n['normal_force_n']:.4g}, variation {n['normal_force_variation_rel']:.2g}, balance "
              f"{n['balance_residual_rel']:.2g} {'OK' if ct['passed'] else 'FAIL: ' + '; '.join(ct['failures'])}")
        passed.append(ct["passed"])
    print(f"evidence: {out}/*/evidence.json")
    return passed
