"""``make demo``: the model table, then the whole loop over DDS with an independent simulator.

What it runs and prints, and its exit codes: README "The demo". The pure parts (poses, table,
trajectories, residual and tracking statistics) import no ROS; the rclpy client is imported only
when the stack runs.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_VIOLATIONS
from dyn_node.core.robot.model import RobotModel, load_model
from dyn_node.core.check.trajectory import Trajectory, interpolate, validate_trajectory
from dyn_node.ros.demo_output import before_model_in_bag, unanswered_reason, where_line
from dyn_node.ros.demo_gate import gate_scene
from dyn_node.ros.demo_push import PUSH_S, push_checks, run_push
from dyn_node.ros.demo_press import PRESS_SCENE_FILE, scene_press

READY = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
#: Named Panda poses (rad): the 'ready' pose of franka_ros, the arm stretched forward
#: horizontally (largest gravity lever), and folded back onto itself.
PANDA_POSES: dict[str, tuple[float, ...]] = {
    "ready": READY,
    "stretched": (0.0, 1.57, 0.0, -0.0698, 0.0, 1.57, 0.785),
    "folded": (0.0, -1.7, 0.0, -3.0, 0.0, 2.5, 0.785),
}
#: RNEA column of the table: every joint moving at this fraction of its velocity limit while
#: accelerating at TABLE_ACCEL (rad/s²) in the same direction.
TABLE_SPEED_FRACTION = 0.5
TABLE_ACCEL = 5.0
SAFETY_FACTOR = 1.05
TRACKING_TOLERANCE = 0.05
LEAD_S = 1.0      # trajectories start this long after they are sent: the verdict comes first
SETTLE_S = 0.4    # observation continues this long after a trajectory's last point
FINGERS = "panda_finger_joint1,panda_finger_joint2"


# --------------------------------------------------------------------------------------------
# Model table
# --------------------------------------------------------------------------------------------
def named_poses(model: RobotModel) -> dict[str, np.ndarray]:
    """Panda's named poses, or zero / mid-range / a seeded random pose for other robots."""
    if model.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8)):
        return {k: np.array(v) for k, v in PANDA_POSES.items()}
    lo, hi = model.limits.position_lower, model.limits.position_upper
    lo_f = np.where(np.isfinite(lo), lo, -math.pi)
    hi_f = np.where(np.isfinite(hi), hi, math.pi)
    zero = np.clip(np.zeros(model.nv), lo_f, hi_f)
    return {"zero": zero, "mid-range": 0.5 * (lo_f + hi_f),
            "random(seed 0)": np.random.default_rng(0).uniform(lo_f, hi_f)}


