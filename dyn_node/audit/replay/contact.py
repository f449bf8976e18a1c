"""dyn-audit's contact replay: joint_states through the node's own ContactMonitor, the recorded
~/external_torque, ~/external_wrench and ~/observer_events re-checked against it, and the
contact episodes as evidence (findings, a section of the record, a plot series).

The observer integrates its whole history, so the replay resets it where the node did: at the
start of the recording (before the first joint_states replayed), at each configuration change
at its ``effective_log_time_ns`` (a new monitor, as the node builds one, then reset), and at each
joint_states gap longer than ``stale_timeout`` (inside :meth:`ContactMonitor.update`, from the
log times, which are the node's receipt times). A power-balance period ends where the bag says
the node ended it (a recorded ``period`` event). Rules: docs/OBSERVER.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from dyn_node.audit.replay.common import (Pending, Recheck, SeriesBins, output_stamp_ns,
                                         worst_status_difference)
from dyn_node.bag.cdr import decode_joint_state
from dyn_node.errors import CONTROL_ERROR

ROLE_EXT_TORQUE, ROLE_EXT_WRENCH, ROLE_OBS_EVENTS = ("external_torque", "external_wrench",
                                                     "observer_events")
CONTACT_ROLES = (ROLE_EXT_TORQUE, ROLE_EXT_WRENCH, ROLE_OBS_EVENTS)
_SCHEMAS = {ROLE_EXT_TORQUE: "sensor_msgs/msg/JointState",
            ROLE_EXT_WRENCH: "geometry_msgs/msg/WrenchStamped",
            ROLE_OBS_EVENTS: "diagnostic_msgs/msg/DiagnosticStatus"}
MAX_LISTED = 1000  # episodes and resets listed in the record (the rest are counted)


def contact_role(topic: str, schema: str) -> str | None:
    """The role of one of the node's contact outputs (by topic name and type), else None."""
    last = topic.rstrip("/").rsplit("/", 1)[-1]
    return last if _SCHEMAS.get(last) == schema else None


def monitor_for(cfg: Any, dynamics: Any) -> Any:
    """The ContactMonitor the node builds for one configuration: on its Monitor's Dynamics."""
    from dyn_node.core.contacts.contact_monitor import ContactMonitor, contact_settings

    return ContactMonitor(dynamics, contact_settings(cfg.settings))


# --- the replay -----------------------------------------------------------------------------
@dataclass
class ContactResult:
    """What the contact replay gave, over every configuration replayed."""

    frame: str
    gain: list[float]
    contact_level: list[float]         # per joint, N·m|N: contact_threshold × effort limit
    episodes: list[Any]                # ContactEpisode (times: input stamps, s), oldest first
    resets: list[dict]                 # {"time_s" (stamp), "code", "reason"}, the first MAX_LISTED
    resets_total: int
    periods: int                       # power-balance periods closed
    samples: int
    estimated: int
    unavailable: dict[str, int]        # samples without an estimate, by reason code
    wrench_singular: int               # samples whose contact frame was singular (no wrench)
    #: SeriesBins over stamps, nv + 1 columns (τ̂_ext, then ‖F̂‖), or None
    series: Any


