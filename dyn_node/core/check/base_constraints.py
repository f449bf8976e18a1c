"""The base and grasp kinds of the feasibility check: ``base_force``, ``base_moment``,
``tipping`` (place ``base_limits``) and ``grasp_slip`` (place ``grasp``).

Each reads the sampled task terms (``Motion.task``, a TaskMotion: the mounting's wrench as
static + s·dynamic, s = 1/k², with the task wrench's reaction in the static part; the grasp and
payload frame points) and hands them to its law in :mod:`dyn_node.core.check.force_laws`, which gives
the value and the exact time scale per sample. The payload interval is exact for all four: the
grasp force is linear in the payload mass, the base force and moment affine (|a + m·b| ≤ L, a
quadratic in m per sample) and each tipping edge, like the normal force, linear in m.
"""
from __future__ import annotations

import dataclasses
import math
from abc import abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from dyn_node.core.check import force_laws as laws
from dyn_node.core.compiled import kernels, law_kernels
from dyn_node.core.check.constraints import (Band, Blocked, LimitedConstraint, Motion, PayloadTerms,
                                             Peak, ScanRequest, Violation, _fmt)
from dyn_node.core.compiled import scan_kernels as sk
from dyn_node.core.check.frames import BaseWrench, FrameTerms

if TYPE_CHECKING:
    from dyn_node.core.robot.model import RobotModel
    from dyn_node.core.check.task_motion import TaskMotion

# ----------------------------------------------------------------------------------------------
# per-sample terms (plain arrays: usable without a Motion)


def mounting_wrench(base: BaseWrench) -> laws.ScaledWrench:
    """The mounting's wrench on the robot (root origin, root axes) split into force and moment,
    each static + s·dynamic."""
    return laws.ScaledWrench(force_static=base.static[:, :3], force_dynamic=base.dynamic[:, :3],
                             moment_static=base.static[:, 3:], moment_dynamic=base.dynamic[:, 3:])


