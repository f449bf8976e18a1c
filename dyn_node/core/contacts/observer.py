"""External joint torque from joint states: the generalized-momentum observer, and the contact
wrench at a frame that best explains it.

r follows the external torque through a first-order lag (ṙ = K(τ_ext − r)) without
differentiating velocities; the update is the exact solution over each step, so it is stable for
any dt. Bad or missing input gives no estimate and the next valid sample restarts the observer.
The method (discretisation, ``effort_timing``, resets, the damped least-squares wrench):
docs/OBSERVER.md. No rclpy: the live node and the offline audit run the same objects.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from dyn_node.core.compiled import observer_kernels as ok
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.frames import joint_tables
from dyn_node.errors import InputError
from dyn_node.core.robot.model import RobotModel

#: restart codes (:attr:`ObserverReset.code`)
RESET_START = "start"
RESET_REQUESTED = "requested"
RESET_GAP = "gap"
#: a step between header stamps longer than ``max_gap_s`` (RESET_GAP: the monitor's receipt-time gap)
RESET_STAMP_GAP = "stamp_gap"
RESET_BACKWARDS = "backwards"
RESET_INVALID = "after_invalid_input"
#: how the measured effort is integrated over a step (:class:`ObserverOptions`)
EFFORT_TIMINGS = ("held", "sampled")
#: the no-estimate code of a joint state without effort
EFFORT_MISSING = "effort_missing"


def per_joint(values: float | Sequence[float], nv: int, what: str, *,
              positive: bool = True) -> np.ndarray:
    """One value per joint from one value (applies to every joint) or nv values; finite, and
    > 0 when ``positive``. Raises ValueError naming ``what``."""
    a = np.atleast_1d(np.asarray(values, dtype=float)).reshape(-1)
    if a.size == 1:
        a = np.full(nv, float(a[0]))
    if a.shape != (nv,):
        raise ValueError(f"{what} needs 1 or {nv} values, got {a.size}")
    if not np.all(np.isfinite(a)) or (positive and np.any(a <= 0)):
        raise ValueError(f"{what} must be finite{' and > 0' if positive else ''}, got {a.tolist()}")
    return a


@dataclass(frozen=True, kw_only=True)
class ObserverOptions:
    """``gain`` K (1/s), one value for every joint or one per joint (model order);
    ``max_gap_s``: a step longer than this restarts the observer (the node passes its
    ``stale_timeout``); ``settle_time_constants``: ``settled`` once this many 1/K_min have
    passed since the restart (3: 95 % of a step); ``effort_timing``: ``held`` or ``sampled``
    (see the module docstring)."""

    gain: float | Sequence[float] = 50.0
    max_gap_s: float = 0.5
    settle_time_constants: float = 3.0
    effort_timing: str = "held"


@dataclass(frozen=True)
class ObserverReset:
    """Why the observer restarted: ``code`` (``RESET_*``) and a sentence for people."""

    code: str
    detail: str


@dataclass(frozen=True)
class ObserverEstimate:
    """One sample's answer.

    ``tau_ext`` (nv, N·m|N, model order): the external torque the environment exerts on the
    robot, or None when this sample gives no estimate (``unavailable`` says why). ``reset`` is
    set on the sample at which the observer restarted. ``since_reset_s``: time since the
    restart (0 on it; NaN with no estimate); ``settled``: at least ``settle_time_constants``/K
    since the restart."""

    t: float
    tau_ext: np.ndarray | None
    unavailable: str | None = None
    reset: ObserverReset | None = None
    since_reset_s: float = math.nan
    settled: bool = False
    #: the reason's code when there is no estimate (``effort_missing``, ``non_finite_effort``…)
    code: str | None = None


def _bad_joints(names: Sequence[str], x: np.ndarray) -> str:
    return ", ".join(names[i] for i in np.flatnonzero(~np.isfinite(x)))


@dataclass(frozen=True)
class ObserverRows:
    """:meth:`MomentumObserver.update_rows`' answer for N rows: ``tau_ext`` (N×nv, NaN rows
    without estimate), ``wrench`` (N×6 at the contact frame, its axes), ``info`` and ``code``
    (columns and codes of :mod:`dyn_node.core.compiled.observer_kernels`), the restarts by row and the
    rows without estimate (row → (code, reason))."""

    tau_ext: np.ndarray
    wrench: np.ndarray
    info: np.ndarray
    code: np.ndarray
    resets: dict[int, ObserverReset]
    unavailable: dict[int, tuple[str, str]]


class MomentumObserver:
    """The generalized-momentum observer on a :class:`Dynamics` (its friction switch and
    armature included), with the contact wrench at ``frame`` (default the last link) and the
    contact-level test (``contact_at``: the detector's contact torque per joint; None: never
    over) computed in the same compiled pass
    (:func:`dyn_node.core.compiled.observer_kernels.observer_rows`); ``power``: the power balance's state
    array it updates (None: its own). One row or N rows per call, the same arithmetic. Not
    thread-safe."""

    def __init__(self, dynamics: Dynamics, *, options: ObserverOptions = ObserverOptions(),
                 frame: str | None = None, wrench: "WrenchOptions | None" = None,
                 contact_at: np.ndarray | None = None, power: np.ndarray | None = None):
        nv = dynamics.nv
        self.dynamics = dynamics
        self.options = options
        self.gain = per_joint(options.gain, nv, "observer gain (1/s)")
        self.gain.setflags(write=False)
        if not (options.max_gap_s > 0 and math.isfinite(options.max_gap_s)):
            raise ValueError(f"max_gap_s must be a positive number of seconds, got {options.max_gap_s}")
        if not (options.settle_time_constants >= 0 and math.isfinite(options.settle_time_constants)):
            raise ValueError("settle_time_constants must be finite and ≥ 0")
        if options.effort_timing not in EFFORT_TIMINGS:
            raise ValueError(f"effort_timing must be one of {', '.join(EFFORT_TIMINGS)}, got {options.effort_timing!r}")
        wo = wrench if wrench is not None else WrenchOptions()
        _check_wrench_options(wo)
        self.wrench_options = wo
        model = dynamics.model
        pm = dynamics.pin_model
        self.frame = frame or model.last_link
        if not pm.existFrame(self.frame):
            raise InputError(f"contact frame '{self.frame}' is not a frame of the model", code="unknown_frame")
        f = pm.frames[pm.getFrameId(self.frame)]
        t = joint_tables(pm, pm.frames[0].name)
        damping, coulomb = dynamics.friction_coefficients
        lv = np.full(nv, np.inf) if contact_at is None else np.array(contact_at, dtype=float)
        if lv.shape != (nv,):
            raise ValueError(f"contact_at needs {nv} values")
        self._model_args = (t.parent, t.revolute, t.index, t.placement, t.axis, t.inertia,
                            t.armature, t.gravity, damping, coulomb, int(f.parentJoint),
                            np.concatenate([np.asarray(f.placement.rotation).reshape(9),
                                            np.asarray(f.placement.translation)]),
                            np.ascontiguousarray(self.gain), float(options.max_gap_s),
                            options.effort_timing == "held",
                            np.array([wo.singular_value, wo.damping_band, wo.max_damping]), lv)
        self._kernel = ok.observer_rows
        self.settle_s = options.settle_time_constants / float(self.gain.min())
        self._names = model.joint_names
        self._nv = nv
        #: restarts and samples without an estimate, by code
        self.counts: dict[str, int] = {}
        self._pending: ObserverReset | None = ObserverReset(RESET_START, "first sample")
        self._invalid_why = ""
        self.state = np.zeros((ok.STATE_ROWS, nv))
        self.clock = np.zeros(4)
        self.power = power if power is not None else np.zeros(9)
        # one row's buffers (the live path): no allocation per sample
        self._q1, self._v1, self._e1 = np.zeros((1, nv)), np.zeros((1, nv)), np.zeros((1, nv))
        self._t1 = np.zeros(1)
        self._valid1, self._reset1 = np.ones(1, dtype=bool), np.zeros(1, dtype=bool)
        self._tau1, self._w1 = np.zeros((1, nv)), np.zeros((1, 6))
        self._info1, self._code1 = np.zeros((1, ok.INFO_COLUMNS)), np.zeros(1, dtype=np.int64)
        #: the last row's wrench (6) and ``info`` columns (σ_min, λ, misfit, …; zeros before
        #: any row); after :meth:`update` views the next sample overwrites
        self.last_wrench = np.full(6, np.nan)
        self.last_info = self._info1[0]
        # what the pass answers for a row without estimate, from the pass itself (on scratch state)
        self._no_wrench, self._no_info = np.zeros((1, 6)), np.zeros((1, ok.INFO_COLUMNS))
        self._kernel(self._q1, self._v1, self._e1, self._t1, np.zeros(1, dtype=bool), self._reset1,
                     *self._model_args, np.zeros_like(self.state), np.zeros(4), np.zeros(9),
                     np.zeros((1, nv)), self._no_wrench, self._no_info, np.zeros(1, dtype=np.int64))
        self._no_wrench, self._no_info = self._no_wrench[0], self._no_info[0]
        for x in (self._no_wrench, self._no_info):
            x.setflags(write=False)

    @property
    def time_constant_s(self) -> np.ndarray:
        """1/K per joint (s)."""
        return 1.0 / self.gain

    def reset(self, reason: str = "reset requested", *, code: str = RESET_REQUESTED) -> ObserverReset:
        """Forget the history; the next valid sample restarts the observer and reports this
        reason and ``code`` (also returned)."""
        self._pending = ObserverReset(code, reason)
        self._reset1[0] = True
        return self._pending

    def _count(self, code: str) -> None:
        self.counts[code] = self.counts.get(code, 0) + 1

    def _check(self, t: float, q, v, effort) -> tuple[tuple[str, str] | None, tuple]:
        if v is None:
            return ("velocity_missing", "velocity not measured"), ()
        if effort is None:
            return (EFFORT_MISSING, "effort not measured"), ()
        arrays = [np.asarray(x, dtype=float) for x in (q, v, effort)]
        for label, a in zip(("position", "velocity", "effort"), arrays):
            if a.shape != (self._nv,):
                raise ValueError(f"{label} needs {self._nv} values in model order, got shape {a.shape}")
        if not math.isfinite(t):
            return ("bad_stamp", f"stamp is not finite ({t})"), ()
        # a sum is NaN or ±inf iff an element is (or it overflows: then the per-element check decides)
        if not math.isfinite(float(arrays[0].sum() + arrays[1].sum() + arrays[2].sum())):
            for label, a in zip(("position", "velocity", "effort"), arrays):
                if not np.all(np.isfinite(a)):
                    return (f"non_finite_{label}",
                            f"{label} not finite for {_bad_joints(self._names, a)}"), ()
        return None, tuple(arrays)

    def _reset_of(self, code: int, dt: float) -> ObserverReset | None:
        """The restart a row's kernel code stands for (None: not a restart)."""
        if code == ok.RESTART:
            r, self._pending = self._pending or ObserverReset(RESET_START, "first sample"), None
        elif code == ok.RESTART_AFTER_INVALID:
            r = ObserverReset(RESET_INVALID, f"restarted after a sample without an estimate ({self._invalid_why})")
        elif code == ok.BACKWARDS:
            r = ObserverReset(RESET_BACKWARDS, f"stamp went back {-dt:.9g} s")
        elif code == ok.STAMP_GAP:
            r = ObserverReset(RESET_STAMP_GAP, f"stamp gap of {dt:.9g} s > {self.options.max_gap_s:g} s")
        else:
            return None
        self._count(r.code)
        return r

    def update(self, t: float, q: Sequence[float], v: Sequence[float] | None,
               effort: Sequence[float] | None) -> ObserverEstimate:
        """One joint state at time ``t`` (s), arrays in model order: position (rad|m), velocity
        (rad/s|m/s; None: not measured) and measured effort (N·m|N; None: not measured).
        Raises ValueError only for arrays of the wrong length (a caller bug)."""
        bad, arrays = self._check(t, q, v, effort)
        if (bad is not None and not self._reset1[0] and self.clock[ok.C_HAS] == 0.0
                and self.power[ok.P_N] == 0.0):
            # nothing for the pass to drop (no history, no open power period): a robot that
            # never reports effort costs no call per message
            self._count(bad[0])
            self.last_wrench, self.last_info = self._no_wrench, self._no_info
            return ObserverEstimate(t=t, tau_ext=None, unavailable=bad[1], code=bad[0])
        self._t1[0] = t
        if bad is None:
            self._q1[0], self._v1[0], self._e1[0] = arrays
        self._valid1[0] = bad is None
        self._kernel(self._q1, self._v1, self._e1, self._t1, self._valid1, self._reset1,
                     *self._model_args, self.state, self.clock, self.power,
                     self._tau1, self._w1, self._info1, self._code1)
        self._reset1[0] = False
        self.last_wrench, self.last_info = self._w1[0], self._info1[0]
        if bad is not None:
            self._count(bad[0])
            if self._info1[0, ok.I_DROPPED]:
                self._invalid_why = bad[1]
            return ObserverEstimate(t=t, tau_ext=None, unavailable=bad[1], code=bad[0])
        info = self._info1[0]
        restart = self._reset_of(int(self._code1[0]), float(info[ok.I_DT]))
        since = float(info[ok.I_SINCE])
        return ObserverEstimate(t=t, tau_ext=self._tau1[0].copy(), reset=restart,
                                since_reset_s=since, settled=since >= self.settle_s)

    def update_rows(self, T: np.ndarray, Q: np.ndarray, V: np.ndarray | None,
                    E: np.ndarray | None, *, reset: np.ndarray | None = None,
                    reasons: dict[int, ObserverReset] | None = None,
                    measured: np.ndarray | None = None) -> ObserverRows:
        """N joint states at once (T stamps in s, N×nv arrays in model order; V, E None: not
        measured; ``measured[k]`` False: row k has no effort). ``reset[k]`` with
        ``reasons[k]``: :meth:`reset` just before row k. Gives the same numbers, restarts and
        counts as :meth:`update` row by row."""
        N = len(T)
        T = np.ascontiguousarray(T, dtype=float)
        Q = np.ascontiguousarray(Q, dtype=float)
        Vk = np.zeros_like(Q) if V is None else np.ascontiguousarray(V, dtype=float)
        Ek = np.zeros_like(Q) if E is None else np.ascontiguousarray(E, dtype=float)
        has_e = np.ones(N, dtype=bool) if measured is None else np.asarray(measured, dtype=bool)
        finite = (np.isfinite(T) & np.isfinite(Q).all(axis=1) & np.isfinite(Vk).all(axis=1)
                  & np.isfinite(Ek).all(axis=1))
        valid = finite & has_e & (V is not None) & (E is not None)
        for label, a in (("position", Q), ("velocity", Vk), ("effort", Ek)):
            if a.shape != (N, self._nv):
                raise ValueError(f"{label} needs {N}×{self._nv} values in model order, got shape {a.shape}")
        rs = np.zeros(N, dtype=bool) if reset is None else np.array(reset, dtype=bool)
        if rs.shape != (N,) or has_e.shape != (N,):
            raise ValueError(f"reset and measured need {N} values")
        if N:  # a pending reset() applies to the first row (an empty batch keeps it pending)
            rs[0] |= self._reset1[0]
            self._reset1[0] = False
        TAU, W = np.empty((N, self._nv)), np.empty((N, 6))
        info, code = np.empty((N, ok.INFO_COLUMNS)), np.empty(N, dtype=np.int64)
        self._kernel(Q, Vk, Ek, T, valid, rs, *self._model_args, self.state, self.clock,
                     self.power, TAU, W, info, code)
        resets: dict[int, ObserverReset] = {}
        unavailable: dict[int, tuple[str, str]] = {}
        reasons = reasons or {}
        for k in np.flatnonzero(rs | (code != ok.ESTIMATE)).tolist():
            if rs[k] and k in reasons:
                self._pending = reasons[k]
            c = int(code[k])
            if c == ok.NO_ESTIMATE:
                bad, _ = self._check(float(T[k]), Q[k], None if V is None else V[k],
                                     Ek[k] if E is not None and has_e[k] else None)
                bad = bad or ("no_estimate", "no estimate")
                self._count(bad[0])
                if info[k, ok.I_DROPPED]:
                    self._invalid_why = bad[1]
                unavailable[k] = bad
                continue
            r = self._reset_of(c, float(info[k, ok.I_DT]))
            if r is not None:
                resets[k] = r
        if N:
            self.last_wrench = W[-1].copy()
            self.last_info = info[-1].copy()
        return ObserverRows(TAU, W, info, code, resets, unavailable)


