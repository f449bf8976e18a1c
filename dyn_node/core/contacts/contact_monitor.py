"""Live contact and energy awareness: the one object the node and the audit both drive.

Composes the momentum observer and the contact wrench (:mod:`dyn_node.core.contacts.observer`), the episode
state machine (:mod:`dyn_node.core.contacts.contact`) and the power balance
(:mod:`dyn_node.core.contacts.power_balance`), with the resets that make the observer's state reproducible
from a bag (recording start, a joint_states gap > ``stale_timeout``, a model or parameter change),
and builds ``dyn_node: contact`` and ``dyn_node: energy``. Pure: every time is passed in.

Discretisation: r exact over each step, model terms trapezoidal, effort held (docs/OBSERVER.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dyn_node.core.contacts.contact import (COLLISION, CONTACT, NONE, ContactDetector, ContactEpisode,
                                            ContactOptions)
from dyn_node.core.compiled import observer_kernels as ok
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.contacts.live_energy import EnergyPeaks, EnergyPeriod, LiveEnergy
from dyn_node.core.contacts.observer import (EFFORT_MISSING, RESET_GAP, MomentumObserver, ObserverEstimate,
                                             ObserverOptions, ObserverReset, WrenchEstimate,
                                             per_joint)
from dyn_node.core.contacts.power_balance import PeriodBalance, PowerBalance
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status
from dyn_node.core.robot.units import joint_units, unit_key
from dyn_node.errors import CONTROL_ERROR, STATE_ERROR

CONTACT_STATUS = NAME_PREFIX + "contact"
ENERGY_STATUS = NAME_PREFIX + "energy"
OBSERVER_EVENTS = NAME_PREFIX + "observer"
UNAVAILABLE = "unavailable"
#: reset codes of the node's own resets (the observer's: RESET_* in dyn_node.core.contacts.observer)
RESET_RECORDING = "recording_start"
RESET_MODEL = "model_change"
RESET_PARAMETERS = "parameter_change"
_LEVEL_RANK = {NONE: 0, CONTACT: 1, COLLISION: 2}
#: no estimate because the robot does not report it: said, but nothing is wrong (OK)
_NOT_MEASURED = frozenset({EFFORT_MISSING, "velocity_missing"})
_AXES = ("x", "y", "z")


@dataclass(frozen=True, kw_only=True)
class ContactSettings:
    """The parameters the monitor uses (see :func:`contact_settings`)."""

    observer_gain: tuple[float, ...] = (50.0,)
    contact_threshold: tuple[float, ...] = (0.05,)
    collision_threshold: tuple[float, ...] = (0.20,)
    contact_min_duration: float = 0.02
    contact_frame: str = ""
    stale_timeout: float = 0.5


def contact_settings(settings: Settings) -> ContactSettings:
    """The node's :class:`Settings` as the monitor's."""
    return ContactSettings(observer_gain=settings.observer_gain,
                           contact_threshold=settings.contact_threshold,
                           collision_threshold=settings.collision_threshold,
                           contact_min_duration=settings.contact_min_duration,
                           contact_frame=settings.contact_frame,
                           stale_timeout=settings.stale_timeout)


@dataclass(frozen=True)
class ContactSample:
    """One accepted joint_states message's answer. ``tau_ext`` (nv, model order, N·m|N) None:
    no estimate (``unavailable`` says why); ``wrench`` None also when the contact frame is
    singular at this sample (``wrench_singular``). ``state``: none|contact|collision|unavailable."""

    stamp_ns: int
    tau_ext: np.ndarray | None
    wrench: WrenchEstimate | None
    state: str
    reset: ObserverReset | None
    unavailable: str | None = None
    wrench_singular: bool = False
    unavailable_code: str | None = None


@dataclass(frozen=True)
class RowsSample:
    """:meth:`ContactMonitor.update_rows`' answer: per row the stamp used (ns), τ̂_ext (N×nv,
    NaN rows without estimate), the wrench (N×6), whether there is an estimate and a wrench
    (not singular), and the wrench's force (N)."""

    stamp_ns: np.ndarray
    tau_ext: np.ndarray
    wrench: np.ndarray
    estimated: np.ndarray
    has_wrench: np.ndarray
    force_n: np.ndarray