def model_table(model: RobotModel) -> str:
    """Readable table: per pose and joint, g(q) and RNEA(q, q̇, q̈) (N·m) and % of the limit."""
    dyn = Dynamics(model)
    lim = model.limits.effort
    v = TABLE_SPEED_FRACTION * np.where(np.isfinite(model.limits.velocity), model.limits.velocity, 1.0)
    a = np.full(model.nv, TABLE_ACCEL)
    lines = [f"{model.name}: {model.nv} DoF, {model.total_mass:.2f} kg, source {model.source}",
             f"gravity g(q) and RNEA τ(q, q̇, q̈) with every joint at {TABLE_SPEED_FRACTION:.0%} of "
             f"its velocity limit, accelerating at {TABLE_ACCEL:g} rad/s²; % = |torque| / effort limit",
             ""]
    poses = named_poses(model)
    head = f"{'joint':<14}{'limit N·m':>10}"
    for name in poses:
        head += f" | {name + ' g':>15}{'%':>5}{'τ':>9}{'%':>5}"
    lines += [head, "-" * len(head)]
    rows = {name: (dyn.gravity(q), dyn.rnea(q, v, a)) for name, q in poses.items()}
    for j, jn in enumerate(model.joint_names):
        row = f"{jn:<14}{lim[j]:>10.1f}"
        for name in poses:
            g, tau = rows[name]
            row += (f" | {g[j]:>15.2f}{abs(g[j]) / lim[j] * 100:>4.0f}%"
                    f"{tau[j]:>9.2f}{abs(tau[j]) / lim[j] * 100:>4.0f}%")
        lines.append(row)
    worst = max(((abs(rows[p][i][j]) / lim[j], p, jn, i) for p in poses for i in (0, 1)
                 for j, jn in enumerate(model.joint_names)))
    lines += ["", f"highest utilisation: {worst[2]} at {worst[0] * 100:.0f}% in the "
                  f"'{worst[1]}' pose {'while moving' if worst[3] else 'holding still'}"]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Demo trajectories (model order = Panda's 7 arm joints)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DemoTrajectory:
    """Waypoints at rest (v = a = 0 at each point, so JTC interpolates quintic min-jerk segments)."""

    name: str
    times: tuple[float, ...]
    positions: tuple[tuple[float, ...], ...]
    description: str

    @property
    def duration(self) -> float:
        return self.times[-1]

    def scaled(self, k: float, name: str, description: str) -> "DemoTrajectory":
        """Same path, k times longer (v = a = 0 at the waypoints stay 0)."""
        return replace(self, name=name, times=tuple(t * k for t in self.times), description=description)

    def validated(self, joint_names: Sequence[str]) -> Trajectory:
        z = [[0.0] * len(joint_names)] * len(self.times)
        return validate_trajectory(joint_names, joint_names, self.times, self.positions, z, z)


def demo_trajectories(short: bool = False) -> tuple[DemoTrajectory, DemoTrajectory]:
    """(comfortable, aggressive) for Panda, both starting and ending at READY.

    The aggressive one shakes joint2 (±0.1 rad) and joint4 (∓0.07 rad) with 0.13 s segments: its
    inertial torque is about twice joint2's 87 N·m limit while velocities stay near their limits,
    so effort is what saturates in the simulator.
    """
    r = np.array(READY)
    target = r + np.array([0.6, 0.35, 0.0, 0.5, 0.0, -0.35, 0.0])
    seg = 0.8 if short else 1.5
    comfortable = DemoTrajectory("comfortable", (0.0, seg, 2 * seg),
                                 tuple(tuple(p) for p in (r, target, r)),
                                 f"ready → reach → ready, {2 * seg:g} s")
    d = np.zeros(7)
    d[1], d[3] = 0.1, -0.07
    shakes = [r, r + d, r - d, r + d] + ([] if short else [r - d, r + d]) + [r]
    T = 0.13
    aggressive = DemoTrajectory("aggressive", tuple(i * T for i in range(len(shakes))),
                                tuple(tuple(p) for p in shakes),
                                f"joint2/joint4 shake, {T:g} s segments")
    return comfortable, aggressive


#: The task-limits scene's limits file: the URDF's joint limits plus a 250 mm/s TCP speed limit.
DEMO_TASK_LIMITS = Path(__file__).resolve().parents[2] / "config" / "demo_task_limits.yaml"
TASK_PLACE = "panda_hand"


def task_transfer() -> DemoTrajectory:
    """ready → a 1 rad swing of joint1 (with joint2/4/6) → ready in 1 s segments: inside every
    joint limit (joint1 at 86% of its speed, efforts lower) but the TCP moves at 0.64 m/s."""
    r = np.array(READY)
    target = r + np.array([1.0, 0.2, 0.0, 0.3, 0.0, -0.1, 0.0])
    return DemoTrajectory("fast transfer", (0.0, 1.0, 2.0), tuple(tuple(p) for p in (r, target, r)),
                          "ready → joint1 +1 rad → ready, 2 s")


def task_checks(unlimited: Any, fast: Any, fast_place: dict[str, str] | None, slowed: Any,
                k: float) -> list[tuple[bool, str]]:
    """The task-limits scene's acceptance: ``unlimited``, the local check of the transfer without
    the TCP limit (FeasibilityResult); ``fast`` / ``slowed``, dyn_node's verdicts (client.Verdict
    or None) before and after slowing by ``k``; ``fast_place``: the values of its
    ``…/panda_hand`` status on ~/feasibility."""
    out = [(unlimited.feasible, f"fast transfer: within every joint limit without the TCP limit "
                                f"(local check: {unlimited.message})")]
    if fast is None:
        return out + [(False, "fast transfer: no verdict from dyn_node on ~/check_trajectory")]
    peak = (_f(_num(fast_place, "frame_speed_peak"), ".3g") + " m/s" if fast_place
            else "no panda_hand status")
    out.append((not fast.feasible and fast.worst_joint == TASK_PLACE
                and fast.worst_constraint == "frame_speed" and 1.0 < fast.time_scale < math.inf
                and fast_place is not None,
                f"fast transfer: infeasible before execution on the TCP speed (worst {fast.worst_joint} "
                f"{fast.worst_constraint}, peak {peak} of 0.25 m/s), time_scale {_f(fast.time_scale, '.4g')}"))
    if slowed is None:
        return out + [(False, "slowed transfer: no verdict from dyn_node on ~/check_trajectory")]
    out.append((slowed.feasible, f"slowed transfer (× {_f(k, '.4g')}): feasible ({slowed.message})"))
    return out


# --------------------------------------------------------------------------------------------
# Statistics on what was observed
# --------------------------------------------------------------------------------------------
def tracking_error(traj: Trajectory, start_s: float, stamps_s: np.ndarray, q: np.ndarray) -> float:
    """Largest |q − reference| (rad) over samples inside [start, end], the JTC quintic reference."""
    t = stamps_s - start_s
    inside = (t >= traj.times[0]) & (t <= traj.times[-1])
    if not np.any(inside):
        return math.nan
    ref, _, _, _ = interpolate(traj, "quintic").evaluate(t[inside])
    return float(np.abs(q[inside] - ref).max())


def effort_residual(measured: dict[int, np.ndarray], model_effort: dict[int, np.ndarray],
                    t0_ns: int, t1_ns: int) -> tuple[float, float, int]:
    """(RMS over joints and samples, max |residual|, samples) of measured − model effort (N·m),
    pairing joint_states and ~/inverse_dynamics by header stamp inside [t0, t1]."""
    keys = sorted(k for k in measured.keys() & model_effort.keys() if t0_ns <= k <= t1_ns)
    if not keys:
        return math.nan, math.nan, 0
    r = np.array([measured[k] - model_effort[k] for k in keys])
    return float(np.sqrt(np.mean(r * r))), float(np.abs(r).max()), len(keys)


# --------------------------------------------------------------------------------------------
# Processes
# --------------------------------------------------------------------------------------------
def _die_with_parent() -> None:
    """Child set-up: own process group (signalled as a whole) and SIGTERM if the demo dies."""
    os.setsid()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


class Child:
    """A child process in its own process group, output to a log file."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], log: Path):
        self.name, self.log_path = name, log
        self._log = open(log, "w")
        self.proc = subprocess.Popen(args, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, grace: float = 8.0) -> int:
        """SIGINT the group, wait, SIGKILL after ``grace`` s; returns the exit code."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.proc.wait()
        # Grandchildren (none expected) go with the group.
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self._log.close()
        return self.proc.returncode

    def tail(self, n: int = 5) -> str:
        try:
            return "\n".join(self.log_path.read_text().splitlines()[-n:])
        except OSError:
            return ""


def _module_available(name: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------
@dataclass
class Outcome:
    """What was observed for one trajectory."""

    name: str
    description: str
    duration_s: float
    verdict: str = "n/a"
    verdict_source: str = "unavailable"
    worst_joint: str = ""
    worst_constraint: str = ""
    worst_ratio: float = math.nan
    time_scale: float = math.nan
    message: str = ""
    verdict_lead_s: float = math.nan
    states: list[str] = field(default_factory=list)
    transitions: int = 0
    tracking_error_rad: float = math.nan
    saturated_samples: int = 0
    residual_rms_nm: float = math.nan
    residual_max_nm: float = math.nan
    residual_samples: int = 0
    check_verdict: str = "n/a"            # the answer on ~/check_trajectory, asked before sending
    check_feasible: bool | None = None


_LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def _f(x: float, fmt: str = ".3g") -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def states_text(states: Sequence[str]) -> str:
    """Distinct controller states in order of first appearance, and how many changes."""
    if not states:
        return "—"
    distinct = list(dict.fromkeys(states))
    return ", ".join(distinct) + (f" ({len(states) - 1} changes)" if len(states) > 1 else "")


def summary_table(outcomes: Sequence[Outcome]) -> str:
    cols = ["trajectory", "dur s", "verdict", "worst joint (constraint)", "ratio", "time_scale",
            "controller states seen", "track err rad", "residual RMS/max N·m"]
    rows = []
    for o in outcomes:
        res = ("—" if math.isnan(o.residual_rms_nm) else
               f"{o.residual_rms_nm:.3f}/{o.residual_max_nm:.3f}")
        worst = f"{o.worst_joint} ({o.worst_constraint})" if o.worst_joint else "—"
        rows.append([o.name, f"{o.duration_s:.2f}", o.verdict, worst, _f(o.worst_ratio),
                     _f(o.time_scale), states_text(o.states), _f(o.tracking_error_rad),
                     res])
    w = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(cols), "  ".join("-" * x for x in w)] + [line(r) for r in rows])


