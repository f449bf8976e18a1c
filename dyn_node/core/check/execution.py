"""The trajectory as ros2_controllers' joint_trajectory_controller (JTC, Jazzy) executes it.

Every judge of a trajectory (the check behind the topic, the services and dyn-check, the gate,
the audit's replay) takes the motion from here, so the verdict is on what the controller will
command. Rules as read in ros2_controllers, branch ``jazzy`` at ed360c9 (2026-08-16); line
numbers are of that version:

- T = joint_trajectory_controller/src/trajectory.cpp
- C = joint_trajectory_controller/src/joint_trajectory_controller.cpp
- D = joint_trajectory_controller/doc/trajectory.rst

Start time (T ``Trajectory::update`` 101-107, ``sample`` 125-134): the trajectory's time origin
is ``header.stamp``; a zero stamp is replaced by the first update that samples it, i.e. it
starts on receipt. A non-zero stamp in the past therefore starts *inside* the trajectory
(offset = receipt − stamp); one whose end is already past is refused (C
``validate_trajectory_msg`` 1734-1750).

The start (T ``sample`` 143-169, C ``update`` 292-313, D 94-97): the state before the message
is taken at the first update (measured, or the last command with
``interpolate_from_desired_state``); while the first point's time (stamp + time_from_start) is
ahead, the controller interpolates from that state to the first point; once it is reached there
is no such segment and the command *steps* to the trajectory's state: a jump.

Interpolation (T ``interpolate_between_points`` 279-406, D 29-48): per segment from the fields
present at *both* ends: positions only → linear, + velocities → cubic, + accelerations →
quintic; accelerations without velocities match no branch. The state before the message gets
zero velocities/accelerations where the first point has them and it has not (T
``set_point_before_trajectory_msg`` 58-70). After the last point the controller holds it, with
its velocities (zero when not given; T ``sample`` 208-253). A last point with non-zero velocity
is refused unless ``allow_nonzero_velocity_at_trajectory_end`` (C 1716-1732).

Times here are seconds from the execution start (the first update after receipt); arrays in
model joint order. Pure NumPy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import PiecewisePolynomial, Trajectory, _cubic, _quintic

LINEAR, CUBIC, QUINTIC, HOLD = "linear", "cubic", "quintic", "hold"
#: the start-time rules (T sample 128-131): a zero stamp starts at the first update after receipt
START_ON_RECEIPT = "zero stamp: on receipt"
START_AT_STAMP = "at header.stamp"
#: a goal executed as a single held state (one point reached at once) is judged over this long
HOLD_S = 0.1
#: the controller's test of a non-zero velocity (C 1721: |v| > float epsilon)
_FLOAT_EPS = float(np.finfo(np.float32).eps)


@dataclass(frozen=True, kw_only=True)
class ExecutionOptions:
    """``start_tolerance`` (rad or m): a jump at the start within it is reported, not a violation
    (MoveIt's ``allowed_start_tolerance``, 0.01); ``velocity_tolerance`` (rad/s or m/s): a
    velocity step within it is reported, not a violation (at the start it is measured against
    joint_states); ``allow_nonzero_velocity_at_trajectory_end`` mirrors the controller's
    parameter (default false); ``interpolate_from_desired_state``: the state handed in as the
    start is the controller's last command (with its accelerations), as with the controller's
    parameter of that name (C 300-307)."""

    start_tolerance: float = 0.01
    velocity_tolerance: float = 0.01
    allow_nonzero_velocity_at_trajectory_end: bool = False
    interpolate_from_desired_state: bool = False

    def __post_init__(self) -> None:
        for name in ("start_tolerance", "velocity_tolerance"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a finite number ≥ 0, not {v!r}")


@dataclass(frozen=True)
class Timing:
    """When a trajectory reached the controller: its ``header.stamp`` and the receipt time, s on
    the same clock (the node's; zero stamp = start on receipt)."""

    stamp_s: float = 0.0
    receipt_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.stamp_s) and math.isfinite(self.receipt_s)):
            raise ValueError("stamp and receipt times must be finite")