@dataclass(frozen=True)
class Observed:
    """:meth:`ContactMonitor.observe`'s result, for :meth:`ContactMonitor.finish`: the stamp
    used (ns), the observer's estimate and the sample."""

    stamp_ns: int
    estimate: ObserverEstimate
    q: Sequence[float]
    v: Sequence[float] | None
    effort: Sequence[float] | None


@dataclass(frozen=True)
class ObserverEvent:
    """A reset of the observer or the end of a power-balance period, published on
    ``~/observer_events`` so a replay can check it. ``time_s``: the stamp of the sample it
    happened at (a period: its last sample); ``samples``: a period's sample count."""

    event: str            # "reset" | "period"
    reason: str           # a reset's code, or "diagnostics period"
    message: str
    time_s: float
    samples: int = 0

    def status(self, hardware_id: str) -> Status:
        values = {"event": self.event, "reason": self.reason, "time_s": self.time_s}
        if self.event == "period":
            values["samples"] = self.samples
        return Status(OBSERVER_EVENTS, OK, self.message, hardware_id, values)


class ContactMonitor:
    """τ̂_ext, the contact wrench, contact episodes and the power balance for one model and one
    :class:`ContactSettings`. Raises ValueError / InputError for settings the model cannot take
    (a gain list of the wrong length, an unknown contact frame). ``history_limit``: ended
    episodes kept (None: all, as the audit needs; the node keeps the latest). Not thread-safe."""

    def __init__(self, dynamics: Dynamics, settings: ContactSettings, *,
                 history_limit: int | None = None):
        model = dynamics.model
        nv = model.nv
        self.settings = settings
        self.frame = settings.contact_frame or model.last_link
        self._names = model.joint_names
        self._units = joint_units(model)["effort"]
        options = ContactOptions(contact_threshold=settings.contact_threshold,
                                 collision_threshold=settings.collision_threshold,
                                 min_duration_s=settings.contact_min_duration,
                                 history_limit=history_limit)
        self.detector = ContactDetector(model.joint_names, model.limits.effort, units=self._units,
                                        frame=self.frame, options=options)
        self.power = PowerBalance(dynamics)
        d = self.detector
        self.observer = MomentumObserver(
            dynamics, options=ObserverOptions(gain=per_joint(settings.observer_gain, nv, "observer_gain"),
                                              max_gap_s=settings.stale_timeout),
            frame=self.frame, contact_at=d.contact_level,
            power=self.power.state)
        self._nv = nv
        self.energy = LiveEnergy(model, include_armature=dynamics.options.include_armature)
        self._gap_ns = int(round(settings.stale_timeout * 1e9))
        self._last_receipt_ns: int | None = None
        self._events: list[ObserverEvent] = []
        self.last: ContactSample | None = None
        self._last_wrench: WrenchEstimate | None = None  # the last one computed, singular or not
        self.resets = 0
        self.estimates = 0
        #: samples without an estimate by reason code, and with a singular contact frame
        self.unavailable_by_code: dict[str, int] = {}
        self.wrench_singular = 0
        self._period_episode: ContactEpisode | None = None
        self._period_unavailable: dict[str, int] = {}

    # --- per sample -------------------------------------------------------------------------
    @property
    def episodes(self) -> list[ContactEpisode]:
        """Ended episodes, oldest first, then the open one (if any)."""
        d = self.detector
        return d.history + ([d.episode] if d.episode is not None else [])

    def reset(self, code: str, reason: str) -> ObserverReset:
        """Forget the observer's history (recording start, model or parameter change): the next
        valid sample restarts it, and that sample carries this reset (and its event)."""
        self.power.restart()
        return self.observer.reset(reason, code=code)

    def update(self, t_ns: int, stamp_ns: int, q: Sequence[float], v: Sequence[float] | None,
               effort: Sequence[float] | None) -> ContactSample:
        """One accepted joint state: receipt (log) time ``t_ns``, header stamp ``stamp_ns`` (0:
        the receipt is used), arrays in model order (v, effort None: not measured).
        :meth:`observe` then :meth:`finish`."""
        return self.finish(self.observe(t_ns, stamp_ns, q, v, effort))

    def observe(self, t_ns: int, stamp_ns: int, q: Sequence[float], v: Sequence[float] | None,
                effort: Sequence[float] | None) -> Observed:
        """The first half of :meth:`update`: resets and the observer's compiled pass (τ̂_ext,
        and the wrench and power sums the second half reads; the node publishes τ̂_ext before
        the episodes are worked out). Call :meth:`finish` with the result before the next sample."""
        prev = self._last_receipt_ns
        self._last_receipt_ns = t_ns
        if prev is not None and t_ns - prev > self._gap_ns:
            self.reset(RESET_GAP, self._gap_reason(t_ns - prev))
        stamp = stamp_ns if stamp_ns != 0 else t_ns
        est = self.observer.update(stamp * 1e-9, q, v, effort)
        return Observed(stamp, est, q, v, effort)

    def _gap_reason(self, gap_ns: int) -> str:
        return (f"no joint_states for {gap_ns * 1e-9:.9g} s "
                f"(> stale_timeout {self.settings.stale_timeout:g} s)")

    def finish(self, o: Observed) -> ContactSample:
        """The second half of :meth:`update`: the wrench, the episodes and the energies."""
        est, q, v = o.estimate, o.q, o.v
        t = o.stamp_ns * 1e-9
        if est.reset is not None:
            self._reset_event(est.reset, t)
        if v is not None:  # kept until the period closes: callers pass arrays they do not modify
            self.energy.add(np.asarray(q, dtype=float), np.asarray(v, dtype=float))
        if est.tau_ext is None:
            self.power.dropped()
            out = self._unavailable(t, o.stamp_ns, est.code or "no_estimate",
                                    est.unavailable or "no estimate", est.reset)
        else:
            info = self.observer.last_info
            self.power.noted(t, np.asarray(q, dtype=float), np.asarray(v, dtype=float),
                             int(info[ok.I_POWER_STEP]))
            self.estimates += 1
            w = self._last_wrench = WrenchEstimate.from_row(
                self.frame, self.observer.last_wrench.copy(), info, self.observer.wrench_options, self._nv)
            if w.singular:
                self.wrench_singular += 1
            good = None if w.singular else w
            d = self.detector
            # the pass's level test: nothing over, finite, no run open → update would change nothing
            if d.idle and info[ok.I_OVER] == 0.0 and math.isfinite(info[ok.I_FORCE]):
                state = NONE
            else:
                st = d.update(t, est.tau_ext, good)
                self._note(st.ended)
                self._note(st.episode)
                state = st.state
            out = ContactSample(o.stamp_ns, est.tau_ext, good, state, est.reset,
                                wrench_singular=w.singular)
        self.last = out
        return out

    def _reset_event(self, reset: ObserverReset, t: float) -> None:
        self.resets += 1
        self._events.append(ObserverEvent("reset", reset.code, f"observer reset: {reset.detail}", t))

    def _unavailable(self, t: float, stamp_ns: int, code: str, why: str,
                     reset: ObserverReset | None) -> ContactSample:
        self._count_unavailable(code)
        self._note(self.detector.unavailable(t, why).ended)
        return ContactSample(stamp_ns, None, None, UNAVAILABLE, reset, unavailable=why,
                             unavailable_code=code)

    def _count_unavailable(self, code: str) -> None:
        self.unavailable_by_code[code] = self.unavailable_by_code.get(code, 0) + 1
        self._period_unavailable[code] = self._period_unavailable.get(code, 0) + 1

    def update_rows(self, t_ns: np.ndarray, stamp_ns: np.ndarray, Q: np.ndarray,
                    V: np.ndarray | None, E: np.ndarray | None, *,
                    measured: np.ndarray | None = None) -> RowsSample:
        """N accepted joint states at once (receipt times and header stamps in ns, N×nv arrays
        in model order; V, E None: not in the messages; ``measured[k]`` False: row k has no
        effort): the same estimates, wrenches, episodes, resets, counts and power sums as
        :meth:`update` row by row, from one compiled pass. ``last`` is the last row's sample."""
        N = len(t_ns)
        t_ns = np.asarray(t_ns, dtype=np.int64)
        stamps = np.asarray(stamp_ns, dtype=np.int64)
        if stamps.shape != (N,):
            raise ValueError(f"stamp_ns needs {N} values, got shape {stamps.shape}")
        stamps = np.where(stamps != 0, stamps, t_ns)
        T = stamps * 1e-9
        prev = np.empty(N, dtype=np.int64)
        if N:
            prev[0] = self._last_receipt_ns if self._last_receipt_ns is not None else t_ns[0]
            prev[1:] = t_ns[:-1]
            self._last_receipt_ns = int(t_ns[-1])
        gap = (t_ns - prev) > self._gap_ns
        reasons = {k: ObserverReset(RESET_GAP, self._gap_reason(int(t_ns[k] - prev[k])))
                   for k in np.flatnonzero(gap).tolist()}
        rows = self.observer.update_rows(T, Q, V, E, reset=gap, reasons=reasons, measured=measured)
        info = rows.info
        if V is not None:
            self.energy.add_rows(np.asarray(Q, dtype=float), np.asarray(V, dtype=float))
        est = rows.code != ok.NO_ESTIMATE
        singular = est & (info[:, ok.I_SIGMA] < self.observer.wrench_options.singular_value)
        has_w = est & ~singular
        self.estimates += int(est.sum())
        self.wrench_singular += int(singular.sum())
        # the power period's first and last states (their energies are taken at close)
        if N:
            self._note_power_rows(T, Q, V, info, est)
        # counts and reset events in row order, then the episodes over every row
        unavailable = {k: why for k, (_code, why) in rows.unavailable.items()}
        for code, _why in rows.unavailable.values():
            self._count_unavailable(code)
        for k, r in sorted(rows.resets.items()):
            self._reset_event(r, float(T[k]))
        ended = self.detector.update_rows(T, rows.tau_ext, info[:, ok.I_FORCE], rows.wrench, has_w, unavailable)
        for ep in ended:
            self._note(ep)
        self._note(self.detector.episode)
        done = np.flatnonzero(est)
        if len(done):  # the last wrench computed, singular or not, as update leaves it
            j = int(done[-1])
            self._last_wrench = WrenchEstimate.from_row(self.frame, rows.wrench[j].copy(), info[j],
                                                        self.observer.wrench_options, self._nv)
        if N:
            k = N - 1
            if est[k]:
                lw = self._last_wrench
                self.last = ContactSample(int(stamps[k]), rows.tau_ext[k].copy(),
                                          None if singular[k] else lw, self.detector.state,
                                          rows.resets.get(k), wrench_singular=bool(singular[k]))
            else:
                code, why = rows.unavailable[k]
                self.last = ContactSample(int(stamps[k]), None, None, UNAVAILABLE, rows.resets.get(k),
                                          unavailable=why, unavailable_code=code)
        return RowsSample(stamps, rows.tau_ext, rows.wrench, est, has_w, info[:, ok.I_FORCE])

    def _note_power_rows(self, T: np.ndarray, Q: np.ndarray, V: np.ndarray, info: np.ndarray,
                         est: np.ndarray) -> None:
        """The power balance's first and last states over N rows of the pass."""
        pb = self.power
        step = info[:, ok.I_POWER_STEP]
        usable = est & (step != 2.0)
        first = np.flatnonzero(est & (step == 1.0))
        # a row without estimate restarts the period: nothing before it survives
        bad = np.flatnonzero(~est)
        if len(bad) and (not len(first) or bad[-1] > first[-1]):
            pb.dropped()
            return
        if len(first):
            f = int(first[-1])
            pb.noted(float(T[f]), Q[f], V[f], 1)
        idx = np.flatnonzero(usable)
        if len(idx):
            k = int(idx[-1])
            pb.noted(float(T[k]), Q[k], V[k], 0)

    def _note(self, ep: ContactEpisode | None) -> None:
        """Keep the worst episode of the diagnostics period (the latest view of each)."""
        cur = self._period_episode
        if ep is None:
            return
        if cur is None or cur.start_s == ep.start_s or _worse(ep, cur):
            self._period_episode = ep

    def pop_events(self) -> list[ObserverEvent]:
        """Resets and period ends since the last call, oldest first."""
        out, self._events = self._events, []
        return out

    # --- statuses -----------------------------------------------------------------------------
    def contact_status(self, now_ns: int, hardware_id: str = "") -> Status:
        """``dyn_node: contact`` for the period since the last call (the worst episode in it,
        ongoing or ended); starts a new period."""
        now = now_ns * 1e-9
        ep, open_ep = self._period_episode, self.detector.episode
        vals = self._contact_values(ep, now)
        level, label = OK, ""
        if ep is not None:
            level, label = (ERROR if ep.level == COLLISION else WARN), CONTROL_ERROR
            msg = ep.message(now) + ("" if ep.end_s is None else " (ended)")
        elif self.last is not None and self.last.tau_ext is None:
            msg = f"no external-torque estimate: {self.last.unavailable}"
            if any(c not in _NOT_MEASURED for c in self._period_unavailable):
                level, label = WARN, STATE_ERROR
        elif self.last is None:
            msg = "no joint_states yet: no external-torque estimate"
        else:
            msg = self._quiet_message()
        if label:
            vals["failure_label"] = label
        self._period_episode = open_ep
        self._period_unavailable = {}
        return Status(CONTACT_STATUS, level, msg, hardware_id, vals)

    def _quiet_message(self) -> str:
        r = self.last.tau_ext
        ratio = np.abs(r) / self.detector.limit
        j = int(np.argmax(ratio))
        return (f"no contact: largest |τ̂_ext| {abs(r[j]):.3g} {self._units[j]} at "
                f"{self._names[j]} ({ratio[j] * 100:.1f}% of its limit)")

    def _contact_values(self, ep: ContactEpisode | None, now: float) -> dict:
        last = self.last
        vals: dict = {"state": last.state if last is not None else UNAVAILABLE,
                      "contact_frame": self.frame}
        tau = last.tau_ext if last is not None and last.tau_ext is not None else None
        for i, n in enumerate(self._names):
            key = f"{n}_external_torque_{unit_key(self._units[i])}"
            vals[key] = float(tau[i]) if tau is not None else math.nan
        w = last.wrench if last is not None else None
        for k, a in enumerate(_AXES):
            vals[f"external_force_{a}_n"] = float(w.wrench[k]) if w is not None else math.nan
        for k, a in enumerate(_AXES):
            vals[f"external_moment_{a}_nm"] = float(w.wrench[3 + k]) if w is not None else math.nan
        vals["external_force_n"] = w.force_n if w is not None else math.nan
        lw = self._last_wrench
        vals["contact_frame_sigma_min"] = lw.sigma_min if lw is not None else math.nan
        vals["contact_time_s"] = ep.duration_s(now) if ep is not None else 0.0
        peak = ep.peak_force_n if ep is not None else None
        vals["peak_force_n"] = peak if peak is not None else math.nan
        vals["peak_joint"] = ep.joints[0].joint if ep is not None and ep.joints else ""
        vals["peak_ratio"] = ep.peak_ratio if ep is not None else 0.0
        d = self.detector
        vals.update(episodes=d.ended + (d.episode is not None), estimates=self.estimates,
                    observer_resets=self.resets,
                    observer_time_constant_s=float(self.observer.time_constant_s.max()),
                    wrench_singular_samples=self.wrench_singular)
        for code, n in sorted(self.unavailable_by_code.items()):
            vals[f"unavailable_{code}"] = n
        return vals

    def energy_status(self, now_ns: int, hardware_id: str = "") -> Status:
        """``dyn_node: energy``: kinetic energy at the last sample, and the power balance of the
        period that this call closes (its end is an :class:`ObserverEvent`).
        :meth:`close_energy_period` then :meth:`EnergyClose.status`."""
        return self.close_energy_period(now_ns).status(hardware_id)

    def close_energy_period(self, now_ns: int) -> EnergyClose:
        """The cheap half of :meth:`energy_status`, for under the node's joint_states lock: closes
        the power-balance period (its end event queued) and takes the period's states,
        unevaluated; the frame kernel runs in :meth:`EnergyClose.status`, outside the lock."""
        p = self.power.close()
        reading = self.power.reading() if p is not None else ""
        if p is not None:
            self._events.append(ObserverEvent("period", "diagnostics period", reading, p.end_s,
                                              samples=p.samples))
        no_effort = self.last is not None and self.last.unavailable_code == EFFORT_MISSING
        return EnergyClose(self.energy.swap(), p, reading, self.power.persistent_negative,
                           self.power.negative_run, self.power.broken_periods, no_effort)


