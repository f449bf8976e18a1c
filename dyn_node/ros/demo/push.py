"""The demo's push scene: during a comfortable trajectory dyn_sim pushes the flange with 30 N for
0.3 s (``~/apply_wrench``); the demo reports when dyn_node said ``contact``/``collision`` after
the push began and its wrench estimate against the applied force, each with a PASS line.

The push is published at the frame dyn_node estimates the wrench at (its ``contact_frame``,
read from ``~/external_wrench``), in that frame's axes, so estimate and push compare directly;
the settled window is timed by dyn_sim's ``~/applied_wrench`` (when the push acted, in the
stamps the estimate carries), not by the wall clock.
:func:`push_checks` is pure; :func:`run_push` needs the demo's running Stack.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from dyn_node.ros.demo.run import DemoRun, banner, say
from dyn_node.ros.demo.trajectories import demo_trajectories

PUSH_FORCE = (0.0, 0.0, -30.0)   # N, in the contact frame's axes (the flange: along its −z)
PUSH_S = 0.3                     # how long dyn_sim holds it (its apply_wrench_hold)
PUSH_AT_S = 0.5                  # into the trajectory
LEAD_S = 0.4                     # the trajectory starts this long after it is sent
SETTLED_S = 0.1                  # 5/K at the default observer_gain 50/s: the estimate has settled
DETECT_WITHIN_S = PUSH_S         # contact must be reported while the push lasts
CONTACT_STATES = ("contact", "collision")


@dataclass
class PushOutcome:
    """What was observed: wall times in s (``time.time()``), forces in N at ``frame``."""

    frame: str
    applied: np.ndarray
    sent_s: float
    reported_s: float | None = None      # first contact/collision on ~/controller_status
    reported_state: str = ""
    estimate: np.ndarray | None = None   # mean F̂ over [applied + SETTLED_S, its end)
    estimate_samples: int = 0
    wrenches: list = field(default_factory=list)  # (stamp s, frame_id, F̂)
    truth: list = field(default_factory=list)     # dyn_sim's ~/applied_wrench: (stamp s, link, F)
    start_ns: int = 0                    # the trajectory's stamp (its ~/feasibility verdict's)


def push_checks(o: PushOutcome) -> list[tuple[bool, str]]:
    """The scene's two acceptance lines: detected while the push lasted; the settled force
    estimate within 10 % + 1 N of the applied one (the issue's accuracy figure)."""
    f = float(np.linalg.norm(o.applied))
    if o.reported_s is None:
        detected = (False, f"push: no contact/collision on ~/controller_status after the {f:.3g} N push")
    else:
        dt = o.reported_s - o.sent_s
        detected = (0.0 <= dt <= DETECT_WITHIN_S,
                    f"push: dyn_node reported {o.reported_state} {dt * 1e3:.0f} ms after the {f:.3g} N "
                    f"push began (within the push's {DETECT_WITHIN_S:g} s)")
    if o.estimate is None:
        why = ("dyn_sim did not say it applied the push (~/applied_wrench)" if not o.truth else
               f"no ~/external_wrench estimate at {o.frame} during the push")
        return [detected, (False, f"push: {why}")]
    err = float(np.linalg.norm(o.estimate - o.applied))
    tol = 0.1 * f + 1.0
    est = (err <= tol, f"push: estimated force {np.linalg.norm(o.estimate):.1f} N vs {f:.3g} N applied "
                       f"at {o.frame} (|F̂ − F| {err:.2f} N ≤ {tol:.1f} N; mean of {o.estimate_samples} "
                       f"samples {SETTLED_S:g}–{PUSH_S:g} s into the push, dyn_sim's stamps)")
    return [detected, est]


def settle_estimate(o: PushOutcome) -> None:
    """Fill ``o.estimate`` from the wrenches stamped in the settled part of the push, timed by
    what dyn_sim says it applied (``o.truth``: its ~/applied_wrench, in its own stamps), so a
    push that reached a starved simulator late, or a simulator behind the wall clock, does not
    shift the window: [start + SETTLED_S, end) of the first push at ``o.frame``."""
    o.estimate, o.estimate_samples = None, 0
    start = next((i for i, (_, fid, w) in enumerate(o.truth) if fid == o.frame and np.any(w)), None)
    if start is None:
        return
    t0 = o.truth[start][0]
    # the push ends with the next message (a zero wrench, or a push replacing it)
    t1 = o.truth[start + 1][0] if start + 1 < len(o.truth) else t0 + PUSH_S
    F = [w for t, fid, w in o.wrenches if fid == o.frame and t0 + SETTLED_S <= t < t1]
    o.estimate_samples = len(F)
    o.estimate = np.mean(F, axis=0) if F else None


def run_push(stack: Any, traj: Any, say: Callable[[str], None]) -> PushOutcome | None:
    """Send ``traj``, push the flange PUSH_AT_S into it, and observe; None when dyn_node
    publishes no ~/external_wrench (no contact monitoring to show)."""
    from geometry_msgs.msg import WrenchStamped

    from dyn_node.ros.qos import LATCHED_HISTORY

    wrenches: list = []
    truth: list = []

    def entry(m: WrenchStamped) -> tuple[float, str, np.ndarray]:
        f = m.wrench.force
        return (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.header.frame_id,
                np.array([f.x, f.y, f.z]))

    sub = stack.node.create_subscription(WrenchStamped, "/dyn_node/external_wrench",
                                         lambda m: wrenches.append(entry(m)), 1000)
    sub_truth = stack.node.create_subscription(WrenchStamped, "/dyn_sim/applied_wrench",
                                               lambda m: truth.append(entry(m)), LATCHED_HISTORY)
    pub = stack.node.create_publisher(WrenchStamped, "/dyn_sim/apply_wrench", 10)
    try:
        if not stack.spin_until(lambda: wrenches and pub.get_subscription_count() >= 1, 5.0):
            return None
        frame = wrenches[-1][1]
        start_ns = stack.now_ns() + int(LEAD_S * 1e9)
        stack.send(traj, start_ns)
        say(f"  sent '{traj.name}' ({traj.description}); pushing {frame} {PUSH_AT_S:g} s into it")
        stack.spin_until(lambda: stack.now_ns() >= start_ns + int(PUSH_AT_S * 1e9), LEAD_S + PUSH_AT_S + 5)
        msg = WrenchStamped()
        msg.header.frame_id = frame
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = PUSH_FORCE
        states_from = len(stack.states)
        truth.clear()  # only what dyn_sim applied from now on
        o = PushOutcome(frame, np.array(PUSH_FORCE), time.time())
        pub.publish(msg)
        # until dyn_sim has said the push ended and the estimate has passed that stamp
        stack.spin_until(lambda: len(truth) >= 2 and wrenches and wrenches[-1][0] >= truth[1][0] + 0.1,
                         PUSH_S + 5)
        for recv, state in stack.states[states_from:]:
            if state in CONTACT_STATES:
                o.reported_s, o.reported_state = recv, state
                break
        o.wrenches, o.truth = wrenches, list(truth)
        o.start_ns = start_ns
        settle_estimate(o)
        return o
    finally:
        stack.node.destroy_subscription(sub)
        stack.node.destroy_subscription(sub_truth)
        stack.node.destroy_publisher(pub)


def scene_push(run: DemoRun, short: bool) -> None:
    """3c. dyn_sim pushes the flange during the comfortable trajectory (ros/demo/push.py)."""
    say("")
    banner("3c. a push: 30 N at the flange for 0.3 s during the comfortable trajectory")
    if len(run.children) < 2:
        run.missing("push scene (no dyn_node)")
        return
    o = run_push(run.stack, demo_trajectories(short)[0], say)
    if o is None:
        run.missing("push scene (dyn_node publishes no ~/external_wrench)")
        return
    run.verdict_stamps.append(o.start_ns)
    run.push_checks = push_checks(o)
    for _, text in run.push_checks:
        say("  " + text.removeprefix("push: "))
