"""retime(): TOPP-RA for the first- and second-order kinds, then the exact check decides.

Each round: TOPP-RA on the joint rows (limits × ``limit_margin``, below any local caps), the
law smoothed over the window w, a screen of the points' accelerations and efforts (capped
where over, without the exact check), points dense enough that the controller's quintic stays
within ``path_tolerance`` of the path, and the exact check of those points. A violation of a
third-order kind (jerk, effort rate) widens w (its switches then ramp longer); any other (or a
third-order one w did not cure) caps ṡ² around where it happened, by the kind's law in k. The
first trajectory the check passes is the answer; when none does within ``max_rounds``, or the
uniform stretch of the input by the check's time scale is shorter, that stretch (re-sampled
and re-checked likewise) is. Nothing the check has not passed is returned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import (FeasibilityOptions, FeasibilityResult, StartState,
                                             check_trajectory)
from dyn_node.core.check.constraints import Violation
from dyn_node.core.check.kinds import KIND_CLASS
from dyn_node.core.check.trajectory import Trajectory, clamped_spline_velocities, from_current_state
from dyn_node.errors import TrajectoryError
from dyn_node.retime import bound, candidates, knots, timing, topp
from dyn_node.retime.path import (ArcPath, Path, build_path, is_still, is_untimed, pieces, stops,
                                  validate_input)
from dyn_node.retime.result import RetimeResult

#: third-order kinds: their violations widen the smoothing window first
_RAMP_KINDS = ("jerk", "effort_rate")
#: halvings of the output period at most for overshoots between points (:func:`_finer`)
_FINER = 2
#: the least half-width (grid cells) of a local cap
_CAP_CELLS = 8
#: a long cubic path is searched in pieces of this many segments (:func:`_long_cuts`;
#: measured on the 250-waypoint path: 3 → 92.2 s, 5 → 93.5 s, 10 → 106 s, 20 → 161 s, one
#: piece → cut at the stretch's 202 s)
_PIECE_KNOTS = 5
#: rounds checked with the caller's options in full (payload margin too)
_FULL_ROUNDS = 2
#: the first window over the one that spreads every jump of τ (timing.switch_window) for the
#: effort rate: the box filter's rate of τ is not only the jumps' (neighbouring switches and
#: τ's own change along the path add up; a jump of q̈ is the whole of the jerk's, which is
#: why the jerk's window is not widened: one joint's S-curve stays time-optimal), and a wider
#: window costs less (T grows by w) than a round that fails
_RATE_W = 2.5
#: point screens (:func:`_screen`) per search at most
_SCREENS = 4
#: the share of :func:`_lead_room` a moving start's first window may take
_LEAD_SHARE = 0.9
#: how far above :func:`_least_x` a cap at a moving start stays (TOPP-RA's interpolation
#: rows see the next stage too)
_FLOOR_PAD = 1e-3
#: halvings of the output period at most, for violations at a moving start (:func:`_adjust`)
_HALVINGS = 3
#: the share of the limits a moving start that needs all its braking is retried at: the
#: limits themselves, less the rounding of the check's own sums
_FULL = 1 - 1e-9
#: a limit margin this close to 1 is the rows' rounding room (dyn-check's 0.995), not a
#: controller's headroom: a path it leaves no timing is retried at the limits themselves
_ROUNDING = 0.99


@dataclass
class _Search:
    """One retiming's state across rounds."""

    dynamics: Dynamics
    path: Path
    grid: np.ndarray
    options: FeasibilityOptions
    tolerance: float
    period: float
    rows: topp.Rows
    cap: np.ndarray
    w: float
    margin: float
    widened: dict[str, int] = field(default_factory=dict)
    #: a moving start: the robot's ṡ₀ on this path (0: from rest) and its state, the check's
    #: start (:func:`_regrid`)
    sd0: float = 0.0
    start: StartState | None = None
    #: why the search gave up, for the report
    notes: list[str] = field(default_factory=list)
    #: TOPP-RA had no timing from the moving robot's ṡ₀
    refused: bool = False
    #: times the output period was halved for a violation at a moving start, and the caps
    #: before the last :func:`_adjust`
    halved: int = 0
    prev_cap: np.ndarray | None = None
    #: the violations the last round adjusted for, for the report
    last: str = ""
    #: the best candidate's duration so far (the stretch's): a round whose law alone lasts
    #: longer cannot win, and the search stops there
    best: float = math.inf
    #: halvings of the output period for overshoots between points (:func:`_finer`)
    finer: int = 0
    #: the second smoothing window (timing.smoothed): two output periods, kept when only
    #: :func:`_finer` halves the period (a narrower one would steepen the corners it rounds)
    w2: float = 0.0
    #: a cubic path's knots (knots.find), None elsewhere
    knots: knots.Knots | None = None

    def __post_init__(self) -> None:
        self.w2 = self.w2 or 2 * self.period


