"""Rigid-body dynamics on a :class:`~dyn_node.core.robot.model.RobotModel`, single-state and batched.

Units are SI and arrays are in model joint order: q (rad|m), v (rad/s|m/s), a (rad/s²|m/s²),
torques in N·m (N for prismatic joints). Batched functions take and return N×nv arrays, one row
per state.

Friction is the URDF's ``<dynamics>``: viscous ``damping·v`` plus Coulomb ``friction·sign(v)``.
Armature (rotor inertia reflected to the joint) adds ``armature·a``. With both enabled,
``rnea(q, v, a) = M(q)·a + bias(q, v)`` holds exactly, with friction inside ``bias``.

A :class:`Dynamics` owns Pinocchio work buffers and is not thread-safe: give each thread its own.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from dyn_node.core.robot.model import RobotModel


@dataclass(frozen=True)
class DynamicsOptions:
    include_friction: bool = True
    include_armature: bool = True


@dataclass(frozen=True)
class TorqueTerms:
    """Torques split by how they scale when a trajectory is stretched in time by k (N×nv, N·m).

    ``static``: gravity + Coulomb friction (unchanged by k); ``viscous``: damping·v (÷k);
    ``inertial``: M(q)a + C(q, v)v + armature·a (÷k²). Their sum is the full RNEA torque.
    """

    static: np.ndarray
    viscous: np.ndarray
    inertial: np.ndarray
    full: np.ndarray     # the torque at k = 1: their sum, but Pinocchio's RNEA at a state at rest

    def total(self, k: float = 1.0) -> np.ndarray:
        return self.static + self.viscous / k + self.inertial / (k * k)


_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


def joint_axis(joint_model: Any) -> tuple[bool, np.ndarray] | None:
    """(revolute, unit axis in the joint frame) of a one-DoF revolute or prismatic Pinocchio
    joint model (JointModelRZ, JointModelPrismaticUnaligned, ...); None for any other kind."""
    name = joint_model.shortname()
    if name in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
        axis = np.asarray(joint_model.extract().axis, dtype=float)
        return name.startswith("JointModelR"), axis / np.linalg.norm(axis)
    if name[:-1] in ("JointModelR", "JointModelP") and name[-1] in _AXES:
        return name.startswith("JointModelR"), np.array(_AXES[name[-1]])
    return None


def gravity_tables(pm: pin.Model) -> tuple[np.ndarray, ...] | None:
    """The arrays :func:`dyn_node.core.compiled.rigid_kernels.gravity_rows` takes after Q, from a Pinocchio model's
    joint placements, axes, body inertias and gravity; None when a joint is not a one-DoF
    revolute or prismatic one (Pinocchio's own pass is used then)."""
    n = pm.njoints
    parent = np.array(pm.parents, dtype=np.int64)
    revolute = np.zeros(n, dtype=bool)
    index = np.zeros(n, dtype=np.int64)
    placement = np.zeros((n, 12))
    axis = np.zeros((n, 3))
    body = np.zeros((n, 4))
    for i in range(1, n):
        found = joint_axis(pm.joints[i])
        if found is None:
            return None
        revolute[i], axis[i] = found
        index[i] = pm.joints[i].idx_v
        placement[i, :9] = pm.jointPlacements[i].rotation.reshape(9)
        placement[i, 9:] = pm.jointPlacements[i].translation
        body[i, 0] = pm.inertias[i].mass
        body[i, 1:] = pm.inertias[i].lever
    return parent, revolute, index, placement, axis, body, np.array(pm.gravity.linear, dtype=float)


class Dynamics:
    """Gravity, inverse dynamics, mass matrix and bias for one model and one set of options."""

    def __init__(self, model: RobotModel, options: DynamicsOptions = DynamicsOptions(),
                 threads: int = 1):
        self.model = model
        self.options = options
        pm = model.pin_model.copy()
        if not options.include_armature:
            pm.armature = np.zeros(pm.nv)
        self._pm = pm
        self._data = pm.createData()
        self._damping = np.array(pm.damping) if options.include_friction else np.zeros(pm.nv)
        self._coulomb = np.array(pm.friction) if options.include_friction else np.zeros(pm.nv)
        self._has_friction = bool(np.any(self._damping) or np.any(self._coulomb))
        self._zero = np.zeros(pm.nv)
        # One thread by default: Pinocchio's C++ batch is already ~2x the Python loop on one core,
        # and a second OpenMP thread is erratic when the other core is busy (seen in make bench).
        self._cores = os.cpu_count() or 1
        self._threads = max(1, min(int(threads), self._cores))
        self._pool: pin.ModelPool | None = None
        self._gravity_tables = gravity_tables(pm)

    @property
    def nv(self) -> int:
        return self._pm.nv

    @property
    def pin_model(self) -> pin.Model:
        """The Pinocchio model these dynamics use (armature as the options say); do not modify."""
        return self._pm

    @property
    def friction_coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(viscous damping, Coulomb friction) per joint, zeros when friction is disabled."""
        return self._damping, self._coulomb

    # --- single state ------------------------------------------------------------------------
    def gravity(self, q: np.ndarray) -> np.ndarray:
        """Generalized gravity g(q) (N·m): the torque that holds the robot still at q."""
        return pin.computeGeneralizedGravity(self._pm, self._data, q).copy()

    def friction(self, v: np.ndarray) -> np.ndarray:
        """Viscous plus Coulomb friction torque at velocity v (N·m); zero when disabled."""
        return self._damping * v + self._coulomb * np.sign(v)

    def rnea(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Inverse dynamics τ = M(q)a + C(q, v)v + g(q) + friction(v) (N·m)."""
        tau = pin.rnea(self._pm, self._data, q, v, a).copy()
        if self._has_friction:
            tau += self.friction(v)
        return tau

    def gravity_and_rnea(self, q: np.ndarray, v: np.ndarray,
                         a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(g(q), rnea(q, v, a)) for the live path: two Pinocchio calls, no Python in between."""
        return self.gravity(q), self.rnea(q, v, a)

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """Joint-space inertia M(q) (kg·m²), armature on the diagonal when enabled; symmetric."""
        M = pin.crba(self._pm, self._data, q)
        return np.triu(M) + np.triu(M, 1).T

    def bias(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """h(q, v) = C(q, v)v + g(q) + friction(v) (N·m), so that rnea = M·a + h."""
        h = pin.nonLinearEffects(self._pm, self._data, q, v).copy()
        if self._has_friction:
            h += self.friction(v)
        return h

    def coriolis_matrix(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """C(q, v) (N·m·s/rad) in Pinocchio's factorisation, the one with Ṁ = C + Cᵀ that the
        momentum observer needs; C(q, v)v is the Coriolis and centrifugal torque."""
        return pin.computeCoriolisMatrix(self._pm, self._data, q, v).copy()

    def potential_energy(self, q: np.ndarray) -> float:
        """Gravitational potential energy (J) of the model's bodies, payload included; its
        gradient is g(q)."""
        return float(pin.computePotentialEnergy(self._pm, self._data, q))

    # --- batched -----------------------------------------------------------------------------
    def batch_threads(self, threads: int | None = None) -> int:
        """Threads a batched call will use: ``threads`` (None: the constructor's setting),
        clamped to [1, cpu_count]."""
        n = self._threads if threads is None else int(threads)
        return max(1, min(n, self._cores))

    def _rigid_columns(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray,
                       threads: int | None = None) -> np.ndarray:
        """Rigid-body RNEA of N row-major states, as nv×N (one state per column)."""
        n = len(Q)
        out = np.empty((self.nv, n), order="F")
        if n == 0:
            return out
        nt = self.batch_threads(threads)
        if self._pool is None or self._pool.size() < nt:
            self._pool = pin.ModelPool(self._pm, nt)
        # Pinocchio's batch wants one state per column; the row-major N×nv arrays transposed are
        # exactly that memory, so no copy is made on the way in or out. Each state is computed
        # by the same sequential RNEA whatever the thread count, so results do not depend on it.
        pin.rneaInParallel(nt, self._pool, Q.T, V.T, A.T, out)
        return out

    def _rnea_rigid_batch(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray,
                          threads: int | None = None) -> np.ndarray:
        Q, V, A = (np.ascontiguousarray(x, dtype=float) for x in (Q, V, A))
        return self._rigid_columns(Q, V, A, threads).T

    def rnea_batch(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray,
                   threads: int | None = None) -> np.ndarray:
        """rnea over N states: Q, V, A are N×nv; returns N×nv (N·m). ``threads``: OpenMP
        threads for this call (None: the constructor's setting)."""
        tau = self._rnea_rigid_batch(Q, V, A, threads)
        if self._has_friction:
            tau = tau + self._damping * V + self._coulomb * np.sign(V)
        return tau

    def gravity_batch(self, Q: np.ndarray, threads: int | None = None) -> np.ndarray:
        """g(q) over N states (N×nv, N·m), by Pinocchio: equal to the last bit to
        :meth:`gravity` per state, which the audit's replay relies on (the compiled kernel
        :meth:`terms_batch` uses differs by ~1e-14 and is kept for the time-scale split)."""
        Z = np.zeros_like(Q, dtype=float)
        return self._rnea_rigid_batch(Q, Z, Z, threads)

    def terms_batch(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray,
                    threads: int | None = None) -> TorqueTerms:
        """RNEA split into static, viscous and inertial parts (see :class:`TorqueTerms`), each
        N×nv and column-major (every joint's samples contiguous, for per-joint reductions).

        The full torque is Pinocchio's batched RNEA; gravity, which the split needs apart, comes
        from :func:`dyn_node.core.compiled.rigid_kernels.gravity_rows` on this model's tables (single-threaded,
        whatever ``threads``), or from Pinocchio's RNEA at v = a = 0 when the model has a joint
        the kernel does not handle."""
        from dyn_node.core.compiled import rigid_kernels  # here, not at import: Numba only for batched checks

        Q, V, A = (np.ascontiguousarray(x, dtype=float) for x in (Q, V, A))
        if self._gravity_tables is None:
            Z = np.zeros_like(Q)
            G = self._rigid_columns(Q, Z, Z, threads)
        else:
            # about 0.3 of the time of Pinocchio's RNEA at v = a = 0 here (make bench); equal to
            # computeGeneralizedGravity to 1e-11 N·m (test_kernels)
            G = np.empty((self.nv, len(Q)), order="F")
            rigid_kernels.gravity_rows(Q, *self._gravity_tables, G.T)
        return self.split_terms(G, self._rigid_columns(Q, V, A, threads), V, A)

    def split_terms(self, G: np.ndarray, F: np.ndarray, V: np.ndarray,
                    A: np.ndarray) -> TorqueTerms:
        """:class:`TorqueTerms` from rigid-body gravity G and RNEA F (nv×N, armature·a in F)
        of states with velocities V and accelerations A (N×nv), this instance's friction
        added (:func:`dyn_node.core.compiled.kernels.split_terms`): the one split whichever pass gave
        G and F."""
        from dyn_node.core.compiled import kernels

        S, W, I, full = kernels.split_terms(G, F, V, A, self._damping, self._coulomb)
        return TorqueTerms(static=S, viscous=W, inertial=I, full=full)