@dataclass(frozen=True)
class Jump:
    """The step of the command at the start when the first point is reached at once: per joint
    commanded − robot, position and velocity; ``joint`` / ``velocity_joint``: where each is
    largest; ``exceeds``: beyond the tolerances (a violation)."""

    position: np.ndarray
    velocity: np.ndarray
    joint: int
    size: float
    velocity_joint: int
    velocity_size: float
    exceeds_position: bool
    exceeds_velocity: bool


@dataclass(frozen=True)
class VelocityStep:
    """A knot where the commanded velocity is discontinuous (a linear segment on either side):
    executed knot index, message point index (-1: the start, before the first point), time,
    per joint right − left velocity, and the joints beyond the tolerance."""

    knot: int
    point: int
    time_s: float
    step: np.ndarray
    joints: tuple[int, ...]


@dataclass(frozen=True)
class Execution:
    """The executed motion: ``knots`` (times from the execution start; positions, velocities,
    accelerations at every knot, velocities/accelerations 0 where not used) joined by segments
    interpolated as ``modes`` say, ``pp`` their polynomials; how it started (``start_rule``,
    ``offset_s`` = receipt − stamp, 0 for a zero stamp), whether a segment from the robot's state
    was prepended (``start_segment``) and from which state, the ``jump`` when there was none,
    the velocity steps, and why the controller would refuse it (``refusals``: code, text).
    ``point_knots[i]``: the knot of message point i (-1: passed before the execution start)."""

    trajectory: Trajectory
    knots: Trajectory
    modes: tuple[str, ...]
    pp: PiecewisePolynomial
    start_rule: str
    offset_s: float
    start_segment: bool
    start: StartState | None
    jump: Jump | None
    velocity_steps: tuple[VelocityStep, ...]
    refusals: tuple[tuple[str, str], ...]
    point_knots: np.ndarray
    options: ExecutionOptions = field(default_factory=ExecutionOptions)

    @property
    def start_age_s(self) -> float:
        return float(self.start.age_s) if self.start is not None else math.nan

    @property
    def fixed_start(self) -> bool:
        """The start segment begins at a moving robot's state, which does not scale with k."""
        if not self.start_segment:
            return False
        return bool(np.any(self.knots.velocities[0] != 0.0) or np.any(self.knots.accelerations[0] != 0.0))

    @property
    def interpolation(self) -> str:
        """One mode when every segment has it ("hold" aside), else "mixed"."""
        moving = {m for m in self.modes if m != HOLD} or {HOLD}
        return moving.pop() if len(moving) == 1 else "mixed"

    def mode_counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for m in self.modes:
            out[m] = out.get(m, 0) + 1
        return out

    @property
    def linear_segments(self) -> tuple[int, ...]:
        return tuple(i for i, m in enumerate(self.modes) if m == LINEAR)

    def violating_steps(self) -> tuple[VelocityStep, ...]:
        return tuple(s for s in self.velocity_steps if s.joints)

    def stretched(self, k: float) -> "Execution":
        """The same execution k times slower (velocities ÷ k, accelerations ÷ k²), except the
        robot's own state at the start of a start segment, which does not scale."""
        kn = self.knots
        v, a = kn.velocities / k, kn.accelerations / (k * k)
        if self.start_segment:
            v[0], a[0] = kn.velocities[0], kn.accelerations[0]
        knots = Trajectory(times=kn.times * k, positions=kn.positions, velocities=v, accelerations=a)
        return replace(self, knots=knots, pp=build_pp(knots, self.modes))

    def first_segment(self, k: float = 1.0) -> "Execution":
        """The start segment alone (the execution stretched by k)."""
        ex = self.stretched(k)
        kn = ex.knots
        knots = Trajectory(times=kn.times[:2], positions=kn.positions[:2],
                           velocities=kn.velocities[:2], accelerations=kn.accelerations[:2])
        pk = np.full(self.trajectory.n_points, -1)
        pk[0] = 1
        # checked as a trajectory of its own: its start does not stretch with the trial's k
        return replace(ex, knots=knots, modes=ex.modes[:1], pp=build_pp(knots, ex.modes[:1]),
                       velocity_steps=(), point_knots=pk, start_segment=False, jump=None)


