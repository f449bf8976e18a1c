"""The frame and robot kinds of the feasibility check: frame speed, angular speed and
acceleration, transferred energy (per ``frame_limits`` entry) and the robot's kinetic energy.

Each reads :attr:`Motion.task <dyn_node.core.check.constraints.Motion.task>` and applies its
per-sample law from :mod:`dyn_node.core.check.force_laws`; ``where`` holds the place (a frame name,
or "robot_limits"). Under time scaling by k speeds go as 1/k, accelerations and energies as
s = 1/k² (u and m_u do not change with k), so no kind here is ever blocked (k = v/v_max
finite).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np

from dyn_node.core.check import force_laws
from dyn_node.core.check.constraints import (Band, Blocked, LimitedConstraint, Motion, PayloadTerms,
                                             ScanRequest, Scanned, _affine_band, merge)
from dyn_node.core.compiled import law_kernels, scan_kernels as sk
from dyn_node.core.check.force_laws import LawResult
from dyn_node.core.robot.task_limits import FrameLimits
from dyn_node.core.check.task_motion import FRAME_ROLE

if TYPE_CHECKING:
    from dyn_node.core.robot.model import RobotModel

ROBOT_PLACE = "robot_limits"


class TaskConstraint(LimitedConstraint):
    """A kind over places of the task limits, one :class:`LawResult` per place: the values at
    k = 1 against the limit, and the per-sample time scale (the largest over the rows the laws
    cover is the place's factor; a NaN sample, e.g. a singular M(q), counts as no slowdown
    helping)."""

    scope = "task"
    unit: ClassVar[str] = ""
    #: why no slowdown helps at a place where a sample's factor is inf
    blocked_reason: ClassVar[str] = ""

    def _laws(self, motion: Motion) -> list[tuple[str, LawResult]]:
        raise NotImplementedError

    def __init__(self, motion: Motion):
        laws = self._laws(motion)
        self.warnings: list[str] = []
        self.where = tuple(w for w, _ in laws)
        self.units = [self.unit] * len(laws)
        self.laws = [law for _, law in laws]
        self._motion = motion
        self.limit = np.broadcast_to(np.array([law.limit for law in self.laws]),
                                     (len(motion.smp.t), len(laws)))

    @property
    def value(self) -> np.ndarray:
        """The places' values side by side (M × places; formed when asked for)."""
        return np.column_stack([law.value for law in self.laws]) if self.laws else \
            np.empty((len(self._motion.smp.t), 0))

    def scan_requests(self) -> list[ScanRequest]:
        # per place its value against its limit
        return [ScanRequest(sk.ABS, (law.value[:, None],), np.array([law.limit]))
                for law in self.laws]

    def _peak_answer(self, motion: Motion) -> Scanned:
        return merge(self.scanned(motion)[:len(self.laws)])

    def _block_text(self, motion: Motion, c: int, n: int) -> str:
        law = self.laws[c]
        if not np.isfinite(law.value[n]):
            return (f"{self.label or self.kind} at {self.where[c]} is undefined at t = "
                    f"{motion.smp.t[n]:.2f} s; no slowdown helps")
        return (f"{self.blocked_reason or self.label or self.kind} at {self.where[c]}: "
                f"{law.static_value[n]:.3g} {self.unit} of {law.limit:.3g} at t = "
                f"{motion.smp.t[n]:.2f} s; no slowdown helps")

    def _ks(self) -> np.ndarray:
        """Per place the largest per-sample k over the rows (a NaN sample: inf; NaN wins
        numpy.max)."""
        rows = self._motion.rows
        ks = [float(np.max(k)) if (k := law.time_scale[rows]).size else 0.0 for law in self.laws]
        return np.array([math.inf if math.isnan(k) else k for k in ks])

    def time_scale(self) -> np.ndarray:
        return self._ks()

    def blocked(self) -> Blocked | None:
        motion = self._motion
        for c in np.flatnonzero(~(self._ks() < np.inf)):
            k = self.laws[c].time_scale[motion.rows]
            n = motion.r0 + int(np.argmax(~(k < np.inf)))
            return Blocked(self.where[c], self._block_text(motion, int(c), n))
        return None


