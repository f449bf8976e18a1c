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

from dyn_node.core.dynamics import Dynamics
from dyn_node.errors import InputError
from dyn_node.core.model import RobotModel

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


class MomentumObserver:
    """The generalized-momentum observer on a :class:`Dynamics` (its friction switch and
    armature included). Not thread-safe (it shares the Dynamics' Pinocchio buffers)."""

    def __init__(self, dynamics: Dynamics, *, options: ObserverOptions = ObserverOptions()):
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
        self._held = options.effort_timing == "held"
        self.settle_s = options.settle_time_constants / float(self.gain.min())
        self._names = dynamics.model.joint_names
        self._nv = nv
        #: restarts and samples without an estimate, by code
        self.counts: dict[str, int] = {}
        self._pending: ObserverReset | None = ObserverReset(RESET_START, "first sample")
        self._t: float = math.nan
        self._t0: float = math.nan
        self._p: np.ndarray | None = None
        self._s: np.ndarray | None = None
        self._e: np.ndarray | None = None
        self._r = np.zeros(nv)

    @property
    def time_constant_s(self) -> np.ndarray:
        """1/K per joint (s)."""
        return 1.0 / self.gain

    def reset(self, reason: str = "reset requested", *, code: str = RESET_REQUESTED) -> ObserverReset:
        """Forget the history; the next valid sample restarts the observer and reports this
        reason and ``code`` (also returned)."""
        self._pending = ObserverReset(code, reason)
        self._p = None
        return self._pending

    def _count(self, code: str) -> None:
        self.counts[code] = self.counts.get(code, 0) + 1

    def _no_estimate(self, t: float, code: str, why: str) -> ObserverEstimate:
        self._count(code)
        if self._p is not None:
            self._pending = ObserverReset(RESET_INVALID, f"restarted after a sample without an estimate ({why})")
            self._p = None
        return ObserverEstimate(t=t, tau_ext=None, unavailable=why, code=code)

    def _check(self, t: float, q, v, effort) -> tuple[tuple[str, str] | None, tuple]:
        if effort is None:
            return (EFFORT_MISSING, "effort not measured"), ()
        arrays = [np.array(x, dtype=float) for x in (q, v, effort)]  # copies: the previous sample is kept
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

    def update(self, t: float, q: Sequence[float], v: Sequence[float] | None,
               effort: Sequence[float] | None, *, gravity: np.ndarray | None = None) -> ObserverEstimate:
        """One joint state at time ``t`` (s), arrays in model order: position (rad|m), velocity
        (rad/s|m/s; None: not measured) and measured effort (N·m|N; None: not measured);
        ``gravity``: g(q) already computed by this Dynamics at this q (the Monitor's), else
        computed here. Raises ValueError only for arrays of the wrong length (a caller bug)."""
        if v is None:
            return self._no_estimate(t, "velocity_missing", "velocity not measured")
        bad, arrays = self._check(t, q, v, effort)
        if bad is not None:
            return self._no_estimate(t, *bad)
        q, v, e = arrays
        d = self.dynamics
        p, ctv, g = d.momentum_terms(q, v, gravity=gravity)
        s = ctv - g - d.friction(v)
        restart = self._pending
        if restart is None:
            dt = t - self._t
            if dt < 0:
                restart = ObserverReset(RESET_BACKWARDS, f"stamp went back {-dt:.9g} s")
            elif dt > self.options.max_gap_s:
                restart = ObserverReset(RESET_STAMP_GAP, f"stamp gap of {dt:.9g} s > {self.options.max_gap_s:g} s")
            elif dt == 0.0:  # the same instant again: nothing to integrate
                return self._estimate(t, None)
        if restart is not None:
            self._count(restart.code)
            self._pending = None
            self._r = np.zeros(self._nv)
            self._t0 = t
        else:
            effort_int = dt * e if self._held else 0.5 * dt * (self._e + e)
            mean_ext = (p - self._p - 0.5 * dt * (self._s + s) - effort_int) / dt
            a = np.exp(-self.gain * dt)
            self._r = a * self._r + (1.0 - a) * mean_ext
        self._t, self._p, self._s, self._e = t, p, s, e
        return self._estimate(t, restart)

    def _estimate(self, t: float, restart: ObserverReset | None) -> ObserverEstimate:
        since = t - self._t0
        return ObserverEstimate(t=t, tau_ext=self._r.copy(), reset=restart, since_reset_s=since,
                                settled=since >= self.settle_s)


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
        return float(np.linalg.norm(self.wrench[:3]))


def damped_wrench(J: np.ndarray, tau: np.ndarray, *, options: WrenchOptions = WrenchOptions()
                  ) -> tuple[np.ndarray, float, float]:
    """(F̂, σ_min, λ) for a 6×nv Jacobian J and torque τ (see the module docstring)."""
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    sigma_min = float(s.min()) if s.size else 0.0
    band = options.damping_band
    lam2 = 0.0 if sigma_min >= band else (1.0 - (sigma_min / band) ** 2) * options.max_damping ** 2
    # no zero denominator: λ² = 0 only while every s ≥ σ_min ≥ β > 0, and λ² > 0 otherwise
    gain = s / (s * s + lam2)
    return U @ (gain * (Vt @ tau)), sigma_min, math.sqrt(lam2)


class WrenchEstimator:
    """F̂ at one frame of ``model`` (a URDF link or any Pinocchio frame) from τ̂_ext."""

    def __init__(self, model: RobotModel, frame: str, *, options: WrenchOptions = WrenchOptions()):
        o = options
        if not all(x > 0 and math.isfinite(x) for x in (o.singular_value, o.damping_band, o.max_damping)):
            raise ValueError("singular_value, damping_band and max_damping must be finite and > 0")
        if o.damping_band <= o.singular_value:
            raise ValueError("damping_band must exceed singular_value: damping starts before refusal")
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