@dataclass(frozen=True)
class EnergyClose:
    """A closed diagnostics period (:meth:`ContactMonitor.close_energy_period`): its states, not
    yet evaluated, and its power balance (None: fewer than two usable samples)."""

    period: EnergyPeriod
    balance: PeriodBalance | None
    reading: str
    persistent_negative: bool
    negative_run: int
    broken_periods: int
    effort_missing: bool

    def status(self, hardware_id: str = "") -> Status:
        """``dyn_node: energy`` of this period (evaluates its states)."""
        peaks = self.period.evaluate()
        vals, over = _energy_values(peaks)
        b = self.balance
        if b is not None:  # this period's (an earlier period's figures are not repeated)
            vals.update(power_balance_j=b.balance_j, measured_work_j=b.measured_work_j,
                        energy_change_j=b.delta_energy_j, friction_work_j=b.friction_work_j,
                        unexplained_j=b.unexplained_j, period_s=b.end_s - b.start_s,
                        tolerance_j=b.tolerance_j)
        vals.update(negative_periods_in_row=self.negative_run, broken_periods=self.broken_periods)
        if b is None:
            why = ("effort not measured" if self.effort_missing
                   else "fewer than two usable samples since the last period")
            reading, level = f"no power balance this period: {why}", OK
        else:
            reading = self.reading
            level = WARN if self.persistent_negative else OK
        if over:
            level = max(level, over[0][0])
            reading = f"{over[0][1]}; {reading}"
        elif peaks is not None and level == OK:
            reading = f"kinetic energy {peaks.kinetic_j:.3g} J; {reading}"
        if level != OK:
            vals["failure_label"] = CONTROL_ERROR
        return Status(ENERGY_STATUS, level, reading, hardware_id, vals)