class FrameConstraint(TaskConstraint):
    """A kind with one limit per ``frame_limits`` entry (``limit_key``), on its point."""

    limit_key: ClassVar[str]

    @classmethod
    def _entries(cls, model: "RobotModel") -> list[FrameLimits]:
        return [f for f in model.task_limits.frame_limits
                if math.isfinite(getattr(f, cls.limit_key))]

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return bool(cls._entries(model))

    def _law(self, terms: Any, limit: float) -> LawResult:
        raise NotImplementedError

    def _laws(self, motion: Motion) -> list[tuple[str, LawResult]]:
        task = motion.task
        return [(f.frame, self._law(task.frame(FRAME_ROLE + f.frame), getattr(f, self.limit_key)))
                for f in self._entries(motion.dynamics.model)]


def _norm(X: np.ndarray) -> np.ndarray:
    # compiled: ~5× NumPy's einsum on 10k rows, the same sums
    return law_kernels.row_squares(X, True)


class FrameSpeed(FrameConstraint):
    """|J_v·q̇| at the point (m/s); k = v/v_max."""

    kind, label, unit, limit_key, order = ("frame_speed", "speed", "m/s", "max_linear_speed", 1)

    def _law(self, terms: Any, limit: float) -> LawResult:
        return force_laws.speed_law(_norm(terms.linear_velocity), limit)


class FrameAngularSpeed(FrameConstraint):
    """|ω| of the frame (rad/s); k = ω/ω_max."""

    kind, label, unit, limit_key, order = ("frame_angular_speed", "angular speed", "rad/s",
                                           "max_angular_speed", 1)

    def _law(self, terms: Any, limit: float) -> LawResult:
        return force_laws.speed_law(_norm(terms.angular_velocity), limit)


class FrameAcceleration(FrameConstraint):
    """|J_v·q̈ + J̇_v·q̇| at the point (m/s², classical, gravity excluded); scales as s."""

    kind, label, unit, limit_key = ("frame_acceleration", "linear acceleration", "m/s²",
                                    "max_linear_acceleration")

    def _law(self, terms: Any, limit: float) -> LawResult:
        return force_laws.acceleration_law(_norm(terms.linear_acceleration), limit)


class TransferredEnergy(FrameConstraint):
    """½·m_u·v² at the point (J, advisory: an upper bound of ISO/TS 15066's transferred energy,
    which uses the reduced mass of robot and body region; not a certification); scales as s.
    Its payload interval is exact: m_u rises monotonically with the payload mass (M grows by
    Δm·J_cᵀJ_c, J_c the payload point's linear Jacobian), given per sample in closed form by
    Woodbury's identity from the kernel's J_c·M⁻¹ products; the largest extra mass with every
    sample within the limit is found by bisection (relative 1e-9)."""

    kind, label, unit, limit_key = ("transferred_energy", "transferred energy (advisory)", "J",
                                    "max_transferred_energy")
    payload_dependent = True

    def _law(self, terms: Any, limit: float) -> LawResult:
        return force_laws.acceleration_law(terms.transferred_energy, limit)

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        task = motion.task
        lam = task.batch.inertia.couple_inertia
        places = []
        for f in self._entries(motion.dynamics.model):
            terms = task.frame(FRAME_ROLE + f.frame)
            moving = terms.effective_mass > 0       # a still point has no energy at any mass
            v = terms.linear_velocity[moving]
            places.append((_woodbury(lam[moving], terms.coupling[moving],
                                     1.0 / terms.effective_mass[moving]),
                           0.5 * np.einsum("ij,ij->i", v, v) / f.max_transferred_energy))

        def worst(extra: float) -> float:
            """½·m_u·v² / L with ``extra`` kg more, the largest over samples and places."""
            return max((float(np.max(e * _inverse_mass(w, extra))) for w, e in places
                        if len(e)), default=0.0)

        return (-math.inf, _monotone_root(worst, -float(motion.dynamics.model.payload.mass)))


