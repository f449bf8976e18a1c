"""Contact detection latency: the push's first sample → the first ``contact`` state, in ms.

dyn_sim's Simulator (MuJoCo, 1 kHz, PD + feedforward during a comfortable motion) is pushed at
the flange with 30 N in a different direction each time, after the observer has settled; the
node's own ContactMonitor (default parameters: K = 50/s, contact_threshold 0.05, 20 ms minimum
duration) is fed every sample as the node would be, and the latency is the stamp of the first
sample it reports ``contact`` (or ``collision``) minus the stamp of the first sample the push
moved. That is the state ~/controller_status switches on; the ``dyn_node: contact`` diagnostic
follows at the diagnostics period. No DDS: the transport adds its own (live section) latency.

``run()`` returns the JSON-able figures; ``python -m benchmarks.contact_bench`` prints them.
"""
from __future__ import annotations

import json
import math
import statistics
import sys
from typing import Any

import numpy as np

from .common import NotAvailable, progress

FORCE_N = 30.0
PUSHES = 24
SMOKE_PUSHES = 3
PUSH_S = 0.3
FRAME = "panda_link8"
READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
MOVE = np.array([0.3, 0.2, 0.0, 0.3, 0.0, -0.2, 0.0])  # a comfortable reach (~0.5 rad/s peak)


def directions(n: int, seed: int = 19) -> np.ndarray:
    """n unit vectors, spread over the sphere (seeded: the same pushes every run)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def one_push(model: Any, force: np.ndarray, onset_s: float) -> int | None:
    """Latency (ns) of one push starting ``onset_s`` into the motion; None: never detected."""
    from dyn_node.core.contacts.contact_monitor import ContactMonitor, ContactSettings
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.sim.simulator import SimConfig, Simulator

    sim = Simulator(model, SimConfig(initial_positions=tuple(READY)))
    zero = np.zeros((3, model.nv))
    sim.execute(model.joint_names, [0.05, 0.85, 1.65], np.vstack([READY, READY + MOVE, READY]), zero, zero)
    mon = ContactMonitor(Dynamics(model), ContactSettings(contact_frame=FRAME))
    dt_ns = int(round(sim.config.timestep * 1e9))
    start = int(round(onset_s / sim.config.timestep))
    first_pushed = None
    for k in range(start + int(round((PUSH_S + 0.1) / sim.config.timestep))):
        if k == start:
            sim.apply_wrench(FRAME, force, (0.0, 0.0, 0.0), hold_s=PUSH_S)
        st = sim.step(1)
        t_ns = (k + 1) * dt_ns
        s = mon.update(t_ns, t_ns, st.q, st.v, st.effort)
        if k == start:
            first_pushed = t_ns  # the first state the push moved
        if s.state in ("contact", "collision"):
            if first_pushed is None:
                raise RuntimeError(f"contact reported before the push, at {t_ns * 1e-9:.3f} s")
            return t_ns - first_pushed
    return None


def press() -> dict:
    """The press scene (issue 32): the Panda's fingers pressed on dyn_sim's table and held, the
    node's ContactMonitor fed every sample; its wrench at FRAME against the contact truth moved
    there: first touch → first ``contact`` state (ms) and the settled force error over the last
    0.5 s of a 2 s hold (N, and relative to the truth's force)."""
    from dyn_node.core.contacts.contact_monitor import ContactMonitor, ContactSettings
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.ros.demo.press import wrench_at_frame
    from dyn_node.sim.press import PRESS_SCENE, plan_press
    from dyn_node.sim.simulator import SimConfig, Simulator

    model = load_model(builtin="panda")
    sim = Simulator(model, SimConfig(scene=PRESS_SCENE, initial_positions=tuple(READY)))
    plan = plan_press(sim)
    sim.execute(model.joint_names, *plan.waypoints())
    mon = ContactMonitor(Dynamics(model), ContactSettings(contact_frame=FRAME))
    dt_ns = int(round(sim.config.timestep * 1e9))
    n = int(round((plan.t_press + 2.0) / sim.config.timestep))
    touch = detected = None
    errors, forces = [], []
    for k in range(n):
        st = sim.step(1)
        t_ns = (k + 1) * dt_ns
        s = mon.update(t_ns, t_ns, st.q, st.v, st.effort)
        truth = sim.contact_truth()
        if touch is None and truth.active:
            touch = t_ns
        if detected is None and touch is not None and s.state in ("contact", "collision"):
            detected = t_ns
        if k >= n - 500 and s.wrench is not None:
            F = wrench_at_frame(model, st.q, [w.link for w in truth.link_wrenches],
                                [w.wrench for w in truth.link_wrenches], FRAME)[:3]
            errors.append(float(np.linalg.norm(s.wrench.force - F)))
            forces.append(float(np.linalg.norm(F)))
    err = statistics.mean(errors) if errors else math.nan
    force = statistics.mean(forces) if forces else math.nan
    return {"touch_to_contact_ms": None if detected is None else (detected - touch) / 1e6,
            "settled_error_n": err, "settled_force_n": force, "settled_error_rel": err / force,
            "what": f"Panda's fingers pressed on dyn_sim's table (config/press_scene.yaml) and held 2 s; "
                    f"ContactMonitor at {FRAME} vs ~/contact_truth moved there"}


def run(*, quick: bool = False, smoke: bool = False) -> dict:
    """Detection latency over the pushes (SMOKE_PUSHES in a smoke run, else PUSHES)."""
    try:
        from dyn_node.core.contacts.contact_monitor import ContactSettings
        from dyn_node.core.robot.model import load_model
    except ImportError as exc:  # pragma: no cover - a tree without the contact core
        raise NotAvailable(f"contact monitor not importable ({exc})") from None
    model = load_model(builtin="panda")
    n = SMOKE_PUSHES if smoke else PUSHES
    dirs = directions(n)
    onsets = 0.3 + 0.9 * (np.arange(n) % 8) / 8  # ≥ 3/K settled; spread over the motion
    lat_ms: list[float] = []
    missed = 0
    for i in range(n):
        lat = one_push(model, FORCE_N * dirs[i], float(onsets[i]))
        if lat is None:
            missed += 1
        else:
            lat_ms.append(lat / 1e6)
        if (i + 1) % 8 == 0:
            progress("contact", f"{i + 1}/{n} pushes")
    gain = float(ContactSettings().observer_gain[0])
    out = {"latencies_ms": lat_ms, "pushes": n, "missed": missed, "observer_gain": gain,
           "force_n": FORCE_N, "time_constant_ms": 1e3 / gain, "rise_95_ms": 3e3 / gain,
           "contact_min_duration_ms": ContactSettings().contact_min_duration * 1e3,
           "what": f"{FORCE_N:g} N at {FRAME}, {n} directions, Panda in dyn_sim (MuJoCo 1 kHz) "
                   "during a comfortable reach; first pushed sample → first contact state"}
    try:
        out["press"] = press()
    except ImportError as exc:  # pragma: no cover - a tree without the contact scene
        out["press"] = {"status": f"not available: {exc}"}
    if lat_ms:
        s = sorted(lat_ms)
        out.update(median_ms=statistics.median(s),
                   p95_ms=s[min(len(s) - 1, math.ceil(0.95 * len(s)) - 1)], max_ms=s[-1])
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    res = run(smoke="--smoke" in args, quick="--quick" in args)
    print(json.dumps(res, indent=1))
    return 0 if not res["missed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