class ContactReplay:
    """Feeds every accepted joint_states to the configuration's ContactMonitor; the estimates
    and observer events go to ``sink`` (a :class:`ContactRecheck`, None: not kept), keyed like
    the node's outputs."""

    def __init__(self, cfg: Any, dynamics: Any, *, sink: "ContactRecheck | None" = None):
        self.sink = sink
        self.monitor: Any = None
        self._old: list[Any] = []       # the monitors before the current one
        self.resets: list[dict] = []
        self.resets_total = self.periods = 0
        self.samples = 0
        self.series: Any = None
        self._plot_t: list[int] = []
        self._plot_rows: list[tuple[np.ndarray, float]] = []
        self._started = False
        self.use(cfg, dynamics)
        self._at_start = True  # the monitor existed when the recording started

    def without_model(self) -> None:
        """The node had no model when the recording started (its description came later, on
        /robot_description): it monitored nothing until its first core, built at the first
        configuration change, and that core's observer simply starts; the replay does the same."""
        self.monitor, self._at_start = None, False

    def use(self, cfg: Any, dynamics: Any) -> None:
        """A new monitor for ``cfg`` on ``dynamics`` (the node builds one with every core, on
        each model or parameter change), reset from the configuration before, as the node does
        (DynNode._make_core)."""
        from dyn_node.core.contacts.contact_monitor import RESET_MODEL, RESET_PARAMETERS

        prev = self.cfg if self.monitor is not None else None
        if self.monitor is not None:
            self._old.append(self.monitor)
        self.cfg = cfg
        self.monitor = monitor_for(cfg, dynamics)
        self._at_start = False
        if prev is not None:
            model = prev.settings.model_key() != cfg.settings.model_key()
            self.monitor.reset(RESET_MODEL if model else RESET_PARAMETERS,
                               "model changed" if model else "parameters changed")

    def sample(self, t_ns: int, stamp_ns: int, key: int, q: np.ndarray, v: np.ndarray | None,
               effort: np.ndarray | None) -> None:
        """One accepted joint_states (model order; v, effort None: not in the message) at log
        time ``t_ns``, header stamp ``stamp_ns`` (0: zero-stamped, the receipt is used as the
        node does); ``key``: the stamp (ns) the node's outputs for it carry."""
        if not self._start():
            return  # the node had no core yet
        s = self.monitor.update(t_ns, stamp_ns, q, v, effort)
        self.samples += 1
        self._events()
        if s.tau_ext is None:
            return
        if self.sink is not None:
            self.sink.expect_estimate(key, s.tau_ext, s.wrench)
        self._plot(s.stamp_ns, s.tau_ext, s.wrench)  # on the episodes' clock: the stamps

    def _start(self) -> bool:
        """False while the node had no core; the recording-start reset before the first sample."""
        if self.monitor is None:
            return False
        if not self._started:
            from dyn_node.core.contacts.contact_monitor import RESET_RECORDING

            self._started = True
            if self._at_start:  # a core that ran before the recording: the node reset it
                self.monitor.reset(RESET_RECORDING, "recording started")
        return True

    def _events(self) -> None:
        for ev in self.monitor.pop_events():
            if ev.event == "reset":
                self.resets_total += 1
                if len(self.resets) < MAX_LISTED:
                    self.resets.append({"time_s": ev.time_s, "code": ev.reason,
                                        "reason": ev.message})
            else:
                self.periods += 1
            if self.sink is not None:
                self.sink.expect_event(ev)

    def recorded_output(self, role: str, m: Any, decoder: Any) -> None:
        """A recorded contact output, seen before the re-check takes it: a ``period`` event is
        where the node closed a power-balance period (its diagnostics timer, not an input), so
        the replay closes one there too."""
        if role != ROLE_OBS_EVENTS or not self._started or self.monitor is None:
            return
        try:
            st = decoder.decode(m.channel, m.data)
            event = next((kv.value for kv in st.values if kv.key == "event"), "")
        except Exception:  # noqa: BLE001 - a damaged event is the re-check's finding
            return
        if event == "period":
            self.monitor.energy_status(m.log_time_ns)
            self._events()

    def sample_result(self, t_ns: int, js: Any, r: Any, inputs: tuple) -> None:
        """An accepted message of the per-message path: decoded ``js``, Monitor result ``r``
        and the Monitor's ``last_inputs`` (q, v, effort in model order), which the node hands on."""
        key = output_stamp_ns(r.stamp_s) if r.zero_stamp else js.stamp_ns
        self.sample(t_ns, js.stamp_ns, key, *inputs)

    def sample_batch(self, ts: Sequence[int], jb: Any, b: Any) -> None:
        """Every row of a batch the Monitor accepted (decoded ``jb``, BatchResult ``b``). The
        batch path takes only messages whose efforts are all finite or all absent, so each row's
        inputs are the per-message path's."""
        E = None
        if jb.effort is not None and b.residual is not None:  # all-NaN effort: none, as per message
            idx, _ = self.cfg.model.mapping(jb.names)
            E = jb.effort[:, idx]
        V = b.v if jb.velocity is not None else None
        if not self._start():
            return
        measured = None if E is None or b.measured is None else b.measured
        rs = self.monitor.update_rows(np.asarray(ts, dtype=np.int64), jb.stamp_ns, b.q, V, E,
                                      measured=measured)
        self.samples += len(ts)
        self._events()
        est = np.flatnonzero(rs.estimated)
        if not len(est):
            return
        if self.sink is not None:
            keys = jb.stamp_ns.tolist()
            for k in np.flatnonzero(b.zero_stamp).tolist():
                keys[k] = output_stamp_ns(float(b.stamp_s[k]))
            frame = self.monitor.frame
            for k in est.tolist():
                self.sink.expect_rows(keys[k], rs.tau_ext[k], frame, rs.wrench[k] if rs.has_wrench[k] else None)
        force = np.where(rs.has_wrench, rs.force_n, np.nan)
        self._plot_rows_at(rs.stamp_ns[est], rs.tau_ext[est], force[est])

    def _plot(self, t_ns: int, tau: np.ndarray, wrench: Any) -> None:
        """Buffered rows for the plot series, binned a block at a time (add_batch)."""
        self._plot_t.append(t_ns)
        self._plot_rows.append((tau, wrench.force_n if wrench is not None else math.nan))
        if len(self._plot_t) >= 1024:
            self._flush_plot()

    def _flush_plot(self) -> None:
        if not self._plot_t:
            return
        T = np.array(self._plot_t, dtype=np.int64)
        rows = np.array([np.append(tau, f) for tau, f in self._plot_rows])
        self._plot_t, self._plot_rows = [], []
        self._bin(T, rows)

    def _plot_rows_at(self, T: np.ndarray, tau: np.ndarray, force: np.ndarray) -> None:
        """A batch's rows for the plot series (after the buffered single rows, in time order)."""
        self._flush_plot()
        self._bin(np.asarray(T, dtype=np.int64), np.column_stack([tau, force]))

    def _bin(self, T: np.ndarray, rows: np.ndarray) -> None:
        if self.series is None:
            self.series = SeriesBins(rows.shape[1], int(T[0]))
        zeros = np.zeros_like(rows)
        self.series.add_batch(T, rows, zeros, np.full_like(rows, np.inf),
                              np.full_like(rows, np.nan))

    def finish(self) -> ContactResult | None:
        self._flush_plot()
        monitors = self._old + ([self.monitor] if self.monitor is not None else [])
        if not monitors:
            return None
        m, model = monitors[-1], self.cfg.model
        st = m.settings
        nv = model.nv
        gain = np.broadcast_to(np.asarray(st.observer_gain, dtype=float), (nv,))
        level = (np.broadcast_to(np.asarray(st.contact_threshold, dtype=float), (nv,))
                 * np.asarray(model.limits.effort, dtype=float))
        unavailable: dict[str, int] = {}
        for mon in monitors:
            for code, n in mon.unavailable_by_code.items():
                unavailable[code] = unavailable.get(code, 0) + n
        return ContactResult(frame=m.frame, gain=gain.tolist(), contact_level=level.tolist(),
                             episodes=[e for mon in monitors for e in mon.episodes],
                             resets=self.resets, resets_total=self.resets_total,
                             periods=self.periods,
                             samples=self.samples, estimated=sum(mon.estimates for mon in monitors),
                             unavailable=unavailable,
                             wrench_singular=sum(mon.wrench_singular for mon in monitors),
                             series=self.series)