_INTERRUPTED = threading.Event()


def _on_signal(signum, frame) -> None:
    """Ctrl-C / SIGTERM: set a flag that the wait loops turn into KeyboardInterrupt.

    Raising straight from the handler is unsafe: if the signal lands while rclpy converts a
    message, pybind11 turns the KeyboardInterrupt into a RuntimeError. A second signal raises
    at once (the user insists).
    """
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt
    _INTERRUPTED.set()


def check_interrupted() -> None:
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


class Unavailable(Exception):
    """A stage that cannot run here; the message says which and why."""


class Stack:
    """The ROS side of the demo: an rclpy client beside dyn_sim and dyn_node."""

    def __init__(self, model: RobotModel, domain: int, out: Path, log: Any):
        import rclpy
        from rclpy.context import Context
        from rclpy.node import Node
        from dyn_node.ros.qos import LATCHED_HISTORY
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.rclpy = rclpy
        self.model = model
        self.say = log
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node("dyn_node_demo", context=self.ctx)
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.js: dict[int, np.ndarray] = {}       # stamp ns → measured effort (model order)
        self.js_q: dict[int, np.ndarray] = {}     # stamp ns → q
        self.inv: dict[int, np.ndarray] = {}      # stamp ns → dyn_node RNEA effort
        self.js_last = self.inv_last = 0          # newest stamps seen (ns)
        self.verdicts: list[tuple[float, Any]] = []
        self.states: list[tuple[float, str]] = []
        n = model.nv

        def on_js(m: JointState) -> None:
            try:
                s = model.to_model_order(m.name, m.position, m.velocity, m.effort)
            except Exception:
                return
            k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            self.js_q[k] = s.q
            self.js_last = max(self.js_last, k)
            if s.effort is not None:
                self.js[k] = s.effort

        def on_inv(m: JointState) -> None:
            if len(m.effort) == n:
                idx, _ = model.mapping(m.name)
                k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                self.inv[k] = np.asarray(m.effort)[idx]
                self.inv_last = max(self.inv_last, k)

        self.node.create_subscription(JointState, "joint_states", on_js, 1000)
        self.node.create_subscription(JointState, "/dyn_node/inverse_dynamics", on_inv, 1000)
        self.node.create_subscription(
            DiagnosticArray, "/dyn_node/feasibility",
            lambda m: self.verdicts.append((time.time(), m)), LATCHED_HISTORY)
        self.node.create_subscription(
            DiagnosticStatus, "/dyn_node/controller_status",
            lambda m: self.states.append((time.time(), next(
                (kv.value for kv in m.values if kv.key == "state"), "?"))), 100)
        self.traj_pub = self.node.create_publisher(JointTrajectory, "joint_trajectory", 10)
        from dyn_node.ros.client import DynClient

        self.client = DynClient(self.node)  # each trajectory is checked on ~/check_trajectory first

    def spin_until(self, cond, timeout: float, progress=None) -> bool:
        deadline = time.monotonic() + timeout
        last = 0.0
        while not cond():
            check_interrupted()
            if time.monotonic() > deadline:
                return False
            self.ex.spin_once(timeout_sec=0.02)
            if progress is not None and time.monotonic() - last > 0.5:
                last = time.monotonic()
                progress()
        return True

    def now_ns(self) -> int:
        return time.time_ns()

    def check(self, traj: DemoTrajectory, start_ns: int, timeout: float = 15.0) -> Any:
        """dyn_node's verdict (client.Verdict) on ``traj`` from ~/check_trajectory, or None."""
        fut = self.client.check_async(self.message(traj, start_ns), timeout=timeout, from_current_state=True)
        self.spin_until(fut.done, timeout)
        return fut.result() if fut.done() and fut.exception() is None else None

    def retime(self, traj: DemoTrajectory, start_ns: int, timeout: float = 30.0) -> Any:
        """dyn_node's retiming (client.Retimed) of ``traj`` from ~/retime_trajectory, or None."""
        fut = self.client.retime_async(self.message(traj, start_ns), timeout=timeout, from_current_state=True)
        self.spin_until(fut.done, timeout)
        return fut.result() if fut.done() and fut.exception() is None else None

    def send(self, traj: DemoTrajectory, start_ns: int) -> None:
        self.traj_pub.publish(self.message(traj, start_ns))

    def message(self, traj: DemoTrajectory, start_ns: int) -> Any:
        from builtin_interfaces.msg import Duration, Time
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        msg = JointTrajectory(joint_names=list(self.model.joint_names))
        msg.header.stamp = Time(sec=start_ns // 10**9, nanosec=start_ns % 10**9)
        zero = [[0.0] * self.model.nv] * len(traj.times)
        vel, acc = getattr(traj, "velocities", zero), getattr(traj, "accelerations", zero)
        for t, p, v, a in zip(traj.times, traj.positions, vel, acc):
            ns = int(round(t * 1e9))
            msg.points.append(JointTrajectoryPoint(
                positions=list(p), velocities=list(v), accelerations=list(a),
                time_from_start=Duration(sec=ns // 10**9, nanosec=ns % 10**9)))
        return msg

    def set_node_parameters(self, timeout: float = 10.0, **values: Any) -> str:
        """Set dyn_node's parameters; "" when it took them, else why not."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        cli = self.node.create_client(SetParameters, "/dyn_node/set_parameters")
        try:
            if not cli.wait_for_service(timeout_sec=timeout):
                return "no /dyn_node/set_parameters service"
            req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
            fut = cli.call_async(req)
            self.spin_until(fut.done, timeout)
            if not fut.done() or fut.result() is None:
                return "no answer"
            bad = [r.reason for r in fut.result().results if not r.successful]
            return "; ".join(bad)
        finally:
            self.node.destroy_client(cli)

    def verdict_for(self, start_ns: int) -> tuple[float, dict[str, str], int, str] | None:
        for recv, arr in self.verdicts:
            if arr.header.stamp.sec * 10**9 + arr.header.stamp.nanosec != start_ns:
                continue
            for st in arr.status:
                if st.name.endswith("trajectory feasibility"):
                    return recv, {kv.key: kv.value for kv in st.values}, int.from_bytes(st.level, "little") \
                        if isinstance(st.level, bytes) else int(st.level), st.message
        return None

    def close(self) -> None:
        try:
            self.node.destroy_node()
        finally:
            self.rclpy.try_shutdown(context=self.ctx)

    def call_stop_recording(self, timeout: float = 5.0) -> str | None:
        from std_srvs.srv import Trigger

        cli = self.node.create_client(Trigger, "/dyn_node/stop_recording")
        if not cli.wait_for_service(timeout_sec=timeout):
            return None
        fut = cli.call_async(Trigger.Request())
        self.spin_until(fut.done, timeout)
        if fut.done() and fut.result() is not None and fut.result().success:
            return fut.result().message
        return None


def _num(values: dict[str, str], key: str) -> float:
    try:
        return float(values.get(key, "nan"))
    except ValueError:
        return math.nan


def run_trajectory(stack: Stack, traj: DemoTrajectory, say) -> Outcome:
    """Send ``traj`` to start LEAD_S from now, watch the verdict and the execution."""
    model = stack.model
    o = Outcome(traj.name, traj.description, traj.duration)
    # asked first on ~/check_trajectory (checked exactly like joint_trajectory, never executed)
    v = stack.check(traj, stack.now_ns() + int(LEAD_S * 1e9))
    if v is not None:
        o.check_verdict, o.check_feasible = _LEVELS.get(v.level, str(v.level)), v.feasible
        say(f"  ~/check_trajectory: {o.check_verdict}: {v.message}")
        if not v.feasible:  # the fastest feasible timing along the same path
            r = stack.retime(traj, stack.now_ns() + int(LEAD_S * 1e9))
            say("  ~/retime_trajectory: " + ("no answer" if r is None else
                f"{'retimed' if r.feasible else 'no feasible timing'}: {r.duration_in:.3g} s -> "
                f"{r.duration_out:.3g} s: {r.message}" if r.accepted else f"not retimed ({r.reason})"))
    else:
        say("  stage unavailable: check-only request (no answer on ~/check_trajectory)")
    start_ns = stack.now_ns() + int(LEAD_S * 1e9)
    end_ns = start_ns + int(traj.duration * 1e9)
    states_from = len(stack.states)
    stack.send(traj, start_ns)
    say(f"  sent '{traj.name}' ({traj.description}), starting in {LEAD_S:g} s")
    got = stack.spin_until(lambda: stack.verdict_for(start_ns) is not None, LEAD_S + 10.0)
    if got:
        recv, vals, level, msg = stack.verdict_for(start_ns)  # type: ignore[misc]
        o.verdict = _LEVELS.get(level, str(level))
        o.verdict_source = "dyn_node"
        o.worst_joint = vals.get("worst_joint", "")
        o.worst_constraint = vals.get("worst_constraint", "")
        o.worst_ratio = _num(vals, "worst_ratio")
        o.time_scale = _num(vals, "time_scale")
        o.message = msg
        o.verdict_lead_s = start_ns * 1e-9 - recv
        say(f"  ~/feasibility: {o.verdict}: {msg} (verdict {o.verdict_lead_s:+.2f} s before start)")
    else:
        say("  stage unavailable: dyn_node feasibility verdict (no ~/feasibility answer within "
            f"{LEAD_S + 10:g} s); checking locally instead")
        _local_verdict(model, traj, o, say)

    def progress() -> None:
        now = stack.now_ns()
        t = (now - start_ns) * 1e-9
        st = stack.states[-1][1] if stack.states else "?"
        phase = "waiting" if t < 0 else ("executing" if t <= traj.duration else "settling")
        say(f"    {traj.name:<12} {phase:<9} t = {t:+.2f} s / {traj.duration:.2f} s   "
            f"controller: {st}")

    # Wait in stamp time, not wall time: on a loaded machine the simulator may deliver a burst of
    # late (but correctly stamped) samples, and dyn_node may answer late; both must be in.
    settle_ns = end_ns + int(SETTLE_S * 1e9)
    node_up = bool(stack.inv)

    def observed() -> bool:
        js_done = stack.js_last >= settle_ns
        inv_done = not node_up or stack.inv_last >= settle_ns
        return js_done and inv_done

    if not stack.spin_until(observed, traj.duration + LEAD_S + 20, progress):
        say("  (timed out waiting for samples up to the end of the trajectory; using what arrived)")
    stack.spin_until(lambda: False, 0.2)  # the last controller_status messages
    seen: list[str] = []
    for _, s in stack.states[states_from:]:
        if not seen or seen[-1] != s:
            seen.append(s)
    o.states = seen
    o.transitions = max(0, len(seen) - 1)
    keys = sorted(k for k in stack.js_q if start_ns <= k <= end_ns)
    if keys:
        o.tracking_error_rad = tracking_error(traj.validated(model.joint_names), start_ns * 1e-9,
                                              np.array(keys) * 1e-9, np.array([stack.js_q[k] for k in keys]))
        lim = model.limits.effort
        o.saturated_samples = int(sum(np.any(np.abs(stack.js[k]) >= lim * (1 - 1e-9))
                                      for k in keys if k in stack.js))
    o.residual_rms_nm, o.residual_max_nm, o.residual_samples = effort_residual(
        stack.js, stack.inv, start_ns, end_ns)
    say(f"  done: max tracking error {_f(o.tracking_error_rad)} rad, "
        f"{o.saturated_samples} saturated samples, controller states {' → '.join(seen) or '—'}")
    return o


def _local_verdict(model: RobotModel, traj: DemoTrajectory, o: Outcome, say) -> None:
    try:
        from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
    except ImportError as exc:
        say(f"  stage unavailable: local feasibility check ({exc})")
        return
    r = check_trajectory(Dynamics(model), traj.validated(model.joint_names), FeasibilityOptions())
    o.verdict = _LEVELS.get(int(r.level), str(r.level))
    o.verdict_source = "local check (not dyn_node)"
    o.worst_joint, o.worst_constraint = r.worst_joint, r.worst_constraint
    o.worst_ratio, o.time_scale, o.message = r.worst_ratio, r.time_scale, r.message


def _say(s: str) -> None:
    print(s, flush=True)


def _banner(title: str) -> None:
    _say("=" * 100)
    _say(f"dyn_node demo — {title}")
    _say("=" * 100)


@dataclass
class DemoRun:
    """What the scenes of one demo run share: where it writes, the children's environment, and
    what has been observed and checked so far."""

    out: Path
    t_begin: float
    env: dict[str, str] = field(default_factory=dict)
    children: list[Child] = field(default_factory=list)
    stack: Stack | None = None
    outcomes: list[Outcome] = field(default_factory=list)
    checks: list[tuple[bool, str]] = field(default_factory=list)
    unavailable: list[str] = field(default_factory=list)
    bag_path: str | None = None
    task_checks: list[tuple[bool, str]] = field(default_factory=list)  # the task-limits scene's
    extra_verdicts: int = 0  # ~/feasibility answers of the scenes beyond the three trajectories
    push_checks: list[tuple[bool, str]] = field(default_factory=list)  # the push scene's
    retime_checks: list[tuple[bool, str]] = field(default_factory=list)  # ros/demo_retime.py

    @property
    def logs(self) -> Path:
        return self.out / "logs"

    @property
    def bag_dir(self) -> Path:
        return self.out / "bags"

    def elapsed(self) -> float:
        return time.monotonic() - self.t_begin

    def missing(self, what: str, say_text: str | None = None) -> None:
        """A stage that could not run: listed in the summary, and said now."""
        self.unavailable.append(what)
        _say(say_text or f"stage unavailable: {what}")


def run_demo(args: argparse.Namespace) -> int:
    run = DemoRun(Path(args.out).resolve(), time.monotonic())
    run.out.mkdir(parents=True, exist_ok=True)
    run.logs.mkdir(exist_ok=True)
    _say(where_line(run.out))
    model = load_model(builtin="panda")
    _banner("1. the model")
    _say(model_table(model))
    if args.table_only:
        return 0
    try:
        _scene_stack(run, model, args.domain)
        _scene_trajectories(run, args.short)
        _scene_task_limits(run)
        _scene_push(run, args.short)
        scene_press(run, _say, _banner, DemoTrajectory)
        if len(run.children) > 1 and run.children[1].alive():
            run.bag_path = run.stack.call_stop_recording()
        _save_samples(run.stack, run.out)
    finally:
        _stop_stack(run)
    _say(f"stack stopped ({run.elapsed():.1f} s)")
    if not args.short:  # processes of its own: ~30 s more
        _scene_gate(run)
    _scene_summary(run)
    _scene_audit(run)
    return _finish(run, strict=args.strict)


def _scene_stack(run: DemoRun, model: RobotModel, domain: int) -> None:
    """2. dyn_sim and dyn_node as child processes, and this process's view of them (Stack)."""
    _say("")
    _banner(f"2. the stack (ROS_DOMAIN_ID={domain}, localhost only; logs in {run.logs})")
    # DYN_DEMO_RUN marks the children so a test can prove none is left behind.
    run.env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1", DYN_DEMO_RUN=str(run.out))
    run.env.pop("ROS_LOCALHOST_ONLY", None)
    children = run.children
    children.append(Child("dyn_sim", [sys.executable, "-m", "dyn_node.ros.sim_node", "--ros-args",
                                      "-p", f"initial_positions:={list(READY)}",
                                      "-p", f"apply_wrench_hold:={PUSH_S}",
                                      "-p", f"scene_file:={PRESS_SCENE_FILE}",
                                      # the controller's topic, where dyn_node and this client meet
                                      "-r", "/joint_trajectory_controller/joint_trajectory:=/joint_trajectory"],
                          run.env, run.logs / "dyn_sim.log"))
    node_ok = _module_available("dyn_node.ros.node")
    if node_ok:
        children.append(Child("dyn_node", [
            sys.executable, "-m", "dyn_node.ros.node", "--ros-args",
            "-p", f"locked_joints:={FINGERS}",
            "-p", f"tracking_tolerance:={TRACKING_TOLERANCE}",
            "-p", "record.enabled:=true", "-p", f"record.directory:={run.bag_dir}"],
            run.env, run.logs / "dyn_node.log"))
    else:
        run.missing("dyn_node (module dyn_node.ros.node missing)",
                    "stage unavailable: dyn_node (module dyn_node.ros.node missing); the simulator runs alone")
    stack = run.stack = Stack(model, domain, run.out, _say)
    _say("waiting for dyn_sim's joint_states …")
    if not stack.spin_until(lambda: len(stack.js) > 50, 60):
        raise Unavailable(f"dyn_sim published no joint_states within 60 s:\n{children[0].tail()}")
    _say(f"  dyn_sim up ({run.elapsed():.1f} s)")
    if node_ok:
        _say("waiting for dyn_node to load the model from /robot_description and answer …")
        if stack.spin_until(lambda: len(stack.inv) > 50, 60):
            _say(f"  dyn_node up ({run.elapsed():.1f} s)")
        else:
            run.missing("dyn_node (no ~/inverse_dynamics within 60 s)",
                        "stage unavailable: dyn_node (no ~/inverse_dynamics within 60 s):\n"
                        + children[1].tail())
    # Let the subscriptions to joint_trajectory match before sending: dyn_sim's, dyn_node's
    # and, when it records, the recorder's (discovered a little later), so the bag has all.
    stack.spin_until(lambda: stack.traj_pub.get_subscription_count() >= len(children), 10)
    if node_ok:
        stack.spin_until(lambda: stack.traj_pub.get_subscription_count() >= 3, 3)


def _scene_trajectories(run: DemoRun, short: bool) -> None:
    """3. a comfortable, an aggressive and the aggressive one slowed by its time_scale."""
    _say("")
    _banner("3. trajectories")
    comfortable, aggressive = demo_trajectories(short)
    run.outcomes.append(run_trajectory(run.stack, comfortable, _say))
    agg = run_trajectory(run.stack, aggressive, _say)
    run.outcomes.append(agg)
    k = agg.time_scale
    if not (math.isfinite(k) and k > 0):
        run.missing("time_scale (no finite time_scale reported for the aggressive trajectory)",
                    "stage unavailable: slowed trajectory (no finite time_scale was reported)")
    else:
        slowed = aggressive.scaled(k * SAFETY_FACTOR, "slowed",
                                   f"aggressive × {k:.3f} × {SAFETY_FACTOR:g}")
        run.outcomes.append(run_trajectory(run.stack, slowed, _say))
        from dyn_node.ros.demo_retime import run_retimed   # 3b: the core retimer's answer
        o, run.retime_checks = run_retimed(run.stack, aggressive, slowed.duration, run_trajectory, _say)
        run.outcomes += [o] if o is not None else []


def _scene_task_limits(run: DemoRun) -> None:
    """3b. a transfer inside every joint limit but over the 250 mm/s TCP speed: dyn_node (given
    config/demo_task_limits.yaml as limits_file for this scene) says so before execution with its
    time_scale, and the transfer slowed by it passes. Check-only requests: nothing moves."""
    _say("")
    _banner("3b. task limits: a TCP speed limit of 250 mm/s (config/demo_task_limits.yaml)")
    stack = run.stack
    if len(run.children) < 2 or not run.children[1].alive() or not DEMO_TASK_LIMITS.is_file():
        run.missing("task-limits scene (no dyn_node, or config/demo_task_limits.yaml missing)")
        return
    from dyn_node.core.check.feasibility import check_trajectory

    t0 = time.monotonic()
    fast = task_transfer()
    unlimited = check_trajectory(Dynamics(stack.model), fast.validated(stack.model.joint_names))
    why = stack.set_node_parameters(limits_file=str(DEMO_TASK_LIMITS))
    if why:
        run.missing(f"task-limits scene (limits_file not taken: {why})")
        return
    try:
        start = stack.now_ns() + int(LEAD_S * 1e9)
        v_fast = stack.check(fast, start)
        place = v_fast.status_values(TASK_PLACE) if v_fast is not None else None  # from the response
        k = v_fast.time_scale if v_fast is not None else math.nan
        _say(f"  {fast.name} ({fast.description}), checked before execution: "
             + (f"{v_fast.message} [time_scale {_f(k, '.4g')}]" if v_fast else "no verdict"))
        slowed = fast.scaled(k * SAFETY_FACTOR, "slowed transfer", f"× {k:.3f} × {SAFETY_FACTOR:g}") \
            if math.isfinite(k) and k > 0 else None
        v_slow = stack.check(slowed, stack.now_ns() + int(LEAD_S * 1e9)) if slowed else None
        if v_slow is not None:
            _say(f"  {slowed.name} ({slowed.description}): {v_slow.message}")
        run.extra_verdicts += (v_fast is not None) + (v_slow is not None)
        run.task_checks = task_checks(unlimited, v_fast, place, v_slow, k * SAFETY_FACTOR)
    finally:
        stack.set_node_parameters(limits_file="")  # the scenes after this one run without it
    for ok, text in run.task_checks:
        _say(f"  [{'PASS' if ok else 'FAIL'}] {text}")
    _say(f"  (scene 3b: {time.monotonic() - t0:.1f} s)")


def _scene_push(run: DemoRun, short: bool) -> None:
    """3c. dyn_sim pushes the flange during the comfortable trajectory (ros/demo_push.py)."""
    _say("")
    _banner("3c. a push: 30 N at the flange for 0.3 s during the comfortable trajectory")
    if len(run.children) < 2:
        run.missing("push scene (no dyn_node)")
        return
    o = run_push(run.stack, demo_trajectories(short)[0], _say)
    if o is None:
        run.missing("push scene (dyn_node publishes no ~/external_wrench)")
        return
    run.extra_verdicts += o.verdict_seen
    run.push_checks = push_checks(o)
    for _, text in run.push_checks:
        _say("  " + text.removeprefix("push: "))


def _scene_gate(run: DemoRun) -> None:
    """3d. a planner-like client sends goals through dyn_node's gate to dyn_sim (ros/demo_gate.py)."""
    _say("")
    _banner("3d. dyn_node between a planner and the controller: the FollowJointTrajectory gate")
    checks, missing = gate_scene(run.env, run.logs, _say)
    run.push_checks += checks  # scene checks shown with the push's in the summary
    for what in missing:
        run.missing(what)


def _save_samples(stack: Stack, out: Path) -> None:
    """Raw observations, for looking into any figure of the summary afterwards."""
    js_k = sorted(stack.js)
    inv_k = sorted(stack.inv)
    np.savez_compressed(out / "samples.npz", js_stamp_ns=np.array(js_k, dtype=np.int64),
                        js_q=np.array([stack.js_q[k] for k in js_k]),
                        js_effort=np.array([stack.js[k] for k in js_k]),
                        inv_stamp_ns=np.array(inv_k, dtype=np.int64),
                        inv_effort=np.array([stack.inv[k] for k in inv_k]))


def _stop_stack(run: DemoRun) -> None:
    if run.stack is not None:
        run.stack.close()
    for c in reversed(run.children):
        rc = c.stop()
        if rc not in (0, -signal.SIGINT, 130):
            _say(f"  {c.name} exited with {rc}; last lines of {c.log_path}:\n{c.tail()}")


def _scene_summary(run: DemoRun) -> None:
    """4. what was observed per trajectory, the acceptance checks and the effort residual."""
    _say("")
    _banner("4. summary")
    outcomes = run.outcomes
    _say(summary_table(outcomes))
    run.checks = acceptance(outcomes) + run.task_checks + run.push_checks + run.retime_checks
    _say("")
    for ok, text in run.checks:
        _say(f"  [{'PASS' if ok else 'FAIL'}] {text}")
    feas = [o for o in outcomes if o.verdict in ("OK", "WARN") and o.residual_samples]
    if feas:
        rms = math.sqrt(sum(o.residual_rms_nm ** 2 * o.residual_samples for o in feas)
                        / sum(o.residual_samples for o in feas))
        _say(f"  live effort residual MuJoCo (measured) − Pinocchio (dyn_node) on feasible "
             f"trajectories: RMS {rms:.4f} N·m, max {max(o.residual_max_nm for o in feas):.4f} N·m "
             f"over {sum(o.residual_samples for o in feas)} samples")


def _scene_audit(run: DemoRun) -> None:
    """5. dyn-audit on the bag dyn_node recorded, checked against the live verdicts."""
    bags = sorted(run.bag_dir.rglob("*.mcap")) if run.bag_dir.exists() else []
    if run.bag_path is None and bags:
        run.bag_path = str(bags[-1])
    _say("")
    if not run.bag_path:
        run.missing("recording (no bag written)", "stage unavailable: recording (no bag was written)")
        return
    bag = Path(run.bag_path)
    _say(f"bag: {bag}")
    if not _module_available("dyn_node.audit.bag_audit"):
        run.missing("dyn-audit (module dyn_node.audit.bag_audit missing)")
        return
    audit_dir = run.out / "audit"
    _say(f"running dyn-audit on the bag → {audit_dir} …")
    a = Child("dyn-audit", [sys.executable, "-m", "dyn_node.audit.bag_audit", str(bag), "--out",
                            str(audit_dir)], run.env, run.logs / "dyn_audit.log")
    rc = _wait_for(a, 90)
    _say("\n".join("  " + ln for ln in a.tail(15).splitlines()))
    report = audit_dir / "report.html"
    evidence = audit_dir / "evidence.json"
    outcome = audit_outcome(rc, report.exists())
    if outcome == "partial":
        run.checks.append((False, f"dyn-audit: partial (exit 3): parts of the demo's own bag "
                                  f"could not be read (see {evidence}, "
                                  "input_quality.unreadable_ranges)"))
        _say(f"  [FAIL] {run.checks[-1][1]}")
        _say(f"report: {report}")
    elif outcome == "audited":
        for line in audit_recheck_lines(evidence, before_model_in_bag(bag)):
            _say(line)
        live = sum(o.verdict_source == "dyn_node" for o in run.outcomes) + sum(
            o.check_feasible is not None for o in run.outcomes) + run.extra_verdicts  # check-only verdicts too
        check = audit_check(evidence, live)
        run.checks.append(check)
        _say(f"  [{'PASS' if check[0] else 'FAIL'}] {check[1]}")
        _say(f"report: {report}")
    else:
        run.missing(f"dyn-audit (exit {rc}; see {a.log_path})",
                    f"stage failed: dyn-audit exited {rc} (log {a.log_path})")


def _wait_for(child: Child, timeout_s: float) -> int:
    """The child's exit code once it ends, or once it was stopped after ``timeout_s``."""
    try:
        deadline = time.monotonic() + timeout_s
        while child.alive() and time.monotonic() < deadline:
            check_interrupted()
            try:
                child.proc.wait(timeout=0.1)
            except subprocess.TimeoutExpired:
                pass
        if child.alive():
            _say(f"  {child.name} did not finish within {timeout_s:g} s")
    finally:
        rc = child.stop()
    return rc


def _finish(run: DemoRun, *, strict: bool) -> int:
    """summary.json, the closing lines, and the exit code: 2 if a check failed, 3 if a stage
    was unavailable and ``strict``, else 0."""
    (run.out / "summary.json").write_text(json.dumps(
        {"outcomes": [o.__dict__ for o in run.outcomes], "checks": [[ok, t] for ok, t in run.checks],
         "unavailable": run.unavailable, "bag": run.bag_path,
         "wall_time_s": run.elapsed()}, indent=2, default=str))
    _say(f"summary: {run.out / 'summary.json'}")
    if run.unavailable:
        _say("unavailable stages: " + "; ".join(run.unavailable))
    _say(f"demo finished in {run.elapsed():.1f} s")
    if any(not ok for ok, _ in run.checks):
        return 2
    return 3 if (run.unavailable and strict) else 0


def audit_outcome(rc: int, report_written: bool) -> str:
    """What the demo makes of dyn-audit's exit code: ``audited`` for 0 (all feasible) or 1
    (violations found: expected, the aggressive trajectory is infeasible); ``partial`` for 3
    (parts of the bag unreadable, no violations in the rest): the demo records its own bag, which
    must be whole, so that is a failure of the demo (a FAIL check), not a missing stage;
    ``failed`` for 2 (unusable input), anything else, or no report."""
    if not report_written:
        return "failed"
    return {EXIT_OK: "audited", EXIT_VIOLATIONS: "audited", EXIT_PARTIAL: "partial"}.get(rc, "failed")


def audit_recheck_lines(evidence: Path, before_model: int | None = None) -> list[str]:
    """One line per output topic the audit recomputed from the bag: matched and identical?
    ``before_model``: the node's count of inputs taken before its model (why some went
    unanswered, demo_output.unanswered_reason)."""
    try:
        rec = json.loads(evidence.read_text())
        recheck = rec.get("outputs", {}).get("recheck", {})
    except (OSError, ValueError, AttributeError) as exc:
        return [f"  (could not read {evidence}: {exc})"]
    lines = ["dyn-audit recomputed the live outputs from the bag alone:"]
    for topic, d in sorted(recheck.items()):
        lines.append(f"  {topic:<36} matched {d.get('matched')}, unmatched {d.get('unmatched')}, "
                     f"not answered live {d.get('unanswered', 0)}"
                     f"{unanswered_reason(d.get('unanswered', 0), before_model)}, "
                     f"max |difference| {d.get('max_abs_difference')}, identical {d.get('identical')}")
    return lines


def audit_check(evidence: Path, live_verdicts: int) -> tuple[bool, str]:
    """dyn-audit reproduced every live ~/feasibility verdict from the bag, identically."""
    try:
        recheck = json.loads(evidence.read_text())["outputs"]["recheck"]
        # executions' verdicts on ~/feasibility, the questions' in ~/check_trajectory's events
        rows = [v for k, v in recheck.items() if k.endswith(("feasibility", "check_trajectory/_service_event"))]
        if not rows:
            raise KeyError("feasibility")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return False, f"dyn-audit: no feasibility recheck in {evidence} ({exc!r})"
    matched = sum(d.get("matched", 0) for d in rows)
    identical = all(d.get("identical") for d in rows if d.get("matched"))
    ok = matched == live_verdicts and not any(d.get("unmatched") for d in rows) and identical
    return ok, (f"dyn-audit reproduced the live verdicts from the bag: {matched} of "
                f"{live_verdicts} matched, identical {identical}")


def acceptance(outcomes: Sequence[Outcome]) -> list[tuple[bool, str]]:
    """The issue's acceptance criteria, evaluated on what was observed."""
    by = {o.name: o for o in outcomes}
    checks: list[tuple[bool, str]] = []
    asked = [o for o in outcomes if o.verdict_source == "dyn_node"]
    if asked:
        same = [o for o in asked if o.check_feasible is not None
                and o.check_feasible == (o.verdict in ("OK", "WARN"))]
        checks.append((len(same) == len(asked),
                       f"every trajectory checked on ~/check_trajectory before it was sent, with "
                       f"the verdict joint_trajectory then got ({len(same)} of {len(asked)}: "
                       + ", ".join(f"{o.name} {o.check_verdict}" for o in asked) + ")"))
    if "comfortable" in by:
        o = by["comfortable"]
        checks.append((o.verdict in ("OK", "WARN") and o.tracking_error_rad <= TRACKING_TOLERANCE,
                       f"comfortable: feasible ({o.verdict}) and tracked within "
                       f"{TRACKING_TOLERANCE} rad ({_f(o.tracking_error_rad)} rad)"))
    if "aggressive" in by:
        o = by["aggressive"]
        checks.append((o.verdict == "ERROR" and o.verdict_lead_s > 0,
                       f"aggressive: ERROR on ~/feasibility before execution "
                       f"({o.verdict}, {_f(o.verdict_lead_s)} s before start)"))
        checks.append((o.saturated_samples > 0 and bool({"saturated", "deviating"} & set(o.states)),
                       f"aggressive: the simulator saturates ({o.saturated_samples} samples) and "
                       f"~/controller_status reports saturated or deviating "
                       f"({states_text(o.states) if o.states else 'nothing'})"))
    if "slowed" in by:
        o = by["slowed"]
        checks.append((o.verdict in ("OK", "WARN") and o.tracking_error_rad <= TRACKING_TOLERANCE,
                       f"slowed: feasible ({o.verdict}) and tracked within {TRACKING_TOLERANCE} rad "
                       f"({_f(o.tracking_error_rad)} rad)"))
    return checks


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="dyn_node_demo", description=__doc__.split("\n")[0])
    p.add_argument("--short", action="store_true", help="shorter trajectories (CI)")
    p.add_argument("--out", default="demo_out", help="output directory (bag, audit, logs)")
    p.add_argument("--domain", type=int, default=int(os.environ.get("DYN_DEMO_DOMAIN", 0)) or
                   60 + os.getpid() % 40, help="ROS_DOMAIN_ID for the demo's processes")
    p.add_argument("--table-only", action="store_true", help="print the model table and stop")
    p.add_argument("--strict", action="store_true",
                   help="exit 3 when a stage was unavailable (default: report it and exit 0)")
    args = p.parse_args(argv)

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        return run_demo(args)
    except KeyboardInterrupt:
        print("\ninterrupted: the stack has been stopped", flush=True)
        return 130
    except Unavailable as exc:
        print(f"stage unavailable: {exc}", flush=True)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