def retime(dynamics: Dynamics, traj: Trajectory, *, start: StartState | None = None,
           feasibility: FeasibilityOptions = FeasibilityOptions(), path_tolerance: float = 1e-4,
           grid_points: int = 1000, point_period: float = 0.004, max_rounds: int = 30,
           limit_margin: float = 0.995, uniform_fallback: bool = True,
           input_check: FeasibilityResult | None = None, certify: bool = True) -> RetimeResult:
    """The fastest trajectory along ``traj``'s path (model order) that passes
    :func:`~dyn_node.core.check.feasibility.check_trajectory` with ``feasibility``; see the module
    docstring and docs/retime.md. ``start``: the robot's state when the first point lies ahead
    (t0 > 0): the path then starts from it (the executed path, ``from_current_state``), and
    the answer from its q and q̇ when it moves (docs/retime.md, "A moving start"). Raises :class:`TrajectoryError` for input no
    retiming can take (fewer than 2 points, non-finite values, bad times).
    ``uniform_fallback``: also consider the uniform stretch (which keeps the input's own end
    velocities, while the optimal search ends at rest and starts at rest or at the moving
    robot's state) and answer the shorter.
    ``input_check``: the caller's ``check_trajectory(dynamics, traj, feasibility, start=start)``
    when it has it (dyn-check, the gate): used instead of checking the input again.
    ``certify=False`` skips the certified T* (``lower_bound`` NaN; ``grid_optimum`` is kept):
    the gate, which forwards the answer and waits for no bound, saves its ~40 ms."""
    validate_input(traj)
    if not (path_tolerance > 0 and grid_points >= 10 and point_period > 0 and max_rounds >= 1
            and 0 < limit_margin <= 1):
        raise TrajectoryError("retime options out of range", code="bad_options")
    duration_in = 0.0 if is_untimed(traj) else traj.duration
    if is_still(traj):
        return _still(dynamics, traj, feasibility, start, duration_in)
    given = traj
    moving_start = start is not None and traj.times[0] > 0 and bool(np.any(start.velocities))
    if start is not None and traj.times[0] > 0 and not moving_start:
        traj = from_current_state(traj, start.positions, start.velocities)
    path = build_path(traj)
    nominal = path.nominal
    checked = _input_check(dynamics, nominal, feasibility, start,
                           input_check if nominal is given else None)
    # the velocity steps of linearly interpolated positions block every slowdown of the input
    # as sent, not of the retimer's smooth path through its points: that path's time scale
    first = _path_check(dynamics, nominal, feasibility, start, checked)
    k = first.time_scale
    uniform_T = nominal.duration * k if 0 < k < math.inf else math.nan
    base = dict(duration_in=duration_in, duration_uniform=uniform_T, input_check=checked,
                source=None if path.untimed else nominal)
    # a moving start: the optimal search may brake where the stretch cannot (the robot's q̇0
    # does not scale), so only its failure makes the check's "no slowdown helps" final
    if not math.isfinite(k) and not moving_start:
        return _none(first, base)
    # from a moving state the search runs on the executed path (docs/retime.md, "A moving
    # start"): the controller's segment from that state, then the input's
    v0 = start.velocities if moving_start else None
    search = (build_path(from_current_state(traj, start.positions, v0)) if moving_start
              else path)
    parts = _search_paths(dynamics, search, grid_points)
    # T* certified against its grid (bound.py); TOPP-RA's optimum on the grid alongside
    base["grid_optimum"] = _bound(dynamics, search, parts, grid_points, v0)
    lower, base["bound_steps"] = (bound.for_retime(dynamics, search, parts, grid_points,
                                                   lambda p: _start_speed(p, v0))
                                  if certify else (math.nan, 0))
    notes: list[str] = []
    # the stretch lasts k·T_in × (1.001 … 1.005) (candidates.STRETCH_PADS): the search is cut
    # as soon as it cannot beat that, and the stretch is built only when the search lost to it
    # or failed (bounded wall time)
    best = uniform_T * candidates.STRETCH_PADS[-1] if uniform_fallback else math.inf
    found = _by_pieces(dynamics, parts, feasibility, path_tolerance, point_period,
                       limit_margin, max_rounds, start=start if moving_start else None,
                       notes=notes, best=best if math.isfinite(best) else math.inf)
    uniform = None
    beaten = found is not None and (found["trajectory"].duration
                                    <= uniform_T * candidates.STRETCH_PADS[0])
    if math.isfinite(k) and (found is None or (uniform_fallback and not beaten)):
        uniform = candidates.stretch(dynamics, path, traj, k, feasibility, start, point_period,
                                     moving_start,
                                     lambda *a: _dense(*a[:4], path_tolerance),
                                     path_tolerance, margin=limit_margin)
    pick = min((c for c in (found, uniform) if c is not None),
               key=lambda c: c["trajectory"].duration, default=None)
    why = f" (optimal search: {'; '.join(notes)})" if notes and found is None else ""
    if pick is None and not math.isfinite(k):
        return _none(first, base, lower, why)
    if pick is None:
        return RetimeResult(False, None, duration_out=math.nan, lower_bound=lower,
                            message="no retiming passed the exact check (optimal search and "
                                    f"uniform stretch both failed){why}", **base)
    return _retimed(pick, found, uniform, base, lower, why, moving_start)