# --- the re-check ---------------------------------------------------------------------------
class ContactRecheck:
    """The recorded contact outputs against the replayed ones. Shares the Rechecker's tables
    (``want``, ``pending``, ``checks``, ``topics``), so the record's re-check section and the
    verdict treat them like every other output. Observer events are compared in order."""

    def __init__(self, rechecker: Any):
        self.r = rechecker
        known = rechecker.known_topics
        for role in CONTACT_ROLES:
            rechecker.want[role] = known is None or any(
                t.rstrip("/").rsplit("/", 1)[-1] == role for t in known)
            rechecker.pending[role] = Pending()
            rechecker.checks[role] = Recheck()
        # observer events: one FIFO under key 0 (compared in order; left over: unanswered)
        self.events = rechecker.pending[ROLE_OBS_EVENTS]

    # what the replay recomputed ------------------------------------------------------------
    def expect_estimate(self, key: int, tau: np.ndarray, wrench: Any) -> None:
        self.expect_rows(key, tau, wrench.frame if wrench is not None else "",
                         wrench.wrench if wrench is not None else None)

    def expect_rows(self, key: int, tau: np.ndarray, frame: str, wrench: np.ndarray | None) -> None:
        """One estimate (τ̂_ext, and the wrench at ``frame``, None while singular)."""
        want, pending = self.r.want, self.r.pending
        if want[ROLE_EXT_TORQUE]:
            pending[ROLE_EXT_TORQUE].put(key, np.asarray(tau, dtype=float))
        if want[ROLE_EXT_WRENCH] and wrench is not None:
            pending[ROLE_EXT_WRENCH].put(key, (frame, np.asarray(wrench, dtype=float)))

    def expect_event(self, ev: Any) -> None:
        if self.r.want[ROLE_OBS_EVENTS]:
            self.events.put(0, ev)

    # what the node recorded ----------------------------------------------------------------
    def output(self, role: str, m: Any, model: Any) -> None:
        self.r.topics[role] = m.topic
        if role == ROLE_EXT_TORQUE:
            self._torque(m, model)
        elif role == ROLE_EXT_WRENCH:
            self._wrench(m)
        else:
            self._event(m)

    def _torque(self, m: Any, model: Any) -> None:
        chk = self.r.checks[ROLE_EXT_TORQUE]
        try:
            out = decode_joint_state(m.data)
        except ValueError:
            chk.unmatched += 1
            return
        want = self.r.pending[ROLE_EXT_TORQUE].take(out.stamp_ns)
        if want is None:
            chk.unmatched += 1
            return
        got, names = out.effort, list(model.joint_names)
        if list(out.names) != names and set(out.names) == set(names):
            got = got[[list(out.names).index(n) for n in names]]
        d = float(np.max(np.abs(got - want))) if got.shape == want.shape else math.inf
        chk.diff(d, {"stamp_ns": out.stamp_ns, "t_ns": m.log_time_ns})

    def _wrench(self, m: Any) -> None:
        chk = self.r.checks[ROLE_EXT_WRENCH]
        try:
            msg = self.r.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001 - a damaged output is a finding, not a crash
            chk.unmatched += 1
            return
        key = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        want = self.r.pending[ROLE_EXT_WRENCH].take(key)
        if want is None:
            chk.unmatched += 1
            return
        frame, w = want
        f, t = msg.wrench.force, msg.wrench.torque
        got = np.array([f.x, f.y, f.z, t.x, t.y, t.z], dtype=float)
        chk.mismatched_values += msg.header.frame_id != frame
        chk.diff(float(np.max(np.abs(got - w))), {"stamp_ns": key, "t_ns": m.log_time_ns})

    def _event(self, m: Any) -> None:
        """A recorded ~/observer_events status against the next event the replay made: every
        value (numbers by difference, text exactly) and the message."""
        from dyn_node.core.robot.status import format_value

        chk = self.r.checks[ROLE_OBS_EVENTS]
        try:
            st = self.r.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001
            chk.unmatched += 1
            return
        ev = self.events.take(0)
        if ev is None:
            chk.unmatched += 1
            return
        mine = ev.status("")
        # a differing name counts as one differing value there
        worst, where, mismatched = worst_status_difference(
            [st], {mine.name: {k: format_value(v) for k, v in mine.values.items()}})
        recorded = {kv.key: kv.value for kv in st.values}
        mismatched += (st.message != mine.message) + (set(recorded) != set(mine.values))
        chk.mismatched_values += mismatched
        chk.diff(worst, {"t_ns": m.log_time_ns, "event": recorded.get("event"),
                         "reason": recorded.get("reason"), **(where or {})})