def _energy_values(peaks: EnergyPeaks | None) -> tuple[dict, list[tuple[int, str]]]:
    """The energy status's kinetic and per-frame keys, and (level, text) of each limit the
    period's peaks exceeded, worst level first (speed and kinetic energy ERROR; the transferred
    energy, an advisory bound, WARN)."""
    if peaks is None:
        return {"kinetic_energy_j": math.nan}, []
    vals: dict = {"kinetic_energy_j": peaks.kinetic_j,
                  "kinetic_energy_peak_j": peaks.kinetic_peak_j,
                  "kinetic_energy_limit_j": peaks.kinetic_limit_j, "energy_states": peaks.states}
    over: list[tuple[int, str]] = []
    if peaks.kinetic_peak_j > peaks.kinetic_limit_j:  # NaN (no limit) never is
        over.append((ERROR, f"kinetic energy {peaks.kinetic_peak_j:.3g} J over its "
                            f"{peaks.kinetic_limit_j:.3g} J limit"))
    for f in peaks.frames:
        vals.update({f"{f.frame}_speed_m_s": f.speed_m_s,
                     f"{f.frame}_speed_limit_m_s": f.speed_limit_m_s,
                     f"{f.frame}_transferred_energy_j": f.energy_j,
                     f"{f.frame}_transferred_energy_limit_j": f.energy_limit_j})
        if f.speed_m_s > f.speed_limit_m_s:
            over.append((ERROR, f"{f.frame} at {f.speed_m_s:.3g} m/s over its "
                                f"{f.speed_limit_m_s:.3g} m/s limit"))
        if f.energy_j > f.energy_limit_j:
            over.append((WARN, f"{f.frame} transferred energy {f.energy_j:.3g} J over its "
                               f"{f.energy_limit_j:.3g} J limit (advisory)"))
    if peaks.skipped:
        vals["energy_states_skipped"] = peaks.skipped
    over.sort(key=lambda x: -x[0])
    return vals, over


def _worse(a: ContactEpisode, b: ContactEpisode) -> bool:
    ra, rb = _LEVEL_RANK[a.level], _LEVEL_RANK[b.level]
    return ra > rb or (ra == rb and a.peak_ratio > b.peak_ratio)


__all__ = ["ContactMonitor", "ContactSample", "EnergyClose", "Observed", "ContactSettings",
           "ObserverEvent", "contact_settings",
           "CONTACT_STATUS", "ENERGY_STATUS", "OBSERVER_EVENTS", "UNAVAILABLE",
           "RESET_RECORDING", "RESET_MODEL", "RESET_PARAMETERS"]
