"""The demo's press scene: dyn_sim runs with the press scene (a table, ``config/press_scene.yaml``);
the Panda presses its fingers on the table and holds; dyn_node's ``~/external_wrench`` is
compared with dyn_sim's ``~/contact_truth`` moved to the same frame.

Figures: the detection latency (from the first contact in dyn_sim's stamps to dyn_node's first
contact/collision on ``~/controller_status``, and to the first estimate above half the settled
force, in the same stamps), the steady-state force error over the last ``SETTLED_WINDOW_S`` of the
hold, and dyn_sim's largest penetration and energy-budget error (its ``dyn_sim: physics``
status). :func:`press_checks` and :func:`wrench_at_frame` are pure; :func:`run_press` needs the
demo's running Stack.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pinocchio as pin

from dyn_node.core.robot.model import RobotModel

PRESS_SCENE_FILE = Path(__file__).resolve().parents[3] / "config" / "press_scene.yaml"
HOLD_S = 2.0               # held after the press point is reached
SETTLED_WINDOW_S = 0.5     # the steady state: the last half second of the hold
DETECT_WITHIN_S = 0.5      # contact must be reported this soon after the first touch
CONTACT_STATES = ("contact", "collision")


def wrench_at_frame(model: RobotModel, q: np.ndarray, links: Sequence[str], wrenches: Sequence[np.ndarray],
                    frame: str) -> np.ndarray:
    """Σ of link wrenches ([f; m] at each link's origin in its axes) as one wrench at ``frame``'s
    origin in its axes, with Pinocchio's placements at q."""
    pm = model.pin_model
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, q)
    oMe = data.oMf[pm.getFrameId(frame)]
    total = pin.Force.Zero()
    for link, w in zip(links, wrenches):
        eMl = oMe.actInv(data.oMf[pm.getFrameId(link)])
        total += eMl.act(pin.Force(np.asarray(w[:3], float), np.asarray(w[3:], float)))
    return np.concatenate([total.linear, total.angular])


@dataclass
class PressOutcome:
    """What was observed; stamps in s (dyn_sim's clock), forces in N at ``frame``."""

    frame: str
    first_contact_stamp_s: float | None = None
    first_contact_wall_s: float | None = None   # the same instant on the wall clock (real time)
    reported_wall_s: float | None = None         # first contact/collision on ~/controller_status
    reported_state: str = ""
    truth: list = field(default_factory=list)      # (stamp s, F at frame)
    estimates: list = field(default_factory=list)  # (stamp s, F̂ at frame)
    physics: dict = field(default_factory=dict)    # the last 'dyn_sim: physics' key/values
    max_penetration_m: float = 0.0
    verdict_stamps: list = field(default_factory=list)  # its trajectories' (their verdicts')

    def settled(self) -> tuple[np.ndarray | None, np.ndarray | None, int]:
        """(mean truth, mean estimate, samples) over the last SETTLED_WINDOW_S of the truth."""
        if not self.truth:
            return None, None, 0
        t1 = self.truth[-1][0]
        F = [f for t, f in self.truth if t > t1 - SETTLED_WINDOW_S]
        E = [f for t, f in self.estimates if t1 - SETTLED_WINDOW_S < t <= t1]
        return np.mean(F, axis=0), (np.mean(E, axis=0) if E else None), len(E)

    def estimate_latency_s(self) -> float | None:
        """First estimate stamp with |F̂| over half the settled |F| − the first contact stamp."""
        F, _, _ = self.settled()
        if F is None or self.first_contact_stamp_s is None:
            return None
        half = 0.5 * float(np.linalg.norm(F))
        t = next((t for t, f in self.estimates if t >= self.first_contact_stamp_s
                  and np.linalg.norm(f) > half), None)
        return None if t is None else t - self.first_contact_stamp_s


def press_checks(o: PressOutcome) -> list[tuple[bool, str]]:
    """Detected within DETECT_WITHIN_S of the first touch; settled estimate within 10 % + 1 N."""
    if o.first_contact_stamp_s is None:
        return [(False, "press: dyn_sim published no ~/contact_truth (the hand never touched the table)")]
    if o.reported_wall_s is None:
        detected = (False, "press: no contact/collision on ~/controller_status during the press")
    else:
        dt = o.reported_wall_s - o.first_contact_wall_s
        detected = (dt <= DETECT_WITHIN_S, f"press: dyn_node reported {o.reported_state} {dt * 1e3:.0f} ms "
                    f"after the first touch (≤ {DETECT_WITHIN_S:g} s)")
    F, E, n = o.settled()
    if E is None:
        return [detected, (False, f"press: no ~/external_wrench at {o.frame} during the hold")]
    f = float(np.linalg.norm(F))
    err, tol = float(np.linalg.norm(E - F)), 0.1 * float(np.linalg.norm(F)) + 1.0
    lat = o.estimate_latency_s()
    return [detected, (err <= tol, f"press: settled estimate {np.linalg.norm(E):.1f} N vs truth {f:.1f} N at "
                       f"{o.frame} (|F̂ − F| {err:.2f} N ≤ {tol:.1f} N, mean of {n} samples; estimate "
                       f"past half the force {'—' if lat is None else f'{lat * 1e3:.0f} ms'} after the touch)")]


