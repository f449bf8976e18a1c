"""The frame terms of a sampled motion that the task kinds read (:class:`TaskMotion`).

Built once per check when the limits file configures any task section: one batched
:class:`~dyn_node.core.check.frames.FrameKinematics` pass over the samples (its tables cached per
:class:`Dynamics`), the task wrench's joint torque J_frameᵀ·W and the mounting's wrench with the
reaction to W. Root axes = world axes for a fixed-base URDF (Pinocchio puts the root link at the
world origin). Units SI.
"""
from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics, TorqueTerms
from dyn_node.core.check.frames import BaseWrench, FrameBatch, FrameKinematics, FramePoint
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.task_limits import TaskLimits
from dyn_node.errors import ModelError

FRAME_ROLE = "frame:"


@dataclass(frozen=True)
class TaskMotion:
    """The task terms over a Motion's M samples at k = 1 (see docs of SPEC18's fields):
    ``roles`` maps "frame:<link>" (per frame_limits entry), "wrench", "grasp" and "payload" (the
    payload CoM point) to an index into ``batch.frames``; ``rotation`` F×M×3×3 frame-to-root;
    ``task_torque`` (M×nv, already inside Motion.S, G and tau) None without a task wrench;
    ``base`` the mounting's wrench on the robot at the root origin in root axes, static part
    with gravity and the reaction +W to the task wrench, None without base_limits."""

    limits: TaskLimits
    batch: FrameBatch
    rotation: np.ndarray
    roles: Mapping[str, int]
    task_torque: np.ndarray | None
    base: BaseWrench | None
    gravity: np.ndarray
    payload_mass: float
    #: τ1 = J_cᵀ·(a_c − g) (M×nv column-major, per kg) at the payload point, when asked for:
    #: the payload margin's torque per kg without a second RNEA pass
    payload_torque: np.ndarray | None = None
    #: the samples' torque terms (friction included, the task wrench not) from the frame pass's
    #: RNEA, when asked for: the check's only dynamics pass (:func:`torque_terms`)
    terms: TorqueTerms | None = None
    #: derived per-sample terms several kinds read (see :meth:`derived`)
    _derived: dict = field(default_factory=dict, repr=False, compare=False)

    def frame(self, role: str):
        """The :class:`~dyn_node.core.check.frames.FrameTerms` of ``role``."""
        return self.batch.frames[self.roles[role]]

    def derived(self, key: str, make: Callable[[], Any]) -> Any:
        """``make()``, computed once per check for ``key`` (terms that several kinds or a
        kind's law and its payload band read, e.g. the per-kg payload wrench)."""
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]


def configured(limits: TaskLimits) -> bool:
    """Whether the limits file configures any task section."""
    return bool(limits.frame_limits) or any(x is not None for x in (
        limits.robot_limits, limits.task_wrench, limits.base_limits, limits.grasp))


def needs_inertia(limits: TaskLimits) -> bool:
    """M(q) per sample: kinetic or transferred energy."""
    return (limits.robot_limits is not None
            or any(np.isfinite(f.max_transferred_energy) for f in limits.frame_limits))


def _points(model: RobotModel) -> tuple[list[FramePoint], dict[str, int]]:
    lim = model.task_limits
    points: list[FramePoint] = []
    roles: dict[str, int] = {}

    def add(role: str, point: FramePoint) -> None:
        roles[role] = len(points)
        points.append(point)

    for f in lim.frame_limits:
        add(FRAME_ROLE + f.frame, FramePoint(f.frame, tuple(map(float, f.point))))
    if lim.task_wrench is not None:
        w = lim.task_wrench
        wrench = (*map(float, w.force), *map(float, w.torque))
        # on a frame_limits entry's frame its point carries the wrench too (applied at the
        # frame's origin whatever the point): one point fewer for the kernel
        shared = roles.get(FRAME_ROLE + w.frame)
        if shared is None:
            add("wrench", FramePoint(w.frame, wrench=wrench))
        else:
            points[shared] = replace(points[shared], wrench=wrench)
            roles["wrench"] = shared
    if lim.grasp is not None:
        add("grasp", FramePoint(lim.grasp.frame))
    # the payload CoM: the grasp's load and the per-kg terms of the payload-dependent kinds
    # (the joint torque per kg of the payload margin included)
    add("payload", FramePoint(model.payload_frame, tuple(map(float, model.payload.com))))
    return points, roles


_CACHE: "weakref.WeakKeyDictionary[Dynamics, tuple[RobotModel, FrameKinematics, dict]]" = \
    weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def kinematics(dynamics: Dynamics) -> tuple[FrameKinematics, dict[str, int]]:
    """The frame kinematics of the model's task points and their roles (cached per instance,
    rebuilt when its model changes)."""
    model = dynamics.model
    with _LOCK:
        hit = _CACHE.get(dynamics)
        if hit is not None and hit[0] is model:
            return hit[1], hit[2]
    points, roles = _points(model)
    # effective masses only where transferred energy reads them, and the payload point's
    # Jacobian coupled into M⁻¹ then: transferred energy's exact payload margin
    massed = [roles[FRAME_ROLE + f.frame] for f in model.task_limits.frame_limits
              if np.isfinite(f.max_transferred_energy)]
    couple = roles.get("payload") if massed else None
    fk = FrameKinematics(model, points, include_armature=dynamics.options.include_armature,
                         couple_point=couple, mass_points=massed,
                         unit_mass_point=roles["payload"])
    with _LOCK:
        _CACHE[dynamics] = (model, fk, roles)
    return fk, roles


