"""The controller tracker behind ``~/controller_status``: idle, tracking, deviating, saturated,
stale or fault, from the monitor's results and the active trajectory."""
from __future__ import annotations

import math
from bisect import bisect_right
from contextlib import nullcontext
from typing import Any

import numpy as np

from dyn_node.errors import CONTROL_ERROR, STATE_ERROR
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.live.monitor_results import BatchResult, SampleResult
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, STALE, WARN, Status
from dyn_node.core.check.execution import Execution, ExecutionOptions, Timing, execute
from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.core.robot.units import joint_units, unit_key

CONTROLLER = NAME_PREFIX + "controller"

CONTROLLER_STATES = ("idle", "tracking", "deviating", "saturated", "contact", "collision", "stale", "fault")


class ControllerTracker:
    """State of execution for ~/controller_status.

    States, first match wins: ``fault`` (the last joint_states was rejected), ``stale`` (nothing
    within stale_timeout), ``collision`` and ``contact`` (the contact monitor's open episode, fed
    by :meth:`note_contact`), ``saturated`` (worst measured |effort| / limit ≥ 1), ``deviating``
    (a trajectory is active and some |q − reference| > tracking_tolerance), ``tracking`` (active
    and within tolerance), ``idle``. A trajectory is active while the controller executes it, as
    the execution model has it (core/check/execution.py: from receipt, or from a past stamp's
    offset, through the segment from the robot's state to the first point, to the last point),
    and the reference is that execution's polynomial (quintic with accelerations, cubic with
    velocities, linear with positions only).
    """

    def __init__(self, model: RobotModel, settings: Settings):
        self.model = model
        self.settings = settings
        self._units = joint_units(model)["position"]  # tracking errors: rad, or m if prismatic
        self.state = "stale"
        self.since_s: float | None = None
        # (polynomial, last position, time origin, active from, active until, breaks as floats,
        # the plan it replaced or None)
        self._plan: tuple | None = None
        self._nan = np.full(model.nv, np.nan)
        self._nan.setflags(write=False)  # shared "no error known" value; never written
        self._error = self._nan
        self._ratio = math.nan
        self._last_receipt: float | None = None
        self._fault: str = ""
        self._active = False
        self._contact: str = "none"
        self._stamp: float | None = None  # the last accepted sample's stamp (s)
        self._episode = None  # the open ContactEpisode behind contact / collision

    def follow(self, traj: Trajectory, *, timing: Timing, start: StartState | None = None,
               options: ExecutionOptions = ExecutionOptions(), lock: Any = None) -> Execution:
        """Track ``traj`` (model order) as the controller executes it (the execution model:
        received at ``timing`` by a robot in ``start``, so a start segment, a past stamp's cut and
        a held single point are followed too). A trajectory the controller refuses leaves the
        plan it runs in place. ``lock``: held only while the plan is replaced (the execution is
        built outside it: the node's joint_states wait on that lock). Returns the execution."""
        ex = execute(traj, start, timing, options)
        if not ex.refusals:
            with lock if lock is not None else nullcontext():
                self.track(ex, timing.receipt_s)
        return ex

    def track(self, ex: Execution, receipt_s: float) -> None:
        """Track an execution whose times count from ``receipt_s`` (s). Safe to call from another
        thread: the new plan replaces the old one in a single assignment."""
        poly, old = ex.pp, self._plan
        # samples stamped before its start (received after it) were still under the old plan
        prev = old[:6] + (None,) if old is not None else None
        self._plan = (poly, ex.knots.positions[-1], receipt_s, receipt_s + float(poly.breaks[0]),
                      receipt_s + float(poly.breaks[-1]), poly.breaks.tolist(), prev)

    def reference(self, t: float) -> np.ndarray | None:
        """Reference position at time t (s), or None when no trajectory is active then."""
        return _reference(self._plan, t)

    def note_contact(self, state: str, episode=None) -> None:
        """The contact monitor's state after the sample about to be fed to :meth:`update`
        (``none``, ``contact``, ``collision`` or ``unavailable``) and its open episode."""
        self._contact, self._episode = state, episode

    def update(self, result: SampleResult, receipt_s: float) -> bool:
        """Feed one monitor result; returns True when the state changed."""
        self._last_receipt = receipt_s
        if not result.accepted:
            self._fault = str(result.error)
        else:
            self._fault = ""
            self._stamp = result.stamp_s
            ref = self.reference(result.stamp_s)
            self._active = ref is not None
            self._error = result.q - ref if ref is not None else self._nan
            self._ratio = result.measured_ratio
        return self.tick(receipt_s)

    _STATE_CODES = ("idle", "tracking", "deviating", "saturated")

    def update_batch(self, batch: BatchResult, receipt_s: np.ndarray) -> list[tuple[int, str]]:
        """:meth:`update` for every row of an accepted batch, in order (receipt times (N,) s);
        returns (row, new state) for each row at which :meth:`update` would return True."""
        n = len(batch)
        if n == 0:
            return []
        ratio = batch.measured_ratio
        sat = ratio >= 1.0 - 1e-9  # NaN compares False, as in _evaluate
        code = np.where(sat, 3, 0)
        plan = self._plan
        active = np.zeros(n, dtype=bool)
        last_error = self._nan
        if plan is not None:
            T = batch.stamp_s
            active = (T >= plan[3]) & (T <= plan[4])  # where reference() is not None
            if plan[6] is not None:
                active |= (T < plan[3]) & (T >= plan[6][3]) & (T <= plan[6][4])
            tol = self.settings.tracking_tolerance
            rows = np.flatnonzero(active & ~sat)
            if active[-1] and sat[-1]:
                rows = np.append(rows, n - 1)
            for k in rows.tolist():
                error = batch.q[k] - _reference(plan, float(T[k]))
                if k == n - 1:
                    last_error = error
                if not sat[k]:
                    err = float(np.fmax.reduce(np.abs(error)))
                    if err != err:
                        err = 0.0
                    code[k] = 2 if err > tol else 1
        prev = self._STATE_CODES.index(self.state) if self.state in self._STATE_CODES else -1
        changed = np.flatnonzero(code != np.r_[prev, code[:-1]])
        if self.since_s is None:
            self.since_s = float(receipt_s[0])
        if len(changed):
            self.since_s = float(receipt_s[changed[-1]])
        self.state = self._STATE_CODES[int(code[-1])]
        self._last_receipt = float(receipt_s[-1])
        self._fault = ""
        self._active = bool(active[-1])
        self._error = last_error
        self._ratio = float(ratio[-1])
        return [(k, self._STATE_CODES[int(code[k])]) for k in changed.tolist()]

    def _evaluate(self, now_s: float) -> str:
        if self._last_receipt is not None and now_s < self._last_receipt:
            self._last_receipt = now_s  # the clock jumped back: staleness counts from the jump
        if self._last_receipt is None or now_s - self._last_receipt > self.settings.stale_timeout:
            return "stale"
        if self._fault:
            return "fault"
        if self._contact in ("collision", "contact"):
            return self._contact
        # A clamped actuator reports exactly its limit, so reaching it (to rounding) is saturation.
        if self._ratio >= 1.0 - 1e-9:
            return "saturated"
        if self._active:
            err = float(np.fmax.reduce(np.abs(self._error)))  # nanmax; NaN only if all are NaN
            if err != err:
                err = 0.0
            return "deviating" if err > self.settings.tracking_tolerance else "tracking"
        return "idle"

    def tick(self, now_s: float) -> bool:
        """Re-evaluate at ``now_s`` (e.g. for staleness); True when the state changed."""
        state = self._evaluate(now_s)
        if state != self.state or self.since_s is None:
            changed = state != self.state
            self.state, self.since_s = state, now_s
            return changed
        return False

    def status(self, now_s: float, hardware_id: str) -> Status:
        vals: dict = {"state": self.state,
                      "time_in_state_s": now_s - self.since_s if self.since_s is not None else 0.0,
                      "worst_measured_effort_ratio": self._ratio,
                      "trajectory_active": self._active and self.state in ("tracking", "deviating")}
        units = self._units
        for n, e, u in zip(self.model.joint_names, self._error, units):
            vals[f"{n}_tracking_error_{unit_key(u)}"] = float(e)
        for u in dict.fromkeys(units):  # one tolerance, read in each joint's unit: rad, m or both
            vals[f"tracking_tolerance_{unit_key(u)}"] = self.settings.tracking_tolerance
        st = self.state
        if st == "stale":
            level, msg, label = STALE, "no joint_states within stale_timeout", STATE_ERROR
        elif st == "fault":
            level, msg, label = ERROR, f"joint_states rejected: {self._fault}", STATE_ERROR
        elif st in ("collision", "contact"):
            ep = self._episode
            level, label = (ERROR if st == "collision" else WARN), CONTROL_ERROR
            # the episode runs on the samples' clock (stamps), not the receipt clock of now_s
            msg = ep.message(self._stamp) if ep is not None else st
        elif st == "saturated":
            level, msg, label = ERROR, f"measured effort at {self._ratio * 100:.0f}% of the limit", CONTROL_ERROR
        elif st == "deviating":
            j = int(np.nanargmax(np.abs(self._error)))
            level, label = WARN, CONTROL_ERROR
            u = self._units[j]
            msg = (f"{self.model.joint_names[j]} is {self._error[j]:+.3g} {u} off the trajectory "
                   f"(tolerance {self.settings.tracking_tolerance:g} {u})")
        elif st == "tracking":
            level, msg, label = OK, "tracking the trajectory within tolerance", ""
        else:
            level, msg, label = OK, "no active trajectory", ""
        if label:
            vals["failure_label"] = label
        return Status(CONTROLLER, level, msg, hardware_id, vals)


def _reference(plan: tuple | None, t: float) -> np.ndarray | None:
    """The plan's position at t, the previous plan's before the plan starts, else None."""
    if plan is None:
        return None
    poly, _last, start, t0, t1, br, prev = plan
    if t < t0:
        return _reference(prev, t)
    if t > t1:
        return None
    tau = t - start
    # bisect on the breaks as Python floats is np.searchsorted(side="right") without its overhead
    seg = min(max(bisect_right(br, tau) - 1, 0), len(poly.coeffs) - 1)
    s = min(max(tau - br[seg], 0.0), br[seg + 1] - br[seg])
    c = poly.coeffs[seg]
    acc = c[-1]  # Horner; the first product makes a new array, c is never written
    for k in range(c.shape[0] - 2, -1, -1):
        acc = acc * s + c[k]
    return acc if c.shape[0] > 1 else acc.copy()


__all__ = ["ControllerTracker", "CONTROLLER", "CONTROLLER_STATES"]