def _retimed(pick: dict, found: dict | None, uniform: dict | None, base: dict, lower: float,
             why: str, moving_start: bool) -> RetimeResult:
    """The answer ``pick`` (the faster candidate) with its message."""
    out, uniform_T = pick["trajectory"], base["duration_uniform"]
    frm = " from the moving start state" if moving_start else ""
    msg = (f"retimed ({pick['method']}{frm}): {base['duration_in']:.4g} s → {out.duration:.4g} s, "
           f"uniform {uniform_T:.4g} s, {_tstar(lower, base)}; "
           f"{_won(found, uniform, uniform_T)}{why}; "
           f"re-check: {pick['check'].message}")
    return RetimeResult(True, out, duration_out=out.duration, lower_bound=lower, message=msg,
                        check=pick["check"], method=pick["method"],
                        rounds=pick.get("rounds", 0), smoothing_s=pick.get("w", 0.0),
                        path_deviation=pick["deviation"], **base)


def _won(found: dict | None, uniform: dict | None, uniform_T: float) -> str:
    """Which candidate won and by how much (the note of docs/retime.md)."""
    if found is not None and uniform is None and math.isfinite(uniform_T):
        a = found["trajectory"].duration
        return (f"optimal search {100 * (1 - a / uniform_T):.1f} % shorter than the stretch "
                "(not built: it lasts at least the uniform time)")
    if found is None or uniform is None:
        return f"only the {'optimal search' if uniform is None else 'stretch'} passed"
    a, b = found["trajectory"].duration, uniform["trajectory"].duration
    if a <= b:
        return f"optimal search {100 * (1 - a / b):.1f} % shorter than the stretch"
    return f"the stretch {100 * (1 - b / a):.1f} % shorter than the optimal search"


def _path_check(dynamics: Dynamics, nominal: Trajectory, options: FeasibilityOptions,
                start: StartState | None, first: FeasibilityResult) -> FeasibilityResult:
    """``first`` (the input as the controller executes it), or, when only the velocity steps of
    positions-only points block it, the check of the path the retimer follows (the C² spline
    through them: :func:`~dyn_node.core.check.trajectory.clamped_spline_velocities`)."""
    ex = first.execution
    jump = ex is not None and ex.jump is not None and (ex.jump.exceeds_position or ex.jump.exceeds_velocity)
    if (ex is None or jump or not ex.violating_steps() or nominal.velocities is not None
            or nominal.n_points < 2):
        return first
    smooth = Trajectory(times=nominal.times, positions=nominal.positions,
                        velocities=clamped_spline_velocities(nominal.times, nominal.positions))
    res = check_trajectory(dynamics, smooth, replace(options, compute_payload_margin=False), start=start)
    return replace(res, payload_margin_kg=math.nan)


def _none(first: FeasibilityResult, base: dict, lower: float = math.nan,
          why: str = "") -> RetimeResult:
    """No slowdown helps (the input check's time scale is infinite): nothing returned, the
    check's reason in ``blocked``."""
    return RetimeResult(False, None, duration_out=math.nan, lower_bound=lower,
                        message=f"no retiming: {first.message}{why}", blocked=_blocked(first),
                        **base)


def _tstar(lower: float, base: dict) -> str:
    if math.isfinite(lower):
        return f"T* {lower:.4g} s (certified, {base['bound_steps']} steps)"
    return f"T* not certified (grid optimum {base['grid_optimum']:.4g} s)"