def _check_wrench_options(o: "WrenchOptions") -> None:
    if not all(x > 0 and math.isfinite(x) for x in (o.singular_value, o.damping_band, o.max_damping)):
        raise ValueError("singular_value, damping_band and max_damping must be finite and > 0")
    if o.damping_band <= o.singular_value:
        raise ValueError("damping_band must exceed singular_value: damping starts before refusal")


# --------------------------------------------------------------------------------------------
# The contact wrench at a frame
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class WrenchOptions:
    """Damping of the least-squares wrench (docs/OBSERVER.md): below ``damping_band`` β the
    solution is damped, λ² = (1 − (σ_min/β)²)·λ_max², reaching ``max_damping`` λ_max at
    σ_min = 0; below ``singular_value`` ε (< β) the frame is singular and its wrench refused.
    So between ε and β an estimate is published, damped. All in the units of J's singular
    values (m/rad along the linear rows, which dominate at a flange)."""

    singular_value: float = 0.02
    damping_band: float = 0.06
    max_damping: float = 0.02


@dataclass(frozen=True)
class WrenchEstimate:
    """The wrench the environment exerts on the robot at ``frame``'s origin, in its axes:
    ``wrench`` = [fx, fy, fz (N), mx, my, mz (N·m)]. ``sigma_min``: J's smallest singular
    value; ``damping`` λ used (0 for σ_min ≥ β); ``singular``: σ_min < ε (the direction J
    barely sees is not trusted: the monitor publishes no wrench); ``misfit`` ‖JᵀF̂ − τ̂_ext‖ (N·m):
    the part of τ̂_ext no wrench at this frame explains (a contact elsewhere, or noise);
    ``determined``: nv ≥ 6, else the minimum-norm solution."""

    frame: str
    wrench: np.ndarray
    sigma_min: float
    damping: float
    singular: bool
    misfit: float
    determined: bool

    @property
    def force(self) -> np.ndarray:
        return self.wrench[:3]

    @property
    def moment(self) -> np.ndarray:
        return self.wrench[3:]

    @property
    def force_n(self) -> float:
        # summed in index order as the compiled pass's I_FORCE, which the batched replay reads:
        # a BLAS norm's order depends on the CPU, and a live peak must equal the replayed one
        f0, f1, f2 = self.wrench[:3].tolist()
        return math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)

    @classmethod
    def from_row(cls, frame: str, wrench: np.ndarray, info: np.ndarray, options: WrenchOptions,
                 nv: int) -> "WrenchEstimate":
        """One row of the observer's compiled pass (wrench and ``info`` columns)."""
        sigma = float(info[ok.I_SIGMA])
        return cls(frame=frame, wrench=wrench, sigma_min=sigma, damping=float(info[ok.I_DAMPING]),
                   singular=sigma < options.singular_value, misfit=float(info[ok.I_MISFIT]),
                   determined=nv >= 6)


