"""dyn-audit's stage 2, the replay of the inputs: joint_states through the node's Monitor and
ControllerTracker, trajectories and inverse-dynamics requests through its check, and each kind of
recorded event through its own replayer (:mod:`.contact`, :mod:`.services`, :mod:`.gates`), a new
core from each configuration change on. A new kind of input is a replayer and a line in
:meth:`Replay.feed`. Batch replay: docs/BAGS.md."""
from __future__ import annotations

import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from dyn_node.audit.accounting import EXECUTE, INVERSE_DYNAMICS, RequestTally, request_of_role
from dyn_node.audit.evidence import add_per_frame
from dyn_node.audit.replay.common import output_stamp_ns
from dyn_node.audit.replay.config import Config
from dyn_node.audit.replay.contact import CONTACT_ROLES, ContactReplay
from dyn_node.audit.replay.gates import ROLE_GATE, GateReplay
from dyn_node.audit.replay.roles import ROLE_CHECK, ROLE_CTRL, ROLE_JOINT_STATES, ROLE_STATES, ROLE_TRAJECTORY
from dyn_node.audit.replay.services import ROLE_SERVICE_EVENT, ServiceReplay
from dyn_node.audit.replay.stats import MAX_EPISODES, LiveStats
from dyn_node.bag.cdr import decode_joint_state, decode_joint_state_batch
from dyn_node.bag.reader import BagMessage, MessageDecoder
from dyn_node.errors import PLANNING_ERROR, STATE_ERROR, InputError, TrajectoryError

if TYPE_CHECKING:
    from dyn_node.audit.replay.recheck import Rechecker

MAX_EXAMPLES = 50        # invalid / out-of-order examples and gaps listed
MAX_TRAJECTORIES = 1000  # per-trajectory verdicts listed (the rest are counted)
MIN_BATCH = 16           # shorter runs of joint_states are replayed message by message
MAX_RUN = 2048           # joint_states replayed per batch (bounds memory)
MAX_CURVE_TRAJECTORIES = 50  # trajectory entries that carry per_frame_curves (≤ 400 points each)


class Capped:
    """A count, and the first ``cap`` items for the record."""

    def __init__(self, cap: int):
        self.cap = cap
        self.items: list[dict] = []
        self.total = 0

    def add(self, item: dict) -> None:
        self.total += 1
        if len(self.items) < self.cap:
            self.items.append(item)


class ControllerTimeline:
    """The replayed controller states: transitions (the first MAX_EPISODES), time in each state,
    and the states the node recorded on ~/controller_status (informational)."""

    def __init__(self) -> None:
        self.transitions: list[dict] = []
        self.time_in_state: dict[str, float] = {}
        self.last: tuple[str, int] | None = None
        self.recorded: dict[str, int] = {}

    def enter(self, state: str, t_ns: int) -> None:
        self.close(t_ns)
        self.last = (state, t_ns)
        if len(self.transitions) < MAX_EPISODES:
            self.transitions.append({"t_ns": t_ns, "state": state})

    def close(self, t_ns: int | None) -> None:
        """The time in the current state until ``t_ns``."""
        if self.last is not None and t_ns is not None:
            st, since = self.last
            self.time_in_state[st] = self.time_in_state.get(st, 0.0) + (t_ns - since) * 1e-9


@dataclass
class ReplayResult:
    """What replaying the inputs gave: the live statistics, the input quality, the trajectory
    verdicts and the controller timeline, under the last configuration replayed."""

    live: LiveStats
    counts: Any                 # Monitor counts, carried across configurations as in the node
    model: Any                  # the last configuration's model and settings
    settings: Any
    js_topics: set[str]
    last_log_ns: int | None     # latest joint_states log time
    gaps: Capped
    stale: Capped
    invalid: Capped
    invalid_by_reason: dict[str, int]
    out_of_order: list[dict]
    trajectories: Capped
    trajectories_bad: int       # executed trajectories infeasible or rejected
    trajectory_failure_labels: set[str]
    controller: ControllerTimeline
    contact: Any = None         # audit.replay.contact.ContactResult
    tally: RequestTally = field(default_factory=RequestTally)  # executed vs questions, exact
    questions: dict = field(default_factory=dict)  # service questions answered, per service
    gate: dict = field(default_factory=dict)  # the gate's decisions (its goals are executed)