def reaction(fk: FrameKinematics, batch: FrameBatch, rotation: np.ndarray, index: int
             ) -> np.ndarray:
    """The task wrench W (frame axes, at the frame origin) of point ``index`` as the mounting
    takes it back: [force; moment] (M×6) at the root origin in root axes (+W: the environment's
    −W on the tool is held by the mounting's +W)."""
    from dyn_node.core.compiled import law_kernels

    spec = fk.points[index]
    R0, r0 = fk.base_placement
    # one compiled pass over the samples (the NumPy form took ~0.9 ms on the bench's 10 s)
    return law_kernels.task_reaction(rotation[index].reshape(-1, 9), batch.frames[index].position,
                                     np.asarray(spec.point, dtype=float),
                                     np.asarray(spec.wrench, dtype=float), R0,
                                     np.asarray(r0, dtype=float))


def build(dynamics: Dynamics, Q: np.ndarray, V: np.ndarray, A: np.ndarray, *,
          payload_torque: bool = False, rnea: bool = False) -> TaskMotion | None:
    """The task terms of the samples Q, V, A (M×nv), or None when nothing is configured;
    ``payload_torque``: also the payload margin's terms (τ1, the torque per kg at the payload
    point, and the effective masses' coupling to it); ``rnea``: also the
    torque terms (:attr:`TaskMotion.terms`)."""
    model = dynamics.model
    lim = model.task_limits
    if not configured(lim):
        return None
    fk, roles = kinematics(dynamics)
    batch = fk.compute(Q, V, A, inertia=needs_inertia(lim), base=lim.base_limits is not None,
                       unit_mass=payload_torque, rnea=rnea, couple=payload_torque)
    rotation = batch.rotations
    tau_w = base = None
    if "wrench" in roles:
        tau_w = batch.frames[roles["wrench"]].task_torque
    if batch.base is not None:
        base = batch.base
        if "wrench" in roles:
            base = replace(base, static=base.static + reaction(fk, batch, rotation,
                                                               roles["wrench"]))
    return TaskMotion(limits=lim, batch=batch, rotation=rotation, roles=roles, task_torque=tau_w,
                      base=base, gravity=np.array(model.gravity, dtype=float),
                      payload_mass=float(model.payload.mass),
                      payload_torque=batch.unit_mass_torque,
                      terms=torque_terms(dynamics, batch, V, A) if rnea else None)


def torque_terms(dynamics: Dynamics, batch: FrameBatch, V: np.ndarray, A: np.ndarray
                 ) -> TorqueTerms:
    """The torque terms of a batch computed with ``rnea=True`` (what Dynamics.terms_batch
    gives from Pinocchio's pass, to ~1e-14 N·m: the same split, friction and armature)."""
    trq, grv = batch.rnea
    V, A = (np.ascontiguousarray(x, dtype=float) for x in (V, A))
    return dynamics.split_terms(grv.T, trq.T, V, A)


_UNSUPPORTED: "weakref.WeakKeyDictionary[Dynamics, RobotModel]" = weakref.WeakKeyDictionary()


def joint_terms(dynamics: Dynamics, Q: np.ndarray, V: np.ndarray, A: np.ndarray, *,
                payload_torque: bool = False
                ) -> tuple[TorqueTerms, np.ndarray | None] | tuple[None, None]:
    """Without a task section: the torque terms of the states from the frame pass on the
    payload point alone (its RNEA and gravity, ~0.6 of Pinocchio's batched RNEA with the
    compiled gravity pass on the bench's Panda), and with ``payload_torque`` τ1 per kg there;
    (None, None) where the kernels cannot take the model (a joint other than one-DoF revolute
    or prismatic) or a state is not finite: the caller then asks Dynamics.terms_batch."""
    model = dynamics.model
    if _UNSUPPORTED.get(dynamics) is model or not all(np.isfinite(X).all() for X in (Q, V, A)):
        return None, None
    try:
        fk, _ = kinematics(dynamics)
    except ModelError:
        _UNSUPPORTED[dynamics] = model
        return None, None
    batch = fk.compute(Q, V, A, inertia=False, base=False, unit_mass=payload_torque, rnea=True)
    return torque_terms(dynamics, batch, V, A), batch.unit_mass_torque


def inverse_dynamics(dynamics: Dynamics, Q: np.ndarray, V: np.ndarray, A: np.ndarray
                     ) -> np.ndarray | None:
    """τ (N×nv) at the states by the check's own route (the frame pass's RNEA terms, plus
    J_frameᵀ·W of a task wrench), None where the check takes Dynamics.terms_batch."""
    if not configured(dynamics.model.task_limits):
        terms = joint_terms(dynamics, Q, V, A)[0]
        return None if terms is None else np.ascontiguousarray(terms.full)
    fk, roles = kinematics(dynamics)
    batch = fk.compute(Q, V, A, inertia=False, base=False, rnea=True)
    tau = np.ascontiguousarray(torque_terms(dynamics, batch, V, A).full)
    if "wrench" in roles:
        tau += batch.frames[roles["wrench"]].task_torque
    return tau