def unit_payload_wrench(point: FrameTerms, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(force, moment) N×3 that 1 kg more at the payload point adds to the mounting's wrench at
    the given timing (root axes, about the root origin): a_c − g and c × (a_c − g)."""
    return law_kernels.payload_wrench_rows(point.position, point.linear_acceleration,
                                           np.asarray(gravity, dtype=float))


def _payload_wrench(task: "TaskMotion") -> tuple[np.ndarray, np.ndarray]:
    """:func:`unit_payload_wrench` at the task's payload point, once per check."""
    return task.derived("payload_wrench_per_kg",
                        lambda: unit_payload_wrench(task.frame("payload"), task.gravity))


def grasp_force(point: FrameTerms, rotation: np.ndarray, gravity: np.ndarray,
                mass: float) -> laws.GraspForce:
    """The force the grasp supplies to a point-mass payload of ``mass`` kg at ``point`` (its
    centre of mass), in the grasp frame's axes (``rotation``: N×3×3 grasp-frame-to-root)."""
    R = np.asarray(rotation, dtype=float)
    a_local = law_kernels.rotate_back(R.reshape(len(R), 9), point.linear_acceleration)
    return laws.payload_grasp_force(mass, a_local, laws.gravity_in_frame(R, gravity))


def _quadratic_norm_band(a: np.ndarray, b: np.ndarray, L: float) -> Band:
    """The interval of m with |a + m·b| ≤ L at every row (N×d): |b|²m² + 2(a·b)m + |a|² − L²."""
    A, B, C = law_kernels.norm_band_terms(a, b, L)
    return kernels.quadratic_band(A[None], B[None], C[None])


# ----------------------------------------------------------------------------------------------
# the kinds

class _TaskKind(LimitedConstraint):
    """One place, one law: value, limit and time scale per sample from a LawResult."""

    scope = "task"
    payload_dependent = True
    place: ClassVar[str]
    unit: ClassVar[str]

    def __init__(self, motion: Motion):
        task = motion.task
        self.where, self.units, self.warnings = (self.place,), [self.unit], []
        self.law = self._law(motion, task)
        self.value = self.law.value[:, None]
        self.limit = np.broadcast_to(self.law.limit, self.value.shape)
        self._motion = motion

    def scan_requests(self) -> list[ScanRequest]:
        return [ScanRequest(sk.ABS, (self.value,), np.array([self.law.limit]))]

    @property
    def _k(self) -> float:
        """The largest per-sample k over the rows the laws cover (NaN if any is)."""
        k = self.law.time_scale[self._motion.rows]
        return float(np.max(k)) if k.size else 0.0

    @abstractmethod
    def _law(self, motion: Motion, task: "TaskMotion") -> laws.LawResult:
        """The kind's law over every sample."""

    @abstractmethod
    def _still_reason(self, motion: Motion, n: int) -> str:
        """What the still pose at sample n needs, beyond the limit."""

    def time_scale(self) -> np.ndarray:
        return np.array([self._k])

    def blocked(self) -> Blocked | None:
        if not math.isinf(self._k):
            return None
        # the worst still pose among the samples no slowdown helps
        motion = self._motion
        k = self.law.time_scale[motion.rows]
        still = np.where(np.isinf(k), self.law.static_value[motion.rows], -math.inf)
        n = motion.r0 + int(np.argmax(still))
        return Blocked(self.place, self._still_reason(motion, n) + f" at q = "
                       f"{_q_text(motion.Q[n])} (t = {motion.smp.t[n]:.2f} s); no slowdown helps")

    def _detail(self, motion: Motion) -> str:
        """What :meth:`describe` needs beyond the Violation (its ``detail``)."""
        return ""

    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        peaks, violations = super().report(motion)
        if violations:
            violations = [dataclasses.replace(v, detail=self._detail(motion))
                          for v in violations]
        return peaks, violations


class _MountingNorm(_TaskKind):
    """|static + s·dynamic| of the mounting's force or moment against its maximum."""

    place = "base_limits"
    part: ClassVar[int]          # 0: force, 1: moment
    limit_key: ClassVar[str]

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        b = model.task_limits.base_limits
        return b is not None and math.isfinite(getattr(b, cls.limit_key))

    def _parts(self, task: "TaskMotion") -> tuple[np.ndarray, np.ndarray]:
        w = mounting_wrench(task.base)
        return ((w.force_static, w.force_dynamic) if self.part == 0
                else (w.moment_static, w.moment_dynamic))

    def _law(self, motion: Motion, task: "TaskMotion") -> laws.LawResult:
        return laws.norm_law(*self._parts(task), getattr(task.limits.base_limits, self.limit_key))

    def _still_reason(self, motion: Motion, n: int) -> str:
        return (f"gravity and the task wrench alone load the mounting with "
                f"{_fmt(self.law.static_value[n])} {self.unit} of {_fmt(self.law.limit)} "
                f"{self.unit}")

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        task = motion.task
        per_kg = _payload_wrench(task)
        static, dynamic = self._parts(task)
        return _quadratic_norm_band(static + dynamic, per_kg[self.part], self.law.limit)

    @classmethod
    def describe(cls, v: Violation) -> str:
        return (f"{cls.label} {_fmt(v.peak_value)} {v.unit} of {_fmt(v.limit)} {v.unit} "
                f"at t = {v.peak_time_s:.2f} s")


class BaseForce(_MountingNorm):
    kind, label, unit, part, limit_key = "base_force", "base force", "N", 0, "max_force"


class BaseMoment(_MountingNorm):
    kind, label, unit, part, limit_key = "base_moment", "base moment", "N·m", 1, "max_moment"


class Tipping(_TaskKind):
    """The centre of pressure on the floor inside the support polygon: the ``tipping_ratio``
    gauge (1 on the edge, inf at lift-off) against 1."""

    kind, label, place, unit = "tipping", "tipping", "base_limits", ""

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return bool(model.task_limits.tipping)

    def _floor(self, task: "TaskMotion", reaction: laws.ScaledWrench) -> laws.TippingResult:
        b = task.limits.base_limits
        return laws.tipping_law(reaction, polygon=b.support_polygon, base_mass=b.base_mass,
                                base_com=b.base_com, gravity=task.gravity)

    def _law(self, motion: Motion, task: "TaskMotion") -> laws.TippingResult:
        return self._floor(task, mounting_wrench(task.base))

    def _still_reason(self, motion: Motion, n: int) -> str:
        g = self.law.static_value[n]
        if math.isinf(g):
            return "the still robot and base lift off the floor (no normal force)"
        w = mounting_wrench(motion.task.base)
        still = laws.ScaledWrench(*(x[n:n + 1] for x in (w.force_static, 0 * w.force_dynamic,
                                                         w.moment_static, 0 * w.moment_dynamic)))
        cop = self._floor(motion.task, still).centre_of_pressure[0]
        return (f"the still robot's centre of pressure {_xy(cop)} m is outside the support "
                f"polygon (tipping gauge {g:.3g})")

    def _detail(self, motion: Motion) -> str:
        cop = self.law.centre_of_pressure[self.law.peak_index]   # the Violation's peak sample
        return "lift-off" if not np.all(np.isfinite(cop)) else _xy(cop)

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        """N and N·p are linear in the extra mass m: each edge b_i·N − n_i·(N·p) ≥ 0 and N > 0
        are linear inequalities in m (the same half-planes the law uses)."""
        task = motion.task
        f1, m1 = _payload_wrench(task)
        w = mounting_wrench(task.base)
        b = task.limits.base_limits
        weight = laws.base_weight(base_mass=b.base_mass, base_com=b.base_com, gravity=task.gravity)
        p = b.support_polygon
        # alpha + m·beta per edge column [N, b_i·N − n_i·P] (of the floor wrench and of f1, m1)
        return law_kernels.tipping_mass_band(
            w.force_static + w.force_dynamic, w.moment_static + w.moment_dynamic, f1, m1,
            *weight, p.normals, p.offsets)

    @classmethod
    def describe(cls, v: Violation) -> str:
        detail = v.detail
        at = f"at t = {v.peak_time_s:.2f} s"
        if math.isinf(v.peak_value) or detail == "lift-off":
            return f"tipping: the base lifts off the floor (no normal force) {at}"
        where = f" {detail} m" if detail else ""
        return (f"tipping: centre of pressure{where} outside the support polygon "
                f"(gauge {v.peak_value:.3g} of 1) {at}")


class GraspSlip(_TaskKind):
    """The grasp force's component perpendicular to the grip's normal axis within
    μ·grip_force·faces (the friction cone)."""

    kind, label, place, unit = "grasp_slip", "grasp slip", "grasp", "N"

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return model.task_limits.grasp is not None

    def _unit_force(self, task: "TaskMotion") -> laws.GraspForce:
        return task.derived("grasp_force_per_kg", lambda: grasp_force(
            task.frame("payload"), task.rotation[task.roles["grasp"]], task.gravity, 1.0))

    def _law(self, motion: Motion, task: "TaskMotion") -> laws.LawResult:
        g = task.limits.grasp
        f = self._unit_force(task)
        m = float(task.payload_mass)
        return laws.grasp_slip_law(laws.GraspForce(m * f.static, m * f.dynamic),
                                   normal_axis=g.normal_axis, limit=g.max_tangential_force)

    def _still_reason(self, motion: Motion, n: int) -> str:
        g = motion.task.limits.grasp
        return (f"the still payload slips at {g.frame}: gravity alone needs "
                f"{self.law.static_value[n]:.1f} N tangential of {self.law.limit:.1f} N")

    def _detail(self, motion: Motion) -> str:
        return motion.task.limits.grasp.frame

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        """The force is (m0 + m)·f1: |tangential| ≤ L is a quadratic in m per sample."""
        task = motion.task
        f = self._unit_force(task)
        t1 = laws.tangential(f.static + f.dynamic, task.limits.grasp.normal_axis)
        return _quadratic_norm_band(float(task.payload_mass) * t1, t1, self.law.limit)

    @classmethod
    def describe(cls, v: Violation) -> str:
        frame = v.detail
        return (f"grasp{' at ' + frame if frame else ''} slips (tangential {v.peak_value:.1f} N "
                f"of {v.limit:.1f} N) at t = {v.peak_time_s:.2f} s")


#: The base and grasp kinds, in the order the time scale breaks ties (registered in core.kinds).
BASE_KINDS: tuple[type[_TaskKind], ...] = (BaseForce, BaseMoment, Tipping, GraspSlip)


def _q_text(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.3g}" for x in q) + "]"


def _xy(p: np.ndarray) -> str:
    return f"({p[0]:.3f}, {p[1]:.3f})"
