"""Textbook recursive Newton–Euler inverse dynamics in NumPy: the hand-built baseline.

Featherstone's RNEA on spatial vectors, written out with 3-vectors so it vectorises over many
states at once. Motion vectors are (linear, angular) at a body's joint frame origin, expressed in
that frame; forces are (force, moment) likewise. Only the model's *parameters* are taken from
Pinocchio (tree, joint placements, joint axes, body inertias, gravity, armature); the algorithm
below uses no Pinocchio function.

Units: q rad|m, v rad/s|m/s, a rad/s²|m/s², returns N·m|N, arrays N×nv in the model's order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.robot.dynamics import joint_axis


@dataclass(frozen=True)
class _Joint:
    parent: int          # index into the joint list, -1 for the fixed base
    idx_v: int           # column in q, v, a, tau
    revolute: bool       # else prismatic
    axis: np.ndarray     # unit axis in the joint frame
    rot: np.ndarray      # 3×3 rotation of the joint frame (at q = 0) in the parent frame
    pos: np.ndarray      # origin of the joint frame in the parent frame (m)
    mass: float          # kg
    com: np.ndarray      # centre of mass in the joint frame (m)
    inertia_c: np.ndarray  # rotational inertia about the centre of mass (kg·m²)


def _axis_of(joint_model) -> tuple[bool, np.ndarray]:
    found = joint_axis(joint_model)
    if found is None:
        raise ValueError("NumPy RNEA supports 1-DoF revolute/prismatic joints, not "
                         f"{joint_model.shortname()}")
    return found


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross carries per-call overhead that dominates for small batches; write it out.
    return np.stack((a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]), axis=-1)


def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (N×3×3) about a unit axis by angles (N,)."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


class NumpyRNEA:
    """Inverse dynamics τ = M(q)a + C(q, v)v + g(q) + armature·a by the textbook recursion."""

    def __init__(self, pin_model):
        joints = []
        for i in range(1, pin_model.njoints):
            revolute, axis = _axis_of(pin_model.joints[i])
            placement = pin_model.jointPlacements[i]
            inertia = pin_model.inertias[i]
            joints.append(_Joint(
                parent=int(pin_model.parents[i]) - 1, idx_v=int(pin_model.joints[i].idx_v),
                revolute=revolute, axis=axis, rot=np.array(placement.rotation),
                pos=np.array(placement.translation), mass=float(inertia.mass),
                com=np.array(inertia.lever), inertia_c=np.array(inertia.inertia)))
        self.joints = tuple(joints)
        self.nv = int(pin_model.nv)
        self.gravity = np.array(pin_model.gravity.linear, dtype=float)
        self.armature = np.array(pin_model.armature, dtype=float)

    def rnea(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """One state: q, v, a of length nv; returns τ (nv,)."""
        return self.rnea_batch(q[None, :], v[None, :], a[None, :])[0]

    def rnea_batch(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray) -> np.ndarray:
        """N states at once: Q, V, A are N×nv; returns N×nv."""
        n = Q.shape[0]
        zero = np.zeros((n, 3))
        # The fixed base: at rest, accelerating upwards at -g so gravity needs no special term.
        base = (zero, zero, np.broadcast_to(-self.gravity, (n, 3)), zero)
        rots, poss, vel, acc, forces = [], [], [], [], []
        for j in self.joints:
            qj, vj, aj = Q[:, j.idx_v], V[:, j.idx_v], A[:, j.idx_v]
            if j.revolute:
                R = j.rot @ _rodrigues(j.axis, qj)             # parent <- child rotation
                p = np.broadcast_to(j.pos, (n, 3))
            else:
                R = np.broadcast_to(j.rot, (n, 3, 3))
                p = j.pos + (qj[:, None] * j.axis) @ j.rot.T
            pv, pw, pa, pal = base if j.parent < 0 else (*vel[j.parent], *acc[j.parent])
            Rt = np.swapaxes(R, 1, 2)
            # Motion transform parent -> child: w_c = Rᵀ w_p, v_c = Rᵀ (v_p + w_p × p).
            w = np.einsum("nij,nj->ni", Rt, pw)
            lin = np.einsum("nij,nj->ni", Rt, pv + _cross(pw, p))
            alpha = np.einsum("nij,nj->ni", Rt, pal)
            acc_lin = np.einsum("nij,nj->ni", Rt, pa + _cross(pal, p))
            s_qd = np.outer(vj, j.axis)
            s_qdd = np.outer(aj, j.axis)
            if j.revolute:
                w = w + s_qd
                # a += S q̈ + v × S q̇, with S q̇ = (0, s_qd): (v_lin × s_qd, w × s_qd).
                acc_lin = acc_lin + _cross(lin, s_qd)
                alpha = alpha + s_qdd + _cross(w, s_qd)
            else:
                lin = lin + s_qd
                # S q̇ = (s_qd, 0): v × S q̇ = (w × s_qd, 0).
                acc_lin = acc_lin + s_qdd + _cross(w, s_qd)
            # Body force f = I a + v ×* I v, about the joint origin with c the centre of mass.
            c, m, Ic = j.com, j.mass, j.inertia_c
            h_lin = m * (lin + _cross(w, c))                       # momentum
            h_ang = w @ Ic.T + _cross(c, h_lin)                    # angular momentum about origin
            f_lin = m * (acc_lin + _cross(alpha, c))
            f_ang = alpha @ Ic.T + _cross(c, f_lin)
            f_lin = f_lin + _cross(w, h_lin)
            f_ang = f_ang + _cross(w, h_ang) + _cross(lin, h_lin)
            rots.append(R)
            poss.append(p)
            vel.append((lin, w))
            acc.append((acc_lin, alpha))
            forces.append([f_lin, f_ang])
        tau = np.empty((n, self.nv))
        for k in range(len(self.joints) - 1, -1, -1):
            j = self.joints[k]
            f_lin, f_ang = forces[k]
            tau[:, j.idx_v] = (f_ang if j.revolute else f_lin) @ j.axis
            if j.parent >= 0:
                # Force transform child -> parent: f_p = R f, n_p = R n + p × (R f).
                R, p = rots[k], poss[k]
                fp = np.einsum("nij,nj->ni", R, f_lin)
                npar = np.einsum("nij,nj->ni", R, f_ang) + _cross(p, fp)
                forces[j.parent][0] = forces[j.parent][0] + fp
                forces[j.parent][1] = forces[j.parent][1] + npar
        return tau + A * self.armature