def damped_wrench(J: np.ndarray, tau: np.ndarray, *, options: WrenchOptions = WrenchOptions()
                  ) -> tuple[np.ndarray, float, float]:
    """(F̂, σ_min, λ) for a 6×nv Jacobian J and torque τ: the compiled solve the observer's
    pass uses (:func:`dyn_node.core.compiled.observer_kernels.damped_solve`)."""
    J = np.ascontiguousarray(J, dtype=float)
    k = min(6, J.shape[1])
    F = np.zeros(6)
    sigma, lam, _ = ok.damped_solve(J, np.ascontiguousarray(tau, dtype=float), options.singular_value,
                                 options.damping_band, options.max_damping, np.zeros((k, k)),
                                 np.zeros((k, k)), np.zeros(k), np.zeros(k), F)
    return F, sigma, lam


class WrenchEstimator:
    """F̂ at one frame of ``model`` (a URDF link or any Pinocchio frame) from τ̂_ext."""

    def __init__(self, model: RobotModel, frame: str, *, options: WrenchOptions = WrenchOptions()):
        _check_wrench_options(options)
        pm = model.pin_model
        if not pm.existFrame(frame):
            raise InputError(f"contact frame '{frame}' is not a frame of the model", code="unknown_frame")
        self.frame = frame
        self.options = options
        self._pm = pm
        self._data = pm.createData()
        self._fid = pm.getFrameId(frame)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The frame's 6×nv Jacobian in its own axes (linear rows first)."""
        return pin.computeFrameJacobian(self._pm, self._data, np.asarray(q, dtype=float), self._fid,
                                        pin.ReferenceFrame.LOCAL)

    def estimate(self, q: np.ndarray, tau_ext: np.ndarray) -> WrenchEstimate:
        J = self.jacobian(q)
        tau = np.asarray(tau_ext, dtype=float)
        F, sigma_min, lam = damped_wrench(J, tau, options=self.options)
        return WrenchEstimate(frame=self.frame, wrench=F, sigma_min=sigma_min, damping=lam,
                              singular=sigma_min < self.options.singular_value,
                              misfit=_norm(J.T @ F - tau), determined=J.shape[1] >= 6)


def _norm(x: np.ndarray) -> float:
    """‖x‖ as np.linalg.norm computes a real vector's (√(x·x)), without its call overhead."""
    return math.sqrt(float(x @ x))