def press_trajectories(model: RobotModel, make: Callable[..., Any]) -> tuple[Any, Any]:
    """(press, release) as the demo's trajectories (``make`` = DemoTrajectory), from the plan
    dyn_node.sim.press computes on a local Simulator with the same scene."""
    from dyn_node.sim.press import PRESS_SCENE, READY, plan_press
    from dyn_node.sim.simulator import SimConfig, Simulator

    plan = plan_press(Simulator(model, SimConfig(scene=PRESS_SCENE, initial_positions=READY)))
    r, a, p = (tuple(float(x) for x in v) for v in (plan.q_ready, plan.q_approach, plan.q_press))
    press = make("press", (0.0, plan.t_approach, plan.t_press), (r, a, p),
                 "ready → above the table → 1 cm into it (held)")
    release = make("release", (0.0, 1.0, 2.0), (p, a, r), "back to ready")
    return press, release


def run_press(stack: Any, press: Any, release: Any, say: Callable[[str], None]) -> PressOutcome | None:
    """Press, hold HOLD_S, release, and observe; None without ~/external_wrench or ~/contact_truth."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import WrenchStamped

    from dyn_node.ros.qos import LATCHED_HISTORY
    try:
        from dyn_node_interfaces.msg import ContactTruth
    except ImportError:
        return None
    raw_truth: list = []
    est: list = []
    phys: list = []
    stamp = lambda h: h.stamp.sec + h.stamp.nanosec * 1e-9  # noqa: E731
    subs = [stack.node.create_subscription(ContactTruth, "/dyn_sim/contact_truth", raw_truth.append, LATCHED_HISTORY),
            stack.node.create_subscription(WrenchStamped, "/dyn_node/external_wrench", lambda m: est.append(
                (stamp(m.header), m.header.frame_id, np.array([m.wrench.force.x, m.wrench.force.y, m.wrench.force.z]))), 1000),
            stack.node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: phys.extend(
                {kv.key: kv.value for kv in s.values} for s in m.status if s.name == "dyn_sim: physics"), 100)]
    try:
        if not stack.spin_until(lambda: est, 5.0):
            return None
        o = PressOutcome(frame=est[-1][1])
        states_from = len(stack.states)
        start_ns = stack.now_ns() + int(0.5e9)
        stack.send(press, start_ns)
        say(f"  sent '{press.name}' ({press.description}); holding {HOLD_S:g} s")
        end_ns = start_ns + int((press.duration + HOLD_S) * 1e9)
        stack.spin_until(lambda: stack.now_ns() >= end_ns, press.duration + HOLD_S + 10)
        o.verdict_stamps.append(start_ns)
        _fill(o, stack, raw_truth, est, phys, states_from)
        back_ns = stack.now_ns() + int(0.3e9)
        stack.send(release, back_ns)
        stack.spin_until(lambda: stack.now_ns() >= back_ns + int((release.duration + 0.5) * 1e9), release.duration + 10)
        o.verdict_stamps.append(back_ns)
        return o
    finally:
        for s in subs:
            stack.node.destroy_subscription(s)


def _fill(o: PressOutcome, stack: Any, raw_truth: list, est: list, phys: list, states_from: int) -> None:
    """Truth moved to the estimate's frame (q of the joint_states with the same stamp), first touch, statuses."""
    for m in raw_truth:
        k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        q = stack.js_q.get(k)
        if q is None:
            continue
        W = [np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]) for w in m.link_wrenches]
        o.truth.append((k * 1e-9, wrench_at_frame(stack.model, q, list(m.link_names), W, o.frame)[:3]))
        o.max_penetration_m = max([o.max_penetration_m, *(c.penetration_depth for c in m.contacts)])
    if o.truth:
        o.first_contact_stamp_s = o.truth[0][0]
        o.first_contact_wall_s = o.first_contact_stamp_s  # real-time stamps: epoch + simulation time
    o.estimates = [(t, f) for t, fid, f in est if fid == o.frame]
    for recv, state in stack.states[states_from:]:
        if state in CONTACT_STATES:
            o.reported_wall_s, o.reported_state = recv, state
            break
    o.physics = phys[-1] if phys else {}


def scene_press(run: Any, say: Callable[[str], None], banner: Callable[[str], None], make: Callable[..., Any]) -> None:
    """3d. the press scene of the demo (``run``: its DemoRun; ``make``: DemoTrajectory)."""
    say("")
    banner("3d. a press: the hand pressed on the table (dyn_sim's press scene), held "
           f"{HOLD_S:g} s; estimate vs contact truth")
    if len(run.children) < 2:
        run.missing("press scene (no dyn_node)")
        return
    o = run_press(run.stack, *press_trajectories(run.stack.model, make), say)
    if o is None:
        run.missing("press scene (no ~/external_wrench from dyn_node or no dyn_node_interfaces)")
        return
    run.verdict_stamps += o.verdict_stamps
    checks = press_checks(o)
    run.push_checks = run.push_checks + checks  # the summary lists the scenes' checks together
    for _, text in checks:
        say("  " + text.removeprefix("press: "))
    p = o.physics
    say(f"  dyn_sim: largest penetration {o.max_penetration_m * 1e3:.2f} mm; last 'dyn_sim: physics' "
        f"status: energy {p.get('energy_j', '—')} J, budget error {p.get('energy_error_rel', '—')} "
        f"(relative), solver iterations ≤ {p.get('solver_iterations_max', '—')}, warnings {p.get('warnings', '—')}")