def segment_mode(v0: bool, a0: bool, v1: bool, a1: bool) -> str | None:
    """The interpolation of a segment from the fields at its ends (T 279-280: a field counts when
    both ends have it; 315, 334, 365: the three branches); None: no branch (accelerations
    without velocities)."""
    has_v, has_a = v0 and v1, a0 and a1
    if not has_v and not has_a:
        return LINEAR
    if has_v and not has_a:
        return CUBIC
    if has_v and has_a:
        return QUINTIC
    return None


def build_pp(knots: Trajectory, modes: tuple[str, ...]) -> PiecewisePolynomial:
    """The polynomials of the segments (T 315-406: the same formulas), padded to one degree."""
    t, p = knots.times, knots.positions
    v, a = knots.velocities, knots.accelerations
    T = np.diff(t)
    deg = max({LINEAR: 1, HOLD: 1, CUBIC: 3, QUINTIC: 5}[m] for m in modes)
    coeffs = np.zeros((len(T), deg + 1, p.shape[1]))
    for mode in set(modes):
        s = np.array([i for i, m in enumerate(modes) if m == mode])
        if mode == QUINTIC:
            c = _quintic(p[s], v[s], a[s], p[s + 1], v[s + 1], a[s + 1], T[s])
        elif mode == CUBIC:
            c = _cubic(p[s], v[s], p[s + 1], v[s + 1], T[s])
        elif mode == LINEAR:
            c = np.stack([p[s], (p[s + 1] - p[s]) / T[s][:, None]], axis=1)
        else:
            c = p[s][:, None, :]
        coeffs[s, :c.shape[1]] = c
    return PiecewisePolynomial(breaks=t.copy(), coeffs=coeffs)


def _end_velocity(pp: PiecewisePolynomial) -> np.ndarray:
    """Each segment's velocity at its end (left of the next knot), segments × nv."""
    T = np.diff(pp.breaks)[:, None]
    c = pp.coeffs
    out = np.zeros((c.shape[0], c.shape[2]))
    for k in range(c.shape[1] - 1, 0, -1):
        out = out * T + k * c[:, k, :]
    return out


def _refusals(traj: Trajectory, timing: Timing | None, options: ExecutionOptions,
              modes_ok: bool) -> list[tuple[str, str]]:
    out = []
    if traj.velocities is not None and not options.allow_nonzero_velocity_at_trajectory_end:
        has_v, _ = traj.point_fields()
        last = traj.velocities[-1]
        if has_v[-1] and np.any(np.abs(last) > _FLOAT_EPS):   # C 1716-1732
            j = int(np.argmax(np.abs(last)))
            out.append(("nonzero_end_velocity", f"the last point's velocity is not zero (joint "
                        f"{j}: {last[j]:.6g}) and allow_nonzero_velocity_at_trajectory_end is false"))
    if timing is not None and timing.stamp_s != 0.0 and timing.stamp_s + traj.duration < timing.receipt_s:
        # C 1734-1750: a stamped trajectory whose end is already past
        out.append(("ends_in_past", f"trajectory with a non-zero start time ends in the past: stamped "
                    f"{timing.receipt_s - timing.stamp_s:.3f} s before receipt, it ended "
                    f"{timing.receipt_s - timing.stamp_s - traj.duration:.3f} s ago"))
    if not modes_ok:
        out.append(("accelerations_without_velocities", "a segment has accelerations but not "
                    "velocities at both ends: no branch of the controller's interpolation takes it"))
    return out


def refusals(traj: Trajectory, timing: Timing | None = None,
             options: ExecutionOptions = ExecutionOptions()) -> list[tuple[str, str]]:
    """What the controller refuses of ``traj`` received at ``timing``: (code, text) each, in the
    order JTC checks them (dyn_sim's action server refuses the goal on the first)."""
    has_v, has_a = traj.point_fields()
    modes_ok = all(segment_mode(has_v[i], has_a[i], has_v[i + 1], has_a[i + 1]) is not None
                   for i in range(traj.n_points - 1))
    return _refusals(traj, timing, options, modes_ok)