class Replay:
    """Stage 2: joint_states through the node's Monitor and ControllerTracker, trajectories
    through check_trajectory, a new core from each configuration change on. The values the node
    would have published go to ``sink`` (the re-check; None: not kept)."""

    def __init__(self, configurations: Sequence[Config], *, gap_threshold_s: float = 0.05,
                 decoder: MessageDecoder | None = None, sink: "Rechecker | None" = None,
                 threads: int = 2):
        first = configurations[0]
        self.changes = list(configurations[1:])
        lim = first.model.limits
        self.live = LiveStats(first.model.nv, lim.position_lower, lim.position_upper, lim.velocity,
                              lim.deceleration)
        self.monitor: Any = None
        self.tracker: Any = None
        self.contact: ContactReplay | None = None
        self._use(first)
        self.decoder = decoder or MessageDecoder()
        self.sink = sink
        self.gap_ns = gap_threshold_s * 1e9
        # (model, log time ns, q, q̇) of the last accepted joint_states: a trajectory whose first
        # point lies ahead starts from it, as in the node (feasibility.current_state)
        self.last_state: tuple[Any, int, np.ndarray, np.ndarray] | None = None
        self.prev_log: int | None = None
        self.js_topics: set[str] = set()
        self.gaps, self.stale, self.invalid = Capped(MAX_EXAMPLES), Capped(MAX_EXAMPLES), Capped(MAX_EXAMPLES)
        self.invalid_by_reason: dict[str, int] = {}
        self.out_of_order: list[dict] = []
        self.trajectories = Capped(MAX_TRAJECTORIES)
        self.trajectories_bad = 0
        self.tally = RequestTally()
        self.trajectory_failure_labels: set[str] = set()
        self.controller = ControllerTimeline()
        # Consecutive joint_states of one topic with one byte layout and no gap are queued as a
        # run and replayed in one batch (decoded at once, Monitor.process_batch); anything else,
        # and any run the batch path declines, goes message by message. Both give the same numbers.
        self._run_topic, self._run_len, self._run_t, self._run_d = "", -1, [], []
        self.contact = ContactReplay(first, self.monitor.dynamics, sink=sink.contact if sink is not None else None)
        # A batch's contact pass (the observer's compiled kernel, which lets go of the GIL) runs
        # on a second thread while this one replays the next batch; anything else that touches
        # the contact replay or runs the Monitor per message first waits for it (_contact_ready).
        self._contact_pool: ThreadPoolExecutor | None = None
        self._threads = threads  # 1: the contact pass runs in turn
        self._contact_job: Future | None = None
        # the question services' request/response pairs, counted in the same tally
        self.services = ServiceReplay(sink, tally=self.tally)
        self.gates = GateReplay(sink, tally=self.tally, tracker=lambda: self.tracker)  # executed, decided again

    def feed(self, role: str, m: BagMessage) -> bool:
        """Replay one message; False when its role is not an input (a recorded output)."""
        t_ns = m.log_time_ns
        if self.changes and t_ns >= self.changes[0].since_ns:
            self.flush()  # the queued joint_states were taken under the configuration before
            while self.changes and t_ns >= self.changes[0].since_ns:
                cfg = self.changes.pop(0)
            self._switch(cfg)
        if role == ROLE_JOINT_STATES:
            self._queue(m.topic, t_ns, m.data)
            return True
        self.flush()
        self._contact_ready()
        if role in (ROLE_TRAJECTORY, ROLE_CHECK):
            self._trajectory_request(role, m)
        elif role == ROLE_STATES:
            self._states_request(m)
        elif role == ROLE_SERVICE_EVENT:
            self.services.feed(m, self.decoder, self.traj_dynamics, self.settings)
        elif role == ROLE_GATE:
            self.gates.feed(m, self.decoder, self.traj_dynamics, self.settings)
        elif role == ROLE_CTRL:
            self._recorded_status(m)
        elif role in CONTACT_ROLES:
            self.contact.recorded_output(role, m, self.decoder)
            return False  # a recorded output: the re-check compares it
        else:
            return False
        return True

    def finish(self) -> ReplayResult:
        self.flush()
        self._contact_ready()
        if self._contact_pool is not None:
            self._contact_pool.shutdown()
            self._contact_pool = None
        self.live.finish()
        self.controller.close(self.prev_log)
        return ReplayResult(self.live, self.monitor.counts, self.model, self.settings,
                            self.js_topics, self.prev_log, self.gaps, self.stale, self.invalid,
                            self.invalid_by_reason, self.out_of_order, self.trajectories,
                            self.trajectories_bad + self.gates.bad,
                            self.trajectory_failure_labels | ({PLANNING_ERROR} if self.gates.bad else set()),
                            self.controller, contact=self.contact.finish(), tally=self.tally,
                            questions=self.services.finish(), gate=self.gates.finish())

    def _switch(self, cfg: Config) -> None:
        """What the node does when a parameter is set: a new core from now on."""
        self.live.flush()
        self._contact_ready()
        self._use(cfg)

    def _use(self, cfg: Config) -> None:
        """A core (monitor, tracker, dynamics, live limits) for ``cfg``; a previous core's
        counts and the plan it was tracking carry over."""
        from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
        from dyn_node.core.live.monitor import Monitor
        from dyn_node.core.live.tracker import ControllerTracker

        self.settings, self.model = cfg.settings, cfg.model
        self.monitor = Monitor(cfg.model, cfg.settings,
                               self.monitor.counts if self.monitor is not None else None)
        tracker = ControllerTracker(cfg.model, cfg.settings)
        if self.tracker is not None:
            tracker._plan = self.tracker._plan
        self.tracker = tracker
        self.traj_dynamics = Dynamics(cfg.model, DynamicsOptions(
            include_friction=cfg.settings.include_friction))
        cl = cfg.model.limits
        live = self.live
        live.lo, live.hi, live.vel = cl.position_lower, cl.position_upper, cl.velocity
        live.dec = cl.deceleration
        if self.contact is not None:
            self.contact.use(cfg, self.monitor.dynamics)

    # joint_states --------------------------------------------------------------------------
    def _queue(self, topic: str, t_ns: int, data: bytes) -> None:
        run_t = self._run_t
        if (topic == self._run_topic and len(data) == self._run_len and self._run_d
                and 0 <= t_ns - run_t[-1] <= self.gap_ns and len(self._run_d) < MAX_RUN):
            run_t.append(t_ns)
            self._run_d.append(data)
            return
        self.flush()
        self._gap_check(topic, t_ns)
        self._run_topic, self._run_len, self._run_t, self._run_d = topic, len(data), [t_ns], [data]

    def flush(self) -> None:
        """Replay the queued run of joint_states: in one batch, or message by message."""
        if not self._run_d:
            return
        ts, datas = self._run_t, self._run_d
        self._run_t, self._run_d = [], []
        if len(datas) < MIN_BATCH or not self._js_batch(ts, datas):
            self._contact_ready()
            for t, d in zip(ts, datas):
                self._js_one(self._run_topic, t, d)
        self.prev_log = max(self.prev_log, ts[-1])

    def _gap_check(self, topic: str, t_ns: int) -> None:
        self.js_topics.add(topic)
        prev_log = self.prev_log
        if prev_log is not None and t_ns - prev_log > self.gap_ns:
            g = {"start_ns": prev_log, "end_ns": t_ns}
            # nothing is known about the limits during a gap: a violation episode ends at
            # its last sample before it, and one after it is a new episode
            self.live.finish()
            self.gaps.add(g)
            if t_ns - prev_log > self.settings.stale_timeout * 1e9:
                self.stale.add(g)
                # The node's controller-status timer sees the silence: stale just after
                # stale_timeout (its timer period is not replayed).
                stale_ns = prev_log + int(self.settings.stale_timeout * 1e9) + 1000
                if self.tracker.tick(stale_ns * 1e-9):
                    self.controller.enter(self.tracker.state, stale_ns)
        self.prev_log = t_ns if prev_log is None or t_ns > prev_log else prev_log

    def _js_one(self, topic: str, t_ns: int, data: bytes) -> None:
        receipt_s = t_ns * 1e-9
        try:
            js = decode_joint_state(data)
        except ValueError as exc:  # counted and tracked as the node does (Monitor.reject_message)
            r = self.monitor.reject_message(InputError(str(exc), code="undecodable"), receipt_s)
        else:
            stamp_s = js.sec + js.nanosec * 1e-9
            r = self.monitor.process(js.names, js.position, js.velocity, js.effort, stamp_s, receipt_s)
        if self.tracker.update(r, receipt_s) or self.controller.last is None:
            self.controller.enter(self.tracker.state, t_ns)
        if not r.accepted:
            code = r.error.code
            self.invalid_by_reason[code] = self.invalid_by_reason.get(code, 0) + 1
            self.invalid.add({"t_ns": t_ns, "reason": str(r.error), "code": code, "topic": topic})
            return
        self.last_state = (self.model, t_ns, r.q, r.v)
        if r.out_of_order and len(self.out_of_order) < MAX_EXAMPLES:
            self.out_of_order.append({"t_ns": t_ns, "stamp_ns": js.stamp_ns})
        if self.sink is not None:
            stamp_key = output_stamp_ns(r.stamp_s) if r.zero_stamp else js.stamp_ns
            self.sink.expect_state(stamp_key, t_ns, r.gravity, r.tau)
        tau = r.tau
        self.contact.sample_result(t_ns, js, r, self.monitor.last_inputs)
        self.live.add(t_ns, tau, r.utilisation, r.effort_limit, r.q, r.v,
                      None if r.residual is None else r.residual + tau, r.a_hat)

    def _js_batch(self, ts: list[int], datas: list[bytes]) -> bool:
        jb = decode_joint_state_batch(datas)
        if jb is None or jb.position is None:
            return False
        stamp_s = jb.sec.astype(float) + jb.nanosec.astype(float) * 1e-9
        T = np.array(ts, dtype=np.int64)
        receipt = T.astype(float) * 1e-9
        b = self.monitor.process_batch(jb.names, jb.position, jb.velocity, jb.effort, stamp_s, receipt)
        if b is None:
            return False
        self.last_state = (self.model, ts[-1], b.q[-1], b.v[-1])  # every row was accepted
        before = self.tracker.state
        changes = self.tracker.update_batch(b, receipt)
        if self.controller.last is None and (not changes or changes[0][0] != 0):
            changes.insert(0, (0, before))  # row 0 left the state as it was
        for k, st in changes:
            self.controller.enter(st, ts[k])
        ooo = self.out_of_order
        if len(ooo) < MAX_EXAMPLES and b.out_of_order.any():
            for k in np.flatnonzero(b.out_of_order)[:MAX_EXAMPLES - len(ooo)].tolist():
                ooo.append({"t_ns": ts[k], "stamp_ns": int(jb.stamp_ns[k])})
        if self.sink is not None and self.sink.wants_states:
            keys = jb.stamp_ns.tolist()
            for k in np.flatnonzero(b.zero_stamp).tolist():
                keys[k] = output_stamp_ns(float(b.stamp_s[k]))
            for k, key in enumerate(keys):
                self.sink.expect_state(key, ts[k], b.gravity[k], b.tau[k])
        meas = (b.residual + b.tau if b.residual is not None
                else np.full(b.tau.shape, np.nan))
        self._contact_batch(ts, jb, b)
        self.live.add_arrays(T, b.tau, b.utilisation, b.effort_limit, b.q, b.v, meas, b.a_hat)
        return True

    def _contact_batch(self, ts: list[int], jb: Any, b: Any) -> None:
        """The contact replay of a batch, on the second thread once the previous one is done."""
        self._contact_ready()
        if self._threads < 2:
            self.contact.sample_batch(ts, jb, b)
            return
        if self._contact_pool is None:
            self._contact_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dyn-audit-contact")
        self._contact_job = self._contact_pool.submit(self.contact.sample_batch, ts, jb, b)

    def _contact_ready(self) -> None:
        """Wait for the contact pass in flight; its exception, if it raised one, is raised here."""
        job, self._contact_job = self._contact_job, None
        if job is not None:
            job.result()

    # trajectories and requests -------------------------------------------------------------
    def _trajectory_request(self, role: str, m: BagMessage) -> None:
        execute = request_of_role(role) == EXECUTE
        entry, res = self._trajectory(m, self.trajectories.total, track=execute)
        entry["request"] = request_of_role(role)
        self.tally.add(entry["request"], answered_yes=entry["feasible"])
        # a check-only request is a question: its "no" is listed, not a violation of the run
        if entry.get("failure_label") and execute:
            self.trajectory_failure_labels.add(entry["failure_label"])
        if not entry["feasible"] and execute:
            self.trajectories_bad += 1
        self.trajectories.add(entry)
        if self.sink is not None:
            # answers are matched by the whole header the node echoes (stamp and frame_id)
            key = (entry["stamp_ns"], entry.get("frame_id", ""))
            self.sink.expect_verdict(key, res if res is not None else entry)
            if res is not None:
                self.sink.expect_efforts(key, res.waypoint_effort)

    def _trajectory(self, m: BagMessage, index: int, *, track: bool):
        """The node's verdict on a trajectory message, recomputed; ``track``: hand it to the
        controller tracker first, as the node does with one it executes."""
        from dyn_node.core.check.feasibility import NO_CURRENT_STATE, Timing, check_trajectory, current_state
        from dyn_node.core.check.on_demand import options_for
        from dyn_node.core.check.trajectory import validate_trajectory

        entry: dict[str, Any] = {"index": index, "topic": m.topic, "time_s": 0.0, "t_ns": m.log_time_ns,
                                 "stamp_ns": 0, "accepted": False, "feasible": False}
        n_points = 0
        traj = None
        try:
            msg = self.decoder.decode(m.channel, m.data)
            st = msg.header.stamp
            entry["stamp_ns"] = int(st.sec) * 1_000_000_000 + int(st.nanosec)
            stamp_s = st.sec + st.nanosec * 1e-9        # as the node reads it (convert.stamp_to_s)
            entry["frame_id"] = msg.header.frame_id
            pts = msg.points
            n_points = len(pts)
            # as the node does (ros_convert.trajectory_arrays, DynNode._check_trajectory): a
            # single point is tracked but not checked
            times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
            args = (self.model.joint_names, list(msg.joint_names), times, [p.positions for p in pts],
                    [p.velocities for p in pts], [p.accelerations for p in pts])
            # the effort lists only validated (joint_trajectory_controller's rule), as the node does
            traj = validate_trajectory(*args, min_points=1, efforts=[p.effort for p in pts])
            last, start = self.last_state, None
            if last is not None and last[0].joint_names == self.model.joint_names:
                start = current_state(last[1:], m.log_time_ns, self.settings.stale_timeout)
            # the node's receipt time is the log time it recorded with
            timing = Timing(stamp_s, m.log_time_ns * 1e-9)
            if track:
                self.tracker.follow(traj, timing=timing, start=start,
                                    options=options_for(self.settings).execution)
            if traj.n_points < 2:
                validate_trajectory(*args, min_points=2)
        except TrajectoryError as exc:
            dur = float(times[-1]) if times and all(map(math.isfinite, times)) else 0.0
            entry.update(level="ERROR", message=f"rejected: {exc}", error_code=exc.code,
                         failure_label=PLANNING_ERROR, n_points=n_points, duration_s=dur)
            return entry, None
        except Exception as exc:  # noqa: BLE001 - undecodable bytes are a finding, not a crash
            entry.update(level="ERROR", message=f"undecodable trajectory message: {exc}",
                         error_code="undecodable", failure_label=STATE_ERROR)
            return entry, None
        try:
            res = check_trajectory(self.traj_dynamics, traj, options_for(self.settings),
                                   start=start, start_unknown=NO_CURRENT_STATE, timing=timing)
        except TrajectoryError as exc:  # e.g. torques that overflow: the node publishes "rejected"
            entry.update(level="ERROR", message=f"rejected: {exc}", error_code=exc.code,
                         failure_label=PLANNING_ERROR, n_points=n_points,
                         duration_s=float(times[-1]))
            return entry, None
        return _verdict_entry(entry, res), res

    def _states_request(self, m: BagMessage) -> None:
        """Recompute the node's answer to an ~/inverse_dynamics_request (torques, or the rejected
        verdict), keyed by the request's header like the node's answer."""
        from dyn_node.core.check import on_demand

        try:
            msg = self.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001 - undecodable: the node could not answer it either
            return
        st = msg.header.stamp
        key = (int(st.sec) * 1_000_000_000 + int(st.nanosec), msg.header.frame_id)
        pts = msg.points
        try:
            Q, V, A = on_demand.states(self.model.joint_names, list(msg.joint_names),
                                       [p.positions for p in pts], [p.velocities for p in pts],
                                       [p.accelerations for p in pts])
            tau = on_demand.inverse_dynamics(self.traj_dynamics, Q, V, A)
        except TrajectoryError as exc:
            self.tally.add(INVERSE_DYNAMICS, answered_yes=False)
            if self.sink is not None:
                self.sink.expect_verdict(key, {"message": f"rejected: {exc}", "error_code": exc.code,
                                               "n_points": len(pts), "duration_s": math.nan})
            return
        self.tally.add(INVERSE_DYNAMICS, answered_yes=True)
        if self.sink is not None:
            self.sink.expect_efforts(key, tau)

    def _recorded_status(self, m: BagMessage) -> None:
        try:
            st = self.decoder.decode(m.channel, m.data)
            state = next((kv.value for kv in st.values if kv.key == "state"), None)
            if state:
                rec = self.controller.recorded
                rec[state] = rec.get(state, 0) + 1
        except Exception:  # noqa: BLE001 - recorded status is informational only
            pass