def _bound(dynamics: Dynamics, path: Path, parts: list[tuple], grid_points: int,
           v0: np.ndarray | None) -> float:
    """T* (module docstring of topp; from the robot's ṡ₀ when ``v0`` is given)."""
    x_lb = None
    if len(parts) == 1:
        # one piece: T* on the search's own path, grid and torque coefficients (computed once)
        p, grid, terms = parts[0]
        x_lb = topp.solve(p, grid, topp.joint_rows(dynamics, p, grid, lower_bound=True,
                                                   terms=terms), free_ends=True,
                          sd_start=_start_speed(p, v0))
    if x_lb is None:
        x_lb, grid = _lower_bound(dynamics, path, grid_points, _start_speed(path, v0))
    return topp.duration(grid, x_lb) if x_lb is not None else math.nan


def _start_speed(path: Path, v0: np.ndarray | None) -> float:
    """ṡ₀ on ``path`` for the robot's q̇0 (0 without one): the executed path starts with q' ∥
    q̇0 (exactly q̇0 by time, its unit direction by arc length)."""
    if v0 is None:
        return 0.0
    d1 = path.derivatives(np.array([path.pp.breaks[0]]))[1][0]
    return max(0.0, float(d1 @ v0 / (d1 @ d1)))


def _input_check(dynamics: Dynamics, nominal: Trajectory, options: FeasibilityOptions,
                 start: StartState | None, given: FeasibilityResult | None) -> FeasibilityResult:
    """The exact check of the input (its time scale for the uniform stretch, its blocked
    reason): ``given`` (the caller's, of this very trajectory), else checked here without the
    payload margin, which nothing of the retiming needs (NaN in the result: not computed)."""
    if given is not None:
        if given.n_points != nominal.n_points or given.duration_s != nominal.duration:
            raise TrajectoryError("input_check is not a check of this trajectory",
                                  code="bad_options")
        return given
    res = check_trajectory(dynamics, nominal, replace(options, compute_payload_margin=False),
                           start=start)
    return replace(res, payload_margin_kg=math.nan)


def _optimal(sr: _Search, max_rounds: int) -> dict | None:
    """The check-driven rounds (module docstring); None when none passes."""
    memo: dict = {"reach": topp.Reach(sr.path, sr.grid, sr.rows), "key": None}
    x0 = _solved(sr, memo)
    if x0 is None:
        return None
    jerk_w, rate_w = timing.switch_window(sr.dynamics, sr.path, sr.grid, x0)
    sr.w = max(sr.w, jerk_w / sr.margin, _RATE_W * rate_w / sr.margin)
    if sr.sd0 > 0:
        # the window's lead runs at ṡ₀: no wider than where ṡ₀ is still controllable
        sr.w = min(sr.w, _LEAD_SHARE * _lead_room(sr, memo["reach"]))
    # a cubic path's knots: ṡ² capped in closed form where their ramps would stray from the
    # path, before the first round rather than after one fails (knots.py)
    sr.knots = knots.find(sr.dynamics, sr.path, sr.sd0 > 0)
    if sr.knots is not None:
        knots.precap(sr.knots, sr.grid, x0, sr.cap, sr.tolerance, sr.period, sr.w, sr.w2)
    # later rounds skip the payload margin (it does not decide feasibility); the answer gets
    # the full check with the caller's options
    plain = replace(sr.options, compute_payload_margin=False)
    screens = 0
    for rnd in range(1, max_rounds + 1):
        while True:
            x = _solved(sr, memo)
            if x is None and _denser(sr):
                continue
            if x is None:
                return None
            lw = timing.law(sr.grid, x, sr.sd0)
            if lw.duration + sr.w + sr.w2 > sr.best:
                sr.notes.append(f"cut after {rnd} round(s): {lw.duration + sr.w:.4g} s cannot "
                                f"beat {sr.best:.4g} s")
                return None
            pts = timing.points(sr.path, lw, sr.w, sr.period, sr.w2)
            # halfway between the rows' share and the limit: over the share by rounding is
            # no reason to slow down, and near the limit the quintic between points may cross
            share = (1.0 + sr.margin) / 2
            hits = _screen(sr.dynamics, pts, share) if screens < _SCREENS else []
            if not hits:
                break
            # caps from the points' accelerations and efforts: cheaper than an exact check
            # that fails
            screens += 1
            if not _adjust(sr, hits, lw, x):
                return None
        out, dev = _dense(sr.path, lw, sr.w, sr.period, sr.tolerance, sr.w2, pts)
        if out is None:
            return None
        if sr.knots is not None:
            out, dev = knots.averaged(sr.dynamics, sr.knots, sr.grid, x, sr.cap, lw, sr.w,
                                      sr.w2, out, dev, sr.period, sr.tolerance)
            if out is None:    # ṡ² capped at the knots: the next round solves again
                continue
        # the first rounds, which usually pass, check in full at once (a second check of the
        # answer costs more than the payload margin of a round that fails)
        opts = sr.options if rnd <= _FULL_ROUNDS else plain
        try:
            res, over = candidates.judge(sr.dynamics, out, opts, sr.start)
        except TrajectoryError as err:   # slowed beyond what the check takes: give up
            sr.notes.append(str(err))
            return None
        if res.feasible:
            full = res if opts == sr.options else check_trajectory(sr.dynamics, out, sr.options,
                                                                   start=sr.start)
            return dict(trajectory=out, check=full, method="optimal", rounds=rnd,
                        w=sr.w + sr.w2, deviation=dev)
        if candidates.between(sr.dynamics, out, over) and _finer(sr, over):
            continue
        if not _adjust(sr, over, lw, x):
            return None
    return None