def execute(traj: Trajectory, start: StartState | None = None, timing: Timing | None = None,
            options: ExecutionOptions = ExecutionOptions()) -> Execution:
    """``traj`` (validated, model order) as JTC executes it, received at ``timing`` (None: zero
    stamp) by a robot in ``start`` (None: unknown; the first point is then the start, judged
    from there as given). Never raises for what the controller would refuse: the refusals are
    listed, and the motion judged as if stamped zero when the stamped end is past."""
    has_v, has_a = traj.point_fields()
    modes_msg = [segment_mode(has_v[i], has_a[i], has_v[i + 1], has_a[i + 1])
                 for i in range(traj.n_points - 1)]
    refusals = _refusals(traj, timing, options, all(m is not None for m in modes_msg))
    modes_msg = [m or LINEAR for m in modes_msg]      # judged linear (positions are all it has)
    stamped = timing is not None and timing.stamp_s != 0.0
    offset = timing.receipt_s - timing.stamp_s if stamped else 0.0
    if any(c == "ends_in_past" for c, _ in refusals):
        stamped, offset = False, 0.0
    rule = START_AT_STAMP if stamped else START_ON_RECEIPT
    t = traj.times - offset                            # message points in execution time
    nv = traj.positions.shape[1]
    V = traj.velocities if traj.velocities is not None else np.zeros_like(traj.positions)
    A = traj.accelerations if traj.accelerations is not None else np.zeros_like(traj.positions)
    if t[0] > 0 and start is not None:
        # T sample 147-169: from the state before the message (taken at the first update, t = 0)
        # to the first point; the state's missing derivatives are zero (T 58-70)
        a0 = (start.accelerations if options.interpolate_from_desired_state
              and getattr(start, "accelerations", None) is not None else np.zeros(nv))
        mode0 = segment_mode(True, True, has_v[0], has_a[0]) or LINEAR
        knots = _knots(np.concatenate(([0.0], t)), np.vstack([start.positions, traj.positions]),
                       np.vstack([start.velocities, V]), np.vstack([a0, A]))
        return _finish(traj, knots, (mode0, *modes_msg), rule, offset, True, start, None,
                       refusals, np.arange(1, traj.n_points + 1), options, has_v)
    if t[0] > 0 or t[0] == 0.0:
        # no state known (the first point is the start), or the first point is due now
        knots = _knots(t, traj.positions, V, A)
        kn = np.arange(traj.n_points)
        ex_modes: tuple[str, ...] = tuple(modes_msg)
    else:
        knots, ex_modes, kn = _cut(traj, t, V, A, modes_msg)
    if knots.n_points == 1:   # a single point reached at once: held (T sample 208-253)
        knots = _knots(np.array([0.0, HOLD_S]), np.repeat(knots.positions, 2, axis=0),
                       np.zeros((2, nv)), np.zeros((2, nv)))
        ex_modes = (HOLD,)
    pp = build_pp(knots, ex_modes)
    jump = None
    if start is not None and knots.times[0] <= 0.0:
        v_cmd = pp.coeffs[0, 1] if pp.coeffs.shape[1] > 1 else np.zeros(nv)
        jump = _jump(knots.positions[0] - start.positions, v_cmd - start.velocities, options)
    return _finish(traj, knots, ex_modes, rule, offset, False, start, jump, refusals, kn, options,
                   has_v, pp)


def _knots(t, p, v, a) -> Trajectory:
    return Trajectory(times=np.asarray(t, dtype=float), positions=np.asarray(p, dtype=float),
                      velocities=np.asarray(v, dtype=float), accelerations=np.asarray(a, dtype=float))


