"""The live monitor: joint states in, torques, limit checks and diagnostic statuses out.

Pure and deterministic: every time is passed in (``stamp_s`` from the message header, ``receipt_s``
and ``now_s`` from the caller's clock), so the offline audit replaying a bag through the same
:class:`Monitor` and :class:`~dyn_node.core.live.tracker.ControllerTracker` reproduces the live node's
numbers bit for bit.

Acceleration estimate (``acceleration_source = finite_difference``): with t the message's header
stamp (the receipt time when the stamp is zero) and v the reported velocity in model order,

    â_raw[k] = (v[k] − v[k−1]) / (t[k] − t[k−1])          (backward difference)

between consecutive *accepted* messages. The estimate is reset to â = 0 (and the filter state
cleared) on the first message, after a message without velocity, when the stamp goes backwards
(out of order), and when the gap t[k] − t[k−1] exceeds ``stale_timeout``. An equal stamp
(t[k] = t[k−1]) keeps the previous estimate. With ``acceleration_filter_hz`` f > 0 the raw estimate
passes a first-order low-pass discretised exactly for the actual step:

    α = 1 − exp(−2π f (t[k] − t[k−1])),   â[k] = â[k−1] + α (â_raw[k] − â[k−1]),

started at the first raw value. ``acceleration_source = zero`` uses â = 0 (quasi-static torques).
A message without velocities is computed with q̇ = 0.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import CONTROL_ERROR, STATE_ERROR, InputError
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.live.monitor_results import BatchResult, Counts, SampleResult, accepted_result
from dyn_node.core.live.monitor_window import Window
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, STALE, WARN, Status
from dyn_node.core.robot.units import joint_units, unit_key

JOINT_STATES = NAME_PREFIX + "joint_states"
EFFORT = NAME_PREFIX + "effort"
LIMITS = NAME_PREFIX + "limits"
RESIDUAL = NAME_PREFIX + "residual"


def _limit_ratio(x: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """|x| / limit where the limit is positive; where it is not, the feasibility check's rule
    (|x| ≤ limit is allowed): 0 for x = 0 at a zero limit, inf otherwise; NaN x stays NaN (not
    measured)."""
    a = np.abs(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = a / limit
    bad = limit <= 0
    if bad.any():
        r = np.where(bad, np.where(np.isnan(a), np.nan,
                                   np.where((a == 0) & (limit == 0), 0.0, np.inf)), r)
    return r


class Monitor:
    """Per-message torques and checks for one model and one :class:`Settings`.

    ``process`` is the hot path; ``statuses`` builds the /diagnostics statuses (call it once per
    diagnostics period: it reports and then resets the worst-case window).
    """

    def __init__(self, model: RobotModel, settings: Settings, counts: Counts | None = None):
        self.model = model
        self.settings = settings
        self.dynamics = Dynamics(model, DynamicsOptions(include_friction=settings.include_friction))
        lim = model.limits
        self._names = model.joint_names
        self._nv = model.nv
        self._units = joint_units(model)  # each joint's own units in statuses (m and N if prismatic)
        # the limits as the feasibility check applies them: a YAML 0 is a real limit (a URDF 0
        # is already inf, "not given"); the ratio rule for limits ≤ 0 is _limit_ratio's
        self._effort = np.array(lim.effort, dtype=float)
        self._effort.setflags(write=False)
        self._has_curve = any(c is not None for c in lim.effort_speed_curve)
        self._nonpositive = bool(np.any(lim.effort <= 0) or any(
            c is not None and c[:, 1].min() <= 0 for c in lim.effort_speed_curve))
        self._lo, self._hi = lim.position_lower, lim.position_upper
        self._slo, self._shi = lim.soft_lower, lim.soft_upper
        self._vel = lim.velocity
        # deceleration: |q̈̂| where q̇·q̈̂ < 0 (None: no joint has the limit, nothing to fold)
        self._dec = lim.deceleration if bool(np.any(np.isfinite(lim.deceleration))) else None
        self._soft_distinct = bool(np.any(lim.soft_lower != lim.position_lower)
                                   or np.any(lim.soft_upper != lim.position_upper))
        # name list → (index array or None when the names are exactly the model's, ignored count)
        self._maps: dict[tuple[str, ...], tuple[np.ndarray | None, int]] = {}
        self._zero = np.zeros(self._nv)
        self._zero.setflags(write=False)
        self._nan = np.full(self._nv, np.nan)
        self._nan.setflags(write=False)
        self._fd = settings.acceleration_source == "finite_difference"
        self._fc = settings.acceleration_filter_hz
        self._stale = settings.stale_timeout
        self._gravity_and_rnea = self.dynamics.gravity_and_rnea
        self.counts = counts if counts is not None else Counts()
        # how the node counts dropped_messages (dyn_node.core.live.drops); None offline: no key
        self.drop_counting: str | None = None
        self.last_receipt_s: float | None = None
        self.last_error: InputError | None = None
        self.last_result: SampleResult | None = None
        self.last_inputs: tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | None = None
        self._prev_t: float | None = None
        self._prev_v: np.ndarray | None = None
        self._a = self._zero
        self._filtered = False
        self._w = Window(self._nv, None)

    # --- hot path ------------------------------------------------------------------------
    def _accel(self, t: float, v: np.ndarray | None) -> tuple[np.ndarray, bool]:
        prev_t, prev_v = self._prev_t, self._prev_v
        out_of_order = prev_t is not None and t < prev_t
        self._prev_t, self._prev_v = t, v
        if not self._fd:
            return self._zero, out_of_order
        if v is None or prev_v is None or out_of_order or t - prev_t > self._stale:
            self._a = self._zero
            self._filtered = False
            return self._a, out_of_order
        dt = t - prev_t
        if dt == 0.0:
            return self._a, False
        raw = (v - prev_v) / dt
        if self._fc > 0.0 and self._filtered:
            alpha = 1.0 - math.exp(-2.0 * math.pi * self._fc * dt)
            self._a = self._a + alpha * (raw - self._a)
        else:
            self._a = raw
            self._filtered = True
        return self._a, False

    def _to_model_order(self, names: Sequence[str], position: Sequence[float],
                        velocity: Sequence[float] | None, effort: Sequence[float] | None):
        """Fast path of :meth:`RobotModel.to_model_order` for the common, valid message: the name
        mapping is cached per name list (no reindexing when the names are the model's, in its
        order) and finiteness is checked with one Python sum per array. Anything unusual is handed
        to the model's full check, so errors and results are exactly the model's."""
        n = len(names)
        key = names if isinstance(names, tuple) else tuple(names)
        m = self._maps.get(key)
        nvel = len(velocity) if velocity is not None else 0
        neff = len(effort) if effort is not None else 0
        if m is None or len(position) != n or nvel not in (0, n) or neff not in (0, n):
            s = self.model.to_model_order(names, position, velocity, effort)
            if len(self._maps) < 64:
                self._mapping(key)  # cached for the next message with these names
            return s.q, s.v, s.effort, s.ignored
        idx, ignored = m
        if idx is None:  # a copy, as the reindexing would make: callers may keep the arrays
            q = np.array(position, dtype=float)
            v = np.array(velocity, dtype=float) if nvel else None
            e = np.array(effort, dtype=float) if neff else None
        else:
            q = np.asarray(position, dtype=float)[idx]
            v = np.asarray(velocity, dtype=float)[idx] if nvel else None
            e = np.asarray(effort, dtype=float)[idx] if neff else None
        # A Python sum of a few floats is NaN or ±inf iff an element is (or, rarely, it
        # overflows: then the model's check decides); cheaper than any NumPy reduction.
        if not math.isfinite(sum(q.tolist())) or (v is not None and not math.isfinite(sum(v.tolist()))):
            s = self.model.to_model_order(names, position, velocity, effort)  # raises
            return s.q, s.v, s.effort, s.ignored
        if e is not None and not math.isfinite(sum(e.tolist())):
            s = self.model.to_model_order(names, position, velocity, effort)  # raises on ±inf
            return s.q, s.v, s.effort, s.ignored  # NaN effort: "not available" (None if all NaN)
        return q, v, e, ignored

    def process(self, names: Sequence[str], position: Sequence[float], velocity: Sequence[float] | None,
                effort: Sequence[float] | None, stamp_s: float, receipt_s: float) -> SampleResult:
        """One joint state. Never raises for bad input: a rejected message returns
        ``accepted=False`` with the :class:`InputError` and is counted by its code."""
        c, w = self.counts, self._w
        c.received += 1
        w.received += 1
        self.last_receipt_s = receipt_s
        if w.start_s is None:
            w.start_s = receipt_s
        try:
            q, v, e, ignored = self._to_model_order(names, position, velocity, effort)
        except InputError as exc:
            return self._reject(exc)
        except (TypeError, ValueError) as exc:  # arrays that are not numbers at all
            return self._reject(InputError(f"joint state is not numeric: {exc}", code="not_numeric"))
        zero = stamp_s == 0.0
        t = receipt_s if zero else stamp_s
        if not math.isfinite(t):
            return self._reject(InputError(f"header stamp is not finite ({stamp_s})", code="bad_stamp"))
        a, ooo = self._accel(t, v)
        # model order as measured (v, e None: not in the message), for the contact monitor
        self.last_inputs = (q, v, e)
        if v is None:
            v = self._zero
        g, tau = self._gravity_and_rnea(q, v, a)
        if not math.isfinite(float(tau.sum()) + float(g.sum())):
            # finite inputs can still overflow the dynamics (|q̇| ~ 1e300): never publish NaN
            return self._reject(InputError("model torques are not finite: position, velocity or "
                                           "acceleration estimate out of any physical range",
                                           code="non_finite_torque"))
        lim = self._effort
        if self._has_curve:
            lim = np.minimum(lim, self.model.limits.effort_envelope(v))
        util = model_ratio = _limit_ratio(tau, lim) if self._nonpositive else np.abs(tau) / lim
        residual = mr = None
        measured_ratio = math.nan
        if e is not None:
            mr = _limit_ratio(e, lim) if self._nonpositive else np.abs(e) / lim
            util = np.fmax(util, mr)
            residual = e - tau
            mrl = mr.tolist()
            if math.isfinite(sum(mrl)):  # no NaN: Python's max is NumPy's nanmax, exactly
                measured_ratio = max(mrl)
            else:
                measured_ratio = float(np.fmax.reduce(mr))  # NaN only when every joint is NaN
        nan = self._nan
        if w.add((q, v, model_ratio, lim, nan if mr is None else mr, nan if residual is None else residual, a)):
            self._fold()
        c.accepted += 1
        w.accepted += 1
        c.ignored_joint_values += ignored
        if zero:
            c.zero_stamp += 1
            w.zero_stamp += 1
        if ooo:
            c.out_of_order += 1
            w.out_of_order += 1
        self.last_error = None
        r = accepted_result(t, q, v, a, g, tau, residual, util, measured_ratio, zero, ooo, lim)
        self.last_result = r
        return r

    def process_batch(self, names: Sequence[str], position: np.ndarray, velocity: np.ndarray | None,
                      effort: np.ndarray | None, stamp_s: np.ndarray,
                      receipt_s: np.ndarray) -> BatchResult | None:
        """N messages with the same name list at once (N×len(names) arrays; ``velocity`` /
        ``effort`` None when the messages have none; stamps and receipts (N,) in s).

        Gives exactly the numbers, counts and state that N calls of :meth:`process` give (the
        offline audit's fast path). Only for regular input: when any message would be rejected
        or needs the model's special handling (NaN effort, non-finite values or stamps, torques
        out of any physical range), it returns None and changes nothing; the caller then feeds
        the messages one by one to :meth:`process`, so findings stay exact.
        """
        inputs = self._batch_inputs(names, position, velocity, effort, stamp_s, receipt_s)
        if inputs is None:
            return None
        Q, V, E, measured, T, zero, ignored = inputs
        A, ooo, state = self._accel_batch(T, V)
        Vd = V if V is not None else np.zeros((len(T), self._nv))
        TAU = self.dynamics.rnea_batch(Q, Vd, A)
        G = self.dynamics.gravity_batch(Q)
        # process rejects a row whose torque sum is not finite; rows that large never occur in a
        # physical recording, so they are left to process (exact) rather than mirrored here.
        if not (np.abs(TAU).max() < 1e300 and np.abs(G).max() < 1e300):
            return None
        lim, UM, util, RES, mratio, MRf, Rf = self._batch_ratios(TAU, E, Vd)
        # --- commit: from here on the state advances exactly as N process calls would ---------
        self._prev_t, self._prev_v, self._a, self._filtered = state
        self._count_batch(receipt_s, ignored=ignored, zero=zero, ooo=ooo)
        self._fold()
        self._w.fold_arrays(self._lo, self._hi, self._slo, self._shi, self._soft_distinct, self._vel,
                            Q, Vd, UM, lim, MRf, Rf, dec=self._dec, A=A)
        out = BatchResult(T, Q, Vd, A, G, TAU, RES, util, mratio, zero, ooo, lim,
                          None if measured is None or measured.all() else measured)
        self.last_result = out.result(len(T) - 1)
        return out

    def _mapping(self, key: tuple[str, ...]) -> tuple[np.ndarray | None, int] | None:
        """The name mapping as (index array, or None when the names are exactly the model's in
        its order; ignored names), cached for up to 64 name lists (None: the names are rejected)."""
        m = self._maps.get(key)
        if m is None:
            try:
                idx, ignored = self.model.mapping(key)
            except InputError:
                return None
            same = ignored == 0 and len(key) == self._nv and bool(np.all(idx == np.arange(len(key))))
            m = (None if same else idx, ignored)
            if len(self._maps) < 64:
                self._maps[key] = m
        return m

    def _batch_inputs(self, names: Sequence[str], position: np.ndarray, velocity: np.ndarray | None,
                      effort: np.ndarray | None, stamp_s: np.ndarray, receipt_s: np.ndarray) -> tuple | None:
        """The batch in model order as (Q, V, E, measured rows, stamps used, zero stamps, ignored
        values per message), or None when some message needs :meth:`process`'s handling."""
        n_msg = len(stamp_s)
        key = names if isinstance(names, tuple) else tuple(names)
        m = self._mapping(key)
        if m is None:
            return None
        shape = (n_msg, len(key))
        if n_msg == 0 or position.shape != shape or (velocity is not None and velocity.shape != shape) \
                or (effort is not None and effort.shape != shape):
            return None
        idx, ignored = m
        Q, V, E = ((x if x is None or idx is None else x[:, idx]) for x in (position, velocity, effort))
        zero = stamp_s == 0.0
        T = np.where(zero, receipt_s, stamp_s)
        if not (np.isfinite(Q).all() and (V is None or np.isfinite(V).all())
                and (E is None or not np.isinf(E).any()) and np.isfinite(T).all()):
            return None
        measured = None  # rows with some effort value (NaN effort: not available, as in process)
        if E is not None:
            measured = ~np.isnan(E).all(axis=1)
            if not measured.any():
                E = measured = None
        return Q, V, E, measured, T, zero, ignored

    def _batch_ratios(self, TAU: np.ndarray, E: np.ndarray | None, Vd: np.ndarray) -> tuple:
        """(effort limit, model ratio, utilisation, residual, measured ratio per row, measured
        ratio and residual for the window (NaN where not measured)) for N rows, as process."""
        lim = self._effort
        if self._has_curve:
            lim = np.minimum(lim, self.model.limits.effort_envelope(Vd))
        else:
            lim = np.broadcast_to(lim, TAU.shape)
        UM = _limit_ratio(TAU, lim) if self._nonpositive else np.abs(TAU) / lim
        if E is None:
            nan = np.broadcast_to(self._nan, TAU.shape)
            return lim, UM, UM, None, np.full(len(TAU), np.nan), nan, nan
        MR = _limit_ratio(E, lim) if self._nonpositive else np.abs(E) / lim
        RES = E - TAU
        mratio = np.fmax.reduce(MR, axis=1)  # nanmax, as in process (NaN: no effort at all)
        return lim, UM, np.fmax(UM, MR), RES, mratio, MR, RES

    def _count_batch(self, receipt_s: np.ndarray, *, ignored: int, zero: np.ndarray,
                     ooo: np.ndarray) -> None:
        """The counts N accepted :meth:`process` calls would add."""
        n_msg = len(receipt_s)
        c, w = self.counts, self._w
        c.received += n_msg
        w.received += n_msg
        if w.start_s is None:
            w.start_s = float(receipt_s[0])
        self.last_receipt_s = float(receipt_s[-1])
        c.accepted += n_msg
        w.accepted += n_msg
        c.ignored_joint_values += ignored * n_msg
        nz, no = int(zero.sum()), int(ooo.sum())
        c.zero_stamp += nz
        w.zero_stamp += nz
        c.out_of_order += no
        w.out_of_order += no
        self.last_error = None

    def _accel_batch(self, T: np.ndarray, V: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, tuple]:
        """:meth:`_accel` over N rows without touching the state: (A, out_of_order, the state
        after the last row as (prev_t, prev_v, a, filtered))."""
        n_msg = len(T)
        prev_T = np.empty(n_msg)
        prev_T[0] = self._prev_t if self._prev_t is not None else np.nan
        prev_T[1:] = T[:-1]
        ooo = T < prev_T  # NaN (no previous message) compares False, as in _accel
        last_v = None if V is None else V[-1]
        zeros = np.zeros((n_msg, self._nv))
        if not self._fd:
            return zeros, ooo, (float(T[-1]), last_v, self._a, self._filtered)
        if V is None:
            return zeros, ooo, (float(T[-1]), None, self._zero, False)
        if self._fc > 0.0:
            # the low-pass filter is recursive: run _accel row by row on a saved state
            saved = (self._prev_t, self._prev_v, self._a, self._filtered)
            try:
                A = np.array([self._accel(float(t), v)[0] for t, v in zip(T, V)])
                state = (self._prev_t, self._prev_v, self._a, self._filtered)
            finally:
                self._prev_t, self._prev_v, self._a, self._filtered = saved
            return A, ooo, state
        dt = T - prev_T
        reset = ooo | (dt > self._stale)
        if self._prev_v is None:
            reset[0] = True
        eq = (dt == 0.0) & ~reset
        prev_V = np.empty_like(V)
        prev_V[0] = self._prev_v if self._prev_v is not None else np.nan
        prev_V[1:] = V[:-1]
        with np.errstate(divide="ignore", invalid="ignore"):
            A = (V - prev_V) / dt[:, None]
        A[reset] = 0.0
        moved = ~eq
        if eq.any():
            # an equal stamp keeps the previous estimate (the state's, before the first row)
            src = np.maximum.accumulate(np.where(moved, np.arange(n_msg), -1))
            A = np.vstack([self._a[None, :], A])[src + 1]
        last = np.flatnonzero(moved)
        if len(last):
            filtered = not bool(reset[last[-1]])
        else:
            filtered = self._filtered
        a_state = A[-1] if len(last) else self._a
        return A, ooo, (float(T[-1]), last_v, a_state, filtered)

    def _fold(self) -> None:
        self._fold_window(self._w)

    def reject_message(self, exc: InputError, receipt_s: float) -> SampleResult:
        """A message taken but unusable before :meth:`process` could read it (e.g. bytes that
        are no JointState): received and invalid, counted by ``exc.code``, as process counts."""
        self.counts.received += 1
        self._w.received += 1
        self.last_receipt_s = receipt_s
        if self._w.start_s is None:
            self._w.start_s = receipt_s
        return self._reject(exc)

    def _reject(self, exc: InputError) -> SampleResult:
        c = self.counts
        c.invalid += 1
        c.invalid_by_reason[exc.code] = c.invalid_by_reason.get(exc.code, 0) + 1
        self._w.invalid += 1
        self.last_error = exc
        return SampleResult(False, exc)

    def note_dropped(self, total: int, method: str) -> None:
        """The transport's running count of messages lost before they reached the node, and
        how it is counted now (:mod:`dyn_node.core.live.drops`)."""
        self.drop_counting = method
        if total > self.counts.dropped:
            self._w.dropped += total - self.counts.dropped
            self.counts.dropped = total

    # --- reports -------------------------------------------------------------------------
    def statuses(self, now_s: float, hardware_id: str) -> list[Status]:
        """joint_states, effort, limits and residual statuses for the window ending at ``now_s``;
        starts a new window (:meth:`close_window` then :meth:`ClosedWindow.statuses`)."""
        return self.close_window(now_s, hardware_id).statuses()

    def close_window(self, now_s: float, hardware_id: str) -> ClosedWindow:
        """End the window at ``now_s`` and start the next; the cheap half of :meth:`statuses`,
        for under the node's joint_states lock. The joint_states status reads the running
        counts, so it is made here; the window's rows are folded and the other statuses
        written by :meth:`ClosedWindow.statuses`, which the next messages do not wait for."""
        js = self._joint_states_status(now_s, hardware_id)
        closed = ClosedWindow(self, self._w, js, hardware_id)
        self._w = Window(self._nv, now_s)
        return closed

    def _fold_window(self, w: Window) -> None:
        w.fold(self._lo, self._hi, self._slo, self._shi, self._soft_distinct, self._vel, dec=self._dec)

    def _joint_states_status(self, now_s: float, hid: str) -> Status:
        c, w = self.counts, self._w
        span = now_s - w.start_s if w.start_s is not None else 0.0
        age = now_s - self.last_receipt_s if self.last_receipt_s is not None else math.inf
        vals = {"rate_hz": w.received / span if span > 0 else 0.0, "age_s": age,
                "received_messages": c.received, "accepted_messages": c.accepted,
                "invalid_messages": c.invalid, "before_model_messages": c.before_model,
                "out_of_order_messages": c.out_of_order,
                "dropped_messages": c.dropped, "zero_stamp_messages": c.zero_stamp,
                "ignored_joint_values": c.ignored_joint_values}
        if self.drop_counting is not None:
            vals["drop_counting"] = self.drop_counting
        for code, n in sorted(c.invalid_by_reason.items()):
            vals[f"invalid_{code}"] = n
        stale = self.settings.stale_timeout
        if self.last_receipt_s is not None and now_s < self.last_receipt_s:
            # the clock jumped back (a replayed /clock restarting): staleness counts from now
            self.last_receipt_s = now_s
            age = vals["age_s"] = 0.0
        if self.last_receipt_s is None:
            level, msg = STALE, "no joint_states received yet: is the publisher running and the topic remapped?"
        elif age > stale:
            level, msg = STALE, f"no joint_states for {age:.3g} s (stale_timeout {stale:g} s)"
        elif self.last_error is not None:
            level = ERROR
            msg = f"last joint_states rejected ({self.last_error.code}): {self.last_error}"
            vals["last_error"] = str(self.last_error)
        elif w.invalid or w.out_of_order or w.zero_stamp or w.dropped:
            level = WARN
            parts = [f"{n} {what}" for n, what in ((w.invalid, "invalid"), (w.dropped, "dropped"),
                                                   (w.out_of_order, "out of order"),
                                                   (w.zero_stamp, "with zero stamp (receipt time used)"))
                     if n]
            msg = "joint_states in the last period: " + ", ".join(parts)
        else:
            level, msg = OK, f"receiving at {vals['rate_hz']:.1f} Hz"
        if level != OK:
            vals["failure_label"] = STATE_ERROR
        return Status(JOINT_STATES, level, msg, hid, vals)

    def _effort_status(self, w: Window, hid: str) -> Status:
        s = self.settings
        vals: dict = {}
        for i, n in enumerate(self._names):
            vals[f"{n}_utilisation"] = float(w.util[i])
        eff_u = self._units["effort"]
        for i, n in enumerate(self._names):
            vals[f"{n}_effort_limit_{unit_key(eff_u[i])}"] = float(w.util_limit[i])
        j = int(np.argmax(w.util))
        worst = float(w.util[j])
        vals.update(worst_joint=self._names[j], worst_utilisation=worst,
                    effort_warn_ratio=s.effort_warn_ratio)
        what = "measured effort" if w.util_measured[j] else "model torque"
        text = (f"{self._names[j]} at {worst * 100:.0f}% of its {w.util_limit[j]:.4g} {eff_u[j]} effort limit "
                f"({what})")
        if worst > 1.0:
            vals["failure_label"] = CONTROL_ERROR
            return Status(EFFORT, ERROR, text, hid, vals)
        if worst > s.effort_warn_ratio:
            vals["failure_label"] = CONTROL_ERROR
            return Status(EFFORT, WARN, text + f"; warn above {s.effort_warn_ratio * 100:.0f}%", hid, vals)
        return Status(EFFORT, OK, f"worst {self._names[j]} at {worst * 100:.0f}% of its effort limit",
                      hid, vals)

    def _limits_status(self, w: Window, hid: str) -> Status:
        lim = self.model.limits
        pos = np.flatnonzero(w.pos_excess > 0)
        vel = np.flatnonzero(w.vel_excess > 0)
        soft = np.flatnonzero(w.soft_excess > 0)
        dec = np.flatnonzero(w.dec_excess > 0)
        vals: dict = {"position_violations": len(pos), "velocity_violations": len(vel),
                      "deceleration_violations": len(dec), "soft_limit_violations": len(soft)}
        lines = []
        pos_u, vel_u = self._units["position"], self._units["velocity"]
        for i in pos:
            n, q, u = self._names[i], float(w.pos_value[i]), pos_u[i]
            vals[f"{n}_position_{unit_key(u)}"] = q
            if q < lim.position_lower[i]:
                lines.append(f"{n} position {q:.4g} {u} below its lower limit {lim.position_lower[i]:.4g} {u}")
            else:
                lines.append(f"{n} position {q:.4g} {u} above its upper limit {lim.position_upper[i]:.4g} {u}")
        for i in vel:
            n, v, u = self._names[i], float(w.vel_value[i]), vel_u[i]
            vals[f"{n}_velocity_{unit_key(u)}"] = v
            lines.append(f"{n} velocity {v:.4g} {u} beyond its limit {lim.velocity[i]:.4g} {u}")
        dec_u = self._units["deceleration"]
        for i in dec:
            n, a, u = self._names[i], float(w.dec_value[i]), dec_u[i]
            vals[f"{n}_deceleration_{unit_key(u)}"] = a
            lines.append(f"{n} decelerating at {abs(a):.4g} {u} (estimate) beyond its limit "
                         f"{lim.deceleration[i]:.4g} {u}")
        soft_lines = []
        for i in soft:
            n, q, u = self._names[i], float(w.soft_value[i]), pos_u[i]
            vals[f"{n}_soft_position_{unit_key(u)}"] = q
            soft_lines.append(f"{n} position {q:.4g} {u} outside its soft limits "
                              f"[{lim.soft_lower[i]:.4g}, {lim.soft_upper[i]:.4g}] {u}")
        if lines or soft_lines:
            vals["failure_label"] = CONTROL_ERROR
            level = ERROR if lines else WARN
            all_lines = lines + soft_lines
            more = f" (+{len(all_lines) - 1} more)" if len(all_lines) > 1 else ""
            return Status(LIMITS, level, all_lines[0] + more, hid, vals)
        return Status(LIMITS, OK, "positions and velocities within limits", hid, vals)

    def _residual_status(self, w: Window, hid: str) -> Status:
        s = self.settings
        have = w.res_n > 0
        if not have.any():
            return Status(RESIDUAL, OK, "effort not measured: no residual", hid, {"effort_measured": False})
        rms = np.full(self._nv, np.nan)
        rms[have] = np.sqrt(w.res_sq[have] / w.res_n[have])
        vals: dict = {"effort_measured": True}
        eff_u = self._units["effort"]
        for i, n in enumerate(self._names):
            if have[i]:
                vals[f"{n}_residual_rms_{unit_key(eff_u[i])}"] = float(rms[i])
        ratio = np.where(have, _limit_ratio(np.nan_to_num(rms), self._effort), 0.0)
        j = int(np.argmax(ratio))
        u = eff_u[j]  # the worst joint's unit names the key: worst_residual_rms_nm, _n if prismatic
        worst_rms = float(rms[j]) if have[j] else 0.0
        vals.update({"worst_joint": self._names[j], f"worst_residual_rms_{unit_key(u)}": worst_rms,
                     "residual_warn_ratio": s.residual_warn_ratio})
        if ratio[j] > s.residual_warn_ratio:
            vals["failure_label"] = CONTROL_ERROR
            return Status(RESIDUAL, WARN,
                          f"{self._names[j]} effort residual {rms[j]:.3g} {u} RMS ({float(ratio[j]) * 100:.0f}% of its "
                          f"{self._effort[j]:.4g} {u} limit): check payload, friction and the model",
                          hid, vals)
        return Status(RESIDUAL, OK, f"largest RMS residual {worst_rms:.3g} {u} ({self._names[j]})",
                      hid, vals)


class ClosedWindow:
    """One ended diagnostics window (:meth:`Monitor.close_window`): its joint_states status,
    and its rows still to fold into the effort, limits and residual statuses."""

    def __init__(self, monitor: Monitor, window: Window, joint_states: Status, hardware_id: str):
        self._monitor, self._w, self._js, self._hid = monitor, window, joint_states, hardware_id

    def statuses(self) -> list[Status]:
        """joint_states, effort, limits and residual; folds the rows (call once)."""
        m, w, hid = self._monitor, self._w, self._hid
        out = [self._js]
        if w.accepted == 0:
            msg = "no accepted joint_states since the last report"
            for name in (EFFORT, LIMITS, RESIDUAL):
                out.append(Status(name, STALE, msg, hid, {"failure_label": STATE_ERROR}))
            return out
        m._fold_window(w)
        return out + [m._effort_status(w, hid), m._limits_status(w, hid), m._residual_status(w, hid)]


__all__ = ["Monitor", "ClosedWindow", "JOINT_STATES", "EFFORT", "LIMITS", "RESIDUAL"]