def _finer(sr: _Search, over: Sequence[Violation]) -> bool:
    """Points twice as dense (at most :data:`_FINER` times) when all the check found is a little
    over between points (:func:`candidates.between`: the quintic between points rounds the
    law's corners; its error shrinks with the period, a cap would cost time)."""
    worst = max(abs(v.peak_value) / v.limit for v in over)
    if worst > 1.05 or sr.finer >= _FINER:
        return False
    sr.finer, sr.period = sr.finer + 1, sr.period / 2
    return True


def _solved(sr: _Search, memo: dict) -> np.ndarray | None:
    """TOPP-RA's ṡ² under the search's caps from its ṡ₀, solved again only when a cap changed
    (a wider window smooths the same law) or, from a moving start, the grid moved with the
    window (:func:`_regrid`)."""
    if sr.sd0 > 0 and sr.grid[0] != _lead_start(sr):
        if not _regrid(sr):
            return None
        memo["reach"], memo["key"] = topp.Reach(sr.path, sr.grid, sr.rows), None
    key = (float(sr.grid[0]), sr.cap.tobytes())
    if memo["key"] != key:
        memo["key"] = key
        x = memo["reach"].solve(cap=sr.cap, sd_start=sr.sd0)
        # TOPP-RA's forward pass backs a start it cannot hold off (its tolerance): the
        # robot's ṡ₀ is not the law's to change
        memo["x"] = x if x is None or x[0] >= sr.sd0**2 * (1 - 1e-12) else None
        if memo["x"] is None and not np.isfinite(sr.cap).any():
            _refuse(sr)
    return memo["x"]


def _refuse(sr: _Search) -> None:
    """TOPP-RA has no timing from the moving robot's ṡ₀ (or from rest) under the rows alone."""
    if not sr.refused and sr.sd0 == 0:
        sr.refused = True
        sr.notes.append(f"the limits × {sr.margin:.9g} leave no timing (a static load takes "
                        "more than their share somewhere on the path)")
    elif not sr.refused:
        sr.refused = True
        sr.notes.append(f"the robot's ṡ0 = {sr.sd0:.6g} (its velocity along the path) is "
                        "outside TOPP-RA's controllable set at the start: no braking within "
                        f"the limits × {sr.margin:.9g} reaches the end")


def _denser(sr: _Search, *, undo: bool = True) -> bool:
    """The output period halved (at most :data:`_HALVINGS` times) where a cap would leave a
    moving robot's ṡ₀ no timing (``undo``: the last caps undone): near such a start what
    breaks a limit is the controller's quintic between points across the window's quick
    turn, not the law."""
    if not (sr.sd0 > 0 and sr.halved < _HALVINGS):
        return False
    if undo:
        if sr.prev_cap is None or np.array_equal(sr.prev_cap, sr.cap):
            return False
        sr.cap = sr.prev_cap
    sr.halved, sr.period = sr.halved + 1, sr.period / 2
    sr.w2 = 2 * sr.period
    return True


def _lead_room(sr: _Search, reach: topp.Reach) -> float:
    """The widest window w whose lead at ṡ₀ (:func:`_lead_start`) ends where ṡ₀ is still in
    TOPP-RA's controllable set (on the current grid): a wider one leaves no timing."""
    K = reach.controllable(0.0)
    bad = np.flatnonzero(~(K[:, 1] >= sr.sd0**2))
    s_max = sr.grid[max(bad[0] - 1, 0)] if bad.size else float(sr.path.pp.breaks[-1])
    return max(0.0, 2 * (s_max - float(sr.path.pp.breaks[0])) / sr.sd0 - sr.w2)


def _lead_start(sr: _Search) -> float:
    """Where TOPP-RA starts from a moving state: ṡ₀ × half the two windows ahead of the
    path's start. The law runs at ṡ₀ before it (timing.Law.lead), so the windows' average
    is at the path's start at t = 0 with exactly ṡ₀ and s̈ = 0: the robot's state."""
    return float(sr.path.pp.breaks[0] + sr.sd0 * (sr.w + sr.w2) / 2)