def _cut(traj: Trajectory, t: np.ndarray, V: np.ndarray, A: np.ndarray, modes: list[str]
         ) -> tuple[Trajectory, tuple[str, ...], np.ndarray]:
    """A past stamp: the execution starts inside the trajectory (T sample 171-206 at the first
    update); its first knot is the trajectory's state there, the rest the points ahead."""
    ahead = np.flatnonzero(t > 0.0)
    kn = np.full(traj.n_points, -1)
    if not len(ahead):                 # exactly at the end: the last point, held
        kn[-1] = 0
        return _knots(t[-1:] * 0.0, traj.positions[-1:], V[-1:], A[-1:]), (), kn
    s = int(ahead[0]) - 1              # the segment the start falls in
    full = _knots(t, traj.positions, V, A)
    seg = build_pp(_knots(t[s:s + 2], traj.positions[s:s + 2], V[s:s + 2], A[s:s + 2]), (modes[s],))
    q, v, a, _ = seg.evaluate(np.array([0.0]))
    if modes[s] == LINEAR:
        v, a = V[s:s + 1], A[s:s + 1]   # not used by a linear segment
    elif modes[s] == CUBIC:
        a = A[s:s + 1]
    kn[s + 1:] = np.arange(1, traj.n_points - s)
    knots = _knots(np.concatenate(([0.0], t[s + 1:])), np.vstack([q, full.positions[s + 1:]]),
                   np.vstack([v, V[s + 1:]]), np.vstack([a, A[s + 1:]]))
    return knots, tuple(modes[s:]), kn


def _jump(dp: np.ndarray, dv: np.ndarray, options: ExecutionOptions) -> Jump:
    j, jv = int(np.argmax(np.abs(dp))), int(np.argmax(np.abs(dv)))
    return Jump(position=dp, velocity=dv, joint=j, size=float(abs(dp[j])), velocity_joint=jv,
                velocity_size=float(abs(dv[jv])),
                exceeds_position=bool(abs(dp[j]) > options.start_tolerance),
                exceeds_velocity=bool(abs(dv[jv]) > options.velocity_tolerance))


def _finish(traj, knots, modes, rule, offset, start_segment, start, jump, refusals, point_knots,
            options, has_v, pp=None) -> Execution:
    pp = pp if pp is not None else build_pp(knots, modes)
    return Execution(trajectory=traj, knots=knots, modes=tuple(modes), pp=pp, start_rule=rule,
                     offset_s=float(offset), start_segment=start_segment, start=start, jump=jump,
                     velocity_steps=_velocity_steps(knots, modes, pp, start_segment, point_knots,
                                                    options, traj, has_v),
                     refusals=tuple(refusals), point_knots=np.asarray(point_knots), options=options)


def _velocity_steps(knots: Trajectory, modes: tuple[str, ...], pp: PiecewisePolynomial,
                    start_segment: bool, point_knots: np.ndarray, options: ExecutionOptions,
                    traj: Trajectory, has_v: np.ndarray) -> tuple[VelocityStep, ...]:
    """Where the commanded velocity steps: at a knot beside a linear segment (left end velocity ≠
    right start velocity), at the start of a linear start segment (the robot's velocity → the
    slope), and at the end (the slope → the held point's velocity, T 240-244)."""
    if modes == (HOLD,):
        return ()
    K = knots.n_points
    lin = np.array([m == LINEAR for m in modes])
    near = np.zeros(K, dtype=bool)
    near[1:] |= lin                 # a linear segment arrives at knot i
    near[:-1] |= lin                # or leaves it
    if not start_segment:
        near[0] = False             # a jump's velocity, or no state: see Jump
    idx = np.flatnonzero(near)
    if not len(idx):
        return ()
    left = _end_velocity(pp)                                   # velocity arriving at knot i+1
    right = pp.coeffs[:, 1, :]                                 # velocity leaving knot i
    held = traj.velocities[-1] if traj.velocities is not None and has_v[-1] else np.zeros(left.shape[1])
    arrive = np.vstack([knots.velocities[:1], left])           # knot 0: the robot's velocity
    leave = np.vstack([right, held[None, :]])                  # the last knot: the hold
    steps = leave[idx] - arrive[idx]
    point_of = {int(k): i for i, k in enumerate(point_knots) if k >= 0}
    out = []
    for n, i in enumerate(idx):
        step = steps[n]
        if not np.any(np.abs(step) > 1e-12):
            continue
        joints = tuple(int(j) for j in np.flatnonzero(np.abs(step) > options.velocity_tolerance))
        out.append(VelocityStep(knot=int(i), point=point_of.get(int(i), -1),
                                time_s=float(knots.times[i]), step=step, joints=joints))
    return tuple(out)