def _woodbury(lam: np.ndarray, c: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per sample (rows), the coefficients of 1/m_u(x) = a − x·(n0 + n1·x + n2·x²) /
    (1 + d1·x + d2·x² + d3·x³): Woodbury's cᵀ(I + x·Λ)⁻¹c with adj(I + xΛ) = I + x(tr Λ·I − Λ)
    + x²·adj Λ and det(I + xΛ) expanded (Λ 3×3 symmetric, c 3), entry by entry (no batched
    linear algebra: N is the sample count)."""
    xx, xy, xz, yy, yz, zz = (lam[:, i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2),
                                                         (2, 2)))
    c0, c1, c2 = c[:, 0], c[:, 1], c[:, 2]
    l0, l1, l2 = xx * c0 + xy * c1 + xz * c2, xy * c0 + yy * c1 + yz * c2, \
        xz * c0 + yz * c1 + zz * c2
    cc, cLc, LcLc = c0 * c0 + c1 * c1 + c2 * c2, c0 * l0 + c1 * l1 + c2 * l2, \
        l0 * l0 + l1 * l1 + l2 * l2
    d1 = xx + yy + zz
    d2 = xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz
    d3 = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
    # cᵀ·adj(Λ)·c = |Λc|² − tr Λ·cᵀΛc + σ2·|c|² (Cayley–Hamilton)
    return np.stack([a, cc, d1 * cc - cLc, LcLc - d1 * cLc + d2 * cc, d1, d2, d3])


def _inverse_mass(w: np.ndarray, x: float) -> np.ndarray:
    """m_u (kg) with x kg more payload, from :func:`_woodbury`'s rows."""
    a, n0, n1, n2, d1, d2, d3 = w
    return 1.0 / (a - x * (n0 + x * (n1 + x * n2)) / (1.0 + x * (d1 + x * (d2 + x * d3))))


def _monotone_root(f: Callable[[float], float], lo: float, rtol: float = 1e-9) -> float:
    """The largest x ≥ lo with f(x) ≤ 1 for a nondecreasing f (−inf when f(lo) > 1, inf when
    it stays ≤ 1 up to 1e6 kg more), to ``rtol`` (the feasible end): regula falsi on
    f − 1 with the Illinois halving, which keeps a bracket (a few evaluations, not ~40)."""
    flo = f(lo) - 1.0
    if not flo <= 0.0:
        return -math.inf
    hi = max(1.0, 2 * abs(lo))
    while (fhi := f(hi) - 1.0) <= 0.0:
        lo, flo, hi = hi, fhi, 4 * hi
        if hi > 1e6:
            return math.inf
    side = 0
    for _ in range(200):
        if hi - lo <= rtol * max(1.0, abs(lo)):
            break
        x = hi - fhi * (hi - lo) / (fhi - flo) if fhi > flo else 0.5 * (lo + hi)
        # a step at a bracket end (rounding) bisects instead
        x = x if lo < x < hi else 0.5 * (lo + hi)
        fx = f(x) - 1.0
        if fx <= 0.0:
            lo, flo = x, fx
            fhi = 0.5 * fhi if side == -1 else fhi
            side = -1
        else:
            hi, fhi = x, fx
            flo = 0.5 * flo if side == 1 else flo
            side = 1
    return lo


class KineticEnergy(TaskConstraint):
    """½·q̇ᵀM(q)q̇ of the robot (J, armature included as in M); scales as s. Affine in the
    payload mass: +½|v_c|² per kg at the payload point (exact)."""

    kind, label, unit = "kinetic_energy", "kinetic energy", "J"
    payload_dependent = True

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        r = model.task_limits.robot_limits
        return r is not None and math.isfinite(r.max_kinetic_energy)

    def _laws(self, motion: Motion) -> list[tuple[str, LawResult]]:
        L = motion.dynamics.model.task_limits.robot_limits.max_kinetic_energy
        return [(ROBOT_PLACE, force_laws.acceleration_law(
            motion.task.batch.inertia.kinetic_energy, L))]

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        per_kg = 0.5 * _norm(motion.task.frame("payload").linear_velocity) ** 2
        band = _affine_band(self.value, per_kg[:, None], self.limit)
        # the energy is ≥ 0: its |·| gives no lower end
        return None if band is None else (-math.inf if band[0] <= band[1] else band[0], band[1])


#: The kinds of this module, in the order the time scale breaks ties.
TASK_KINDS = (FrameSpeed, FrameAngularSpeed, FrameAcceleration, TransferredEnergy, KineticEnergy)