def _regrid(sr: _Search) -> bool:
    """The search's grid (same size) from :func:`_lead_start` to the path's end, its rows,
    and its caps carried over by s; False when that start lies past the end."""
    s_c, end = _lead_start(sr), float(sr.path.pp.breaks[-1])
    if not s_c < end:
        sr.notes.append("the smoothing window from the moving start is longer than the path")
        return False
    old = sr.grid
    sr.grid = np.linspace(s_c, end, len(old))
    sr.cap = sr.cap[np.clip(np.searchsorted(old, sr.grid), 0, len(old) - 1)]
    sr.rows = topp.joint_rows(sr.dynamics, sr.path, sr.grid, scale=sr.margin)
    return True


def _screen(dynamics: Dynamics, pts: Trajectory, share: float) -> list[Violation]:
    """The joint accelerations and efforts (RNEA with friction; the check adds a task
    wrench's torque) at the output points above ``share`` of their limits, one entry per
    joint and run of points over: the smoothing window makes them (q̈ = q'·s̈ + q''·ṡ² of an
    averaged law is not the average of TOPP-RA's), and the controller's quintic passes through
    each point's state, so the exact check would find most of them, at several times the
    cost. (TOPP-RA's rows interpolated between grid points instead of RNEA: false alarms where
    they change fast, next to a stop.)"""
    lim = dynamics.model.limits
    hits = _runs("acceleration", np.abs(pts.accelerations), share, lim.acceleration, pts.times,
                 lim.names)
    if np.any(np.isfinite(lim.effort)):
        tau = dynamics.rnea_batch(pts.positions, pts.velocities, pts.accelerations)
        hits += _runs("effort", np.abs(tau), share, lim.effort, pts.times, lim.names)
    return hits