# --- evidence -------------------------------------------------------------------------------
def _rel(t_s: float | None, start_ns: int) -> float | None:
    """A stamp time (s) relative to the bag's first log time."""
    return None if t_s is None else t_s - start_ns * 1e-9


def episode_entry(ep: Any, start_ns: int) -> dict:
    return {"start_s": _rel(ep.start_s, start_ns), "end_s": _rel(ep.end_s, start_ns),
            "duration_s": ep.duration_s() if ep.end_s is not None else None,
            "level": ep.level, "frame": ep.frame, "peak_force_n": ep.peak_force_n,
            "peak_wrench": None if ep.peak_wrench is None else [float(x) for x in ep.peak_wrench],
            "joints": [{"joint": j.joint, "peak_torque": j.torque, "peak_ratio": j.ratio,
                        "effort_limit": j.limit, "unit": j.unit} for j in ep.joints],
            "end_reason": ep.end_reason, "failure_label": CONTROL_ERROR}


def contact_section(res: ContactResult | None, start_ns: int) -> dict | None:
    """outputs.contact of the record (None: no joint_states replayed)."""
    if res is None or not res.samples:
        return None
    return {"frame": res.frame, "observer_gain_per_s": res.gain,
            "time_constant_s": float(1.0 / min(res.gain)), "contact_level": res.contact_level,
            "samples": res.samples, "estimated": res.estimated, "unavailable": res.unavailable,
            "wrench_singular_samples": res.wrench_singular,
            "episodes": [episode_entry(e, start_ns) for e in res.episodes[:MAX_LISTED]],
            "episodes_total": len(res.episodes),
            "resets": [{"time_s": _rel(r["time_s"], start_ns), "code": r["code"],
                        "reason": r["reason"]} for r in res.resets],
            "resets_total": res.resets_total, "power_balance_periods": res.periods}


def contact_findings(section: dict | None) -> list[str]:
    """One finding per contact episode (the first 20, then a count)."""
    if not section:
        return []
    out = []
    for e in section["episodes"][:20]:
        end = "the end of the recording (ongoing)" if e["end_s"] is None else f"{e['end_s']:.3f} s"
        force = (f"peak {e['peak_force_n']:.3g} N at {e['frame']}; "
                 if e["peak_force_n"] is not None else "")
        joints = ", ".join(f"{j['joint']} {j['peak_torque']:.3g} {j['unit']} of "
                           f"{j['effort_limit']:.4g}" for j in e["joints"][:3])
        out.append(f"{e['level']} from {e['start_s']:.3f} s to {end}: {force}{joints}")
    if section["episodes_total"] > 20:
        out.append(f"{section['episodes_total'] - 20} more contact episode(s) in outputs.contact")
    return out