def _verdict_entry(entry: dict[str, Any], res: Any) -> dict[str, Any]:
    """The trajectory's entry in the record, completed from its FeasibilityResult."""
    d = res.to_dict()
    entry.update(accepted=True, feasible=bool(res.feasible), error_code=None)
    for k in ("level", "message", "failure_label", "time_scale", "payload_margin_kg", "worst_joint",
              "worst_constraint", "worst_ratio", "first_violation_time_s", "n_points", "duration_s",
              "interpolation", "binding_joint", "binding_constraint", "start_segment", "start_state_age_s"):
        if k in d:
            entry[k] = d[k]
    entry["failure_label"] = entry.get("failure_label") or None  # "" (feasible) → null
    if "violations" in d:
        entry["violations"] = d["violations"][:50] if isinstance(d["violations"], list) else d["violations"]
    if "per_joint" in d:
        entry["per_joint"] = d["per_joint"]
    # curves for the report's plot; only the first trajectories', to keep the record small
    add_per_frame(entry, res, curves=entry["index"] < MAX_CURVE_TRAJECTORIES, result_dict=d)
    if not isinstance(entry.get("level"), str):
        from dyn_node.core.robot.status import LEVEL_NAMES
        entry["level"] = LEVEL_NAMES.get(entry.get("level"), str(entry.get("level")))
    return entry