def _runs(kind: str, value: np.ndarray, share: float, limit: np.ndarray, t: np.ndarray,
          names: Sequence[str]) -> list[Violation]:
    """One :class:`Violation` per joint and run of samples with |value| over ``share`` of a
    positive finite limit (a zero one is the exact check's to report)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = value / limit
    over = (ratio > share) & (limit > 0) & np.isfinite(limit)
    out = []
    for j in np.flatnonzero(over.any(axis=0)):
        idx = np.flatnonzero(over[:, j])
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            pk = int(run[np.argmax(ratio[run, j])])
            out.append(Violation(joint=names[j], kind=kind, first_time_s=float(t[run[0]]),
                                 peak_time_s=float(t[pk]),
                                 peak_value=float(ratio[pk, j] * limit[j] / share),
                                 limit=float(limit[j]),
                                 duration_s=float(t[run[-1]] - t[run[0]]), unit=""))
    return out


def _search_paths(dynamics: Dynamics, path: Path, grid_points: int) -> list[tuple]:
    """The pieces between the path's stops (:func:`pieces`; the whole path when it has none),
    each by arc length when it starts or ends at rest (q' = 0: singular in s), with its grid
    and its :func:`topp.joint_terms` there."""
    cut = _long_cuts(path)
    parts = pieces(path, cut) if stops(path).size or cut.size else [path]
    out = []
    for part in parts:
        p = ArcPath(part) if _singular_end(part) else part
        n = max(100, int(round(grid_points * part.length / path.length)))
        grid = np.linspace(p.pp.breaks[0], p.pp.breaks[-1], n + 1)
        out.append((p, grid, topp.joint_terms(dynamics, p, grid)))
    return out


def _long_cuts(path: Path) -> np.ndarray:
    """Knots where a long cubic path is cut, the search stopping there: every
    :data:`_PIECE_KNOTS`-th inner knot when it has more than that. Its joint-space average
    (knots.py) has one window for the whole output, the widest any knot needs, and the law's
    smoothing one for its largest switch; on 250 waypoints the knots' caps under them slowed
    the whole law past the stretch (202 s against T* 70 s). A piece keeps its own (93.5 s)."""
    n = len(path.pp.breaks) - 2
    if path.untimed or path.nominal.natural_interpolation != "cubic" or n <= 2 * _PIECE_KNOTS:
        return np.zeros(0, dtype=int)
    return np.arange(_PIECE_KNOTS, n + 1 - _PIECE_KNOTS // 2, _PIECE_KNOTS)


def _lower_bound(dynamics: Dynamics, path: Path, grid_points: int, sd0: float = 0.0
                 ) -> tuple[np.ndarray | None, np.ndarray]:
    """T*'s ṡ² on the whole path by s (the path may pass its stops moving) and its grid;
    ``sd0``: ṡ at the start (a moving robot's)."""
    for n in (grid_points, grid_points + 1):
        # a grid point exactly where the path stops inside (q' = q'' = 0 at a waypoint) leaves
        # TOPP-RA's controllable set undefined there: the next grid steps over it
        grid = np.linspace(path.pp.breaks[0], path.pp.breaks[-1], n + 1)
        x_lb = topp.solve(path, grid, topp.joint_rows(dynamics, path, grid, lower_bound=True),
                          free_ends=True, sd_start=sd0)
        if x_lb is not None:
            break
    return x_lb, grid


def _by_pieces(dynamics: Dynamics, parts: list[tuple], options: FeasibilityOptions,
               tolerance: float, period: float, margin: float, max_rounds: int, *,
               start: StartState | None = None, notes: list[str] | None = None,
               best: float = math.inf) -> dict | None:
    """The optimal search on each of :func:`_search_paths`' pieces, the pieces joined at rest
    and the whole checked again; ``start``: a moving robot's state, where the first piece
    starts (its velocity along it: ṡ₀)."""
    found, notes = [], [] if notes is None else notes
    for i, (p, grid, terms) in enumerate(parts):
        first = start if i == 0 else None
        sd0 = _start_speed(p, None if first is None else first.velocities)
        # a robot that needs every bit of its braking, or a path where a static load takes
        # more than the rows' rounding share (dyn-check's 0.995; a controller's margin is
        # kept): the limits themselves (the exact check still decides) when their share
        # leaves no timing
        retry = margin < _FULL and (sd0 > 0 or margin >= _ROUNDING)
        for share in (margin, _FULL) if retry else (margin,):
            rows = topp.joint_rows(dynamics, p, grid, scale=share, terms=terms)
            spent = sum(f["trajectory"].duration for f in found)
            sr = _Search(dynamics, p, grid, options, tolerance, period, rows,
                         np.full(len(grid), np.inf), 0.0, share, sd0=sd0, start=first,
                         notes=notes, best=best - spent)
            one = _optimal(sr, max_rounds)
            if one is not None or not sr.refused:
                break
            if share != _FULL:
                notes.append(f"retried at the limits × {_FULL:.9f}")
        if one is None:
            if not notes:
                notes.append("no timing the exact check passes" +
                             (f" (last: {sr.last})" if sr.last else ""))
            return None
        found.append(one)
    if len(found) == 1:
        return found[0]
    out = _join([f["trajectory"] for f in found])
    res, _ = candidates.judge(dynamics, out, options, start)
    if not res.feasible:
        notes.append("the pieces joined fail: " + res.message)
        return None
    return dict(trajectory=out, check=res, method="optimal",
                rounds=sum(f["rounds"] for f in found), w=max(f["w"] for f in found),
                deviation=max(f["deviation"] for f in found))


def _singular_end(path: Path) -> bool:
    """The path stops at an end (q' = 0 there: every positions-only path, every stop piece;
    to rounding of the largest |q'| at its knots: a segment from a moving state, solved for
    its coefficients, ends at 1e-17, not 0)."""
    d1 = np.abs(path.derivatives(path.pp.breaks)[1])
    return bool(np.any(np.all(d1[[0, -1]] <= 1e-12 * np.max(d1), axis=1)))


def _join(parts: list[Trajectory]) -> Trajectory:
    """Trajectories from rest to rest, one after the other (each junction point once)."""
    times, cols = [parts[0].times], [[parts[0].positions], [parts[0].velocities],
                                     [parts[0].accelerations]]
    for tr in parts[1:]:
        times.append(tr.times[1:] + times[-1][-1])
        for c, x in zip(cols, (tr.positions, tr.velocities, tr.accelerations)):
            c.append(x[1:])
    return Trajectory(times=np.concatenate(times), positions=np.vstack(cols[0]),
                      velocities=np.vstack(cols[1]), accelerations=np.vstack(cols[2]))


def _adjust(sr: _Search, violations: Sequence[Violation], lw: timing.Law,
            x: np.ndarray) -> bool:
    """Widen the window or cap ṡ² where ``violations`` are; False when nothing can be
    changed."""
    widen, halved = 1.0, False
    sr.prev_cap = sr.cap.copy()
    sr.last = ", ".join(sorted({f"{v.joint} {v.kind}" for v in violations}))
    for v in violations:
        if v.kind == "position" or v.limit <= 0:
            return False
        ratio = abs(v.peak_value) / v.limit
        if (sr.sd0 > 0 and v.first_time_s <= 0.0
                and (v.kind not in _RAMP_KINDS or sr.widened.get(v.kind, 0) >= 1)):
            # at the robot's own state (a wider window did not cure it): the executed start
            # segment's own third derivative at ṡ₀, or the robot's q̇: no later timing helps
            sr.notes.append(f"{v.joint} {v.kind} {ratio:.3g}× its limit at the robot's state "
                            "(t = 0), which no timing from it changes")
            return False
        if v.kind in _RAMP_KINDS and sr.widened.get(v.kind, 0) < 3:
            widen = max(widen, ratio * 1.02)
            continue
        order = max(1, KIND_CLASS[v.kind].order if v.kind in KIND_CLASS else 2)
        factor = min(0.98, ratio ** (-2.0 / order) * 0.98)
        t0 = v.first_time_s - sr.w
        t1 = max(v.peak_time_s, v.first_time_s + v.duration_s) + sr.w
        s0, s1 = (float(timing.smoothed(lw, sr.w, np.array([tt]))[0][0]) for tt in (t0, t1))
        # at least ±_CAP_CELLS grid cells: TOPP-RA only sees its grid points, and near a stop
        # (q' → 0) the motion between them is what breaks the limit
        lo = max(0, int(np.searchsorted(lw.s, s0)) - _CAP_CELLS)
        hi = min(len(x), int(np.searchsorted(lw.s, s1)) + _CAP_CELLS + 1)
        new = x[lo:hi] * factor
        if sr.sd0 > 0:
            # from a moving start a cap below what braking reaches leaves no timing at all;
            # where it would, the output's points get denser instead (:func:`_denser`)
            floor = _least_x(sr, hi - 1)[lo:hi] * (1 + _FLOOR_PAD)
            if np.any(floor > new) and not halved and _denser(sr, undo=False):
                halved = True
            new = np.maximum(new, floor)
        sr.cap[lo:hi] = np.minimum(sr.cap[lo:hi], new)
    if widen > 1.0:
        for kind in _RAMP_KINDS:
            if any(v.kind == kind for v in violations):
                sr.widened[kind] = sr.widened.get(kind, 0) + 1
        sr.w = max(sr.w * widen, 2 * sr.period)
    return True


def _least_x(sr: _Search, upto: int) -> np.ndarray:
    """The least ṡ² the rows allow at grid points 0 … ``upto`` from the robot's ṡ₀, braking
    as hard as they allow at each step (the largest lower bound they put on s̈): a cap below
    it leaves the moving start no timing."""
    r, d = sr.rows, np.diff(sr.grid)
    x = np.empty(upto + 1)
    x[0] = sr.sd0**2
    for i in range(upto):
        neg = r.a[i] < 0
        room = (r.g - r.c[i] - r.b[i] * x[i])[neg]
        u = float(np.max(room / r.a[i][neg])) if neg.any() else -math.inf
        x[i + 1] = max(0.0, x[i] + 2 * d[i] * u)
    return x


def _dense(path: Path, lw: timing.Law, w: float, period: float, tolerance: float,
           w2: float = 0.0, first: Trajectory | None = None) -> tuple[Trajectory | None, float]:
    """Points at ``period``, halved until the quintic between them stays within ``tolerance``
    of the path (None when even 1/64 of it does not); windows w, w2 (:func:`timing.smoothed`);
    ``first``: the points at ``period``, when already made."""
    for _ in range(7):
        out = first if first is not None else timing.points(path, lw, w, period, w2)
        first = None
        dev = timing.deviation(path, lw, w, out, w2)
        if dev <= tolerance:
            return out, dev
        period /= 2
    return None, math.nan


def _still(dynamics: Dynamics, traj: Trajectory, options: FeasibilityOptions,
           start: StartState | None, duration_in: float) -> RetimeResult:
    """All points equal: nothing to move; returned unchanged when holding there passes."""
    hold = traj if not is_untimed(traj) else Trajectory(times=np.array([0.0, 1.0]),
                                                        positions=traj.positions[:2])
    res = check_trajectory(dynamics, hold, options, start=start)
    ok = res.feasible
    return RetimeResult(ok, traj if ok else None, duration_in=duration_in,
                        duration_out=duration_in if ok else math.nan, duration_uniform=duration_in,
                        lower_bound=0.0, message="all points equal: nothing to move, returned "
                        f"unchanged ({res.message})" if ok else f"all points equal; {res.message}",
                        blocked="" if ok else _blocked(res), check=res, input_check=res,
                        method="unchanged")


def _blocked(res: FeasibilityResult) -> str:
    """The check's reason when no slowdown helps (its message after the first "; ")."""
    if math.isfinite(res.time_scale):
        return ""
    head, _, tail = res.message.partition("; ")
    return tail or head
