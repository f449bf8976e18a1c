"""Compiled rigid-body passes over the joint tree: one joint's world frame at its coordinate
(inlined into every tree walk: this one, the frame kernels', the observer's) and gravity torques
g(q) row by row. Numba, no rclpy; the options and types as in :mod:`dyn_node.core.compiled.jit`.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _B, _I, _JIT, _M, _V, _f8


@njit(inline="always", **_JIT)   # inlined: a call per joint and state would cost time
def joint_frame(R: np.ndarray, b00: float, b01: float, b02: float, b10: float, b11: float,
                b12: float, b20: float, b21: float, b22: float, ux: float, uy: float, uz: float,
                zx: float, zy: float, zz: float, q: float, revolute: bool, px: float, py: float,
                pz: float) -> tuple[float, float, float]:
    """A one-DoF joint at coordinate q: writes its world rotation into R (9, row-major) from the
    rotation B of its frame at q = 0 (b..) and its axis (u, joint frame; z, world), and returns
    its origin p moved by a prismatic stroke. Shared by the gravity and frame kernels."""
    if revolute:
        # R = B · Rot(axis, q), Rodrigues' formula
        sn, cs = math.sin(q), math.cos(q)
        cc = 1.0 - cs
        e00, e01, e02 = cs + ux * ux * cc, ux * uy * cc - uz * sn, ux * uz * cc + uy * sn
        e10, e11, e12 = uy * ux * cc + uz * sn, cs + uy * uy * cc, uy * uz * cc - ux * sn
        e20, e21, e22 = uz * ux * cc - uy * sn, uz * uy * cc + ux * sn, cs + uz * uz * cc
        R[0] = b00 * e00 + b01 * e10 + b02 * e20
        R[1] = b00 * e01 + b01 * e11 + b02 * e21
        R[2] = b00 * e02 + b01 * e12 + b02 * e22
        R[3] = b10 * e00 + b11 * e10 + b12 * e20
        R[4] = b10 * e01 + b11 * e11 + b12 * e21
        R[5] = b10 * e02 + b11 * e12 + b12 * e22
        R[6] = b20 * e00 + b21 * e10 + b22 * e20
        R[7] = b20 * e01 + b21 * e11 + b22 * e21
        R[8] = b20 * e02 + b21 * e12 + b22 * e22
        return px, py, pz
    R[0], R[1], R[2] = b00, b01, b02
    R[3], R[4], R[5] = b10, b11, b12
    R[6], R[7], R[8] = b20, b21, b22
    return px + q * zx, py + q * zy, pz + q * zz


# One compiled pass per state over the joint tree: split into calls, per-state overhead
# would break the check's time budget.
@njit([types.void(_M, _I, _B, _I, _M, _M, _M, _V, types.Array(_f8, 2, "C"))], **_JIT)
def gravity_rows(Q: np.ndarray, parent: np.ndarray, revolute: np.ndarray, index: np.ndarray,
                 placement: np.ndarray, axis: np.ndarray, body: np.ndarray, g: np.ndarray,
                 out: np.ndarray) -> None:
    """Generalized gravity g(q) (N·m, or N for prismatic joints) of N states Q (N×nv) into
    ``out`` (N×nv), for a tree of single-DoF joints 1..n−1 (row 0 is the world):
    ``parent[i] < i``, revolute about (``revolute[i]``) or prismatic along unit ``axis[i]``
    (joint frame), ``index[i]`` its column in Q, ``placement[i]`` the joint frame in its parent's at
    q = 0 (row-major rotation, then translation: 12 values), ``body[i]`` the mass (kg) and centre
    of mass (joint frame, m) of everything rigidly attached to joint i, ``g`` gravity (world,
    m/s²).

    g(q) = ∂U/∂q with U = −Σ mⱼ g·cⱼ: for a revolute joint at pᵢ with world axis zᵢ,
    gᵢ = −zᵢ·((Sᵢ − Mᵢpᵢ) × g), and for a prismatic one gᵢ = −Mᵢ zᵢ·g, where Mᵢ and Sᵢ are the
    mass and first moment Σ mⱼcⱼ of the subtree from joint i. One forward pass (poses) and one
    backward pass (subtree sums) per state: the velocity and acceleration terms that a full
    RNEA with v = a = 0 still computes are never formed."""
    n = len(parent)
    Rw = np.zeros((n, 9))       # world rotation of each joint frame, row-major
    pw = np.zeros((n, 3))       # world position of each joint frame
    z = np.zeros((n, 3))        # world joint axis
    Ms = np.zeros(n)
    S = np.zeros((n, 3))
    Rw[0, 0] = Rw[0, 4] = Rw[0, 8] = 1.0
    g0, g1, g2 = g[0], g[1], g[2]
    for k in range(Q.shape[0]):
        for i in range(1, n):
            a, P = parent[i], placement[i]
            A = Rw[a]
            # B = R_parent · R_placement; p = p_parent + R_parent · t_placement
            b00 = A[0] * P[0] + A[1] * P[3] + A[2] * P[6]
            b01 = A[0] * P[1] + A[1] * P[4] + A[2] * P[7]
            b02 = A[0] * P[2] + A[1] * P[5] + A[2] * P[8]
            b10 = A[3] * P[0] + A[4] * P[3] + A[5] * P[6]
            b11 = A[3] * P[1] + A[4] * P[4] + A[5] * P[7]
            b12 = A[3] * P[2] + A[4] * P[5] + A[5] * P[8]
            b20 = A[6] * P[0] + A[7] * P[3] + A[8] * P[6]
            b21 = A[6] * P[1] + A[7] * P[4] + A[8] * P[7]
            b22 = A[6] * P[2] + A[7] * P[5] + A[8] * P[8]
            px = pw[a, 0] + A[0] * P[9] + A[1] * P[10] + A[2] * P[11]
            py = pw[a, 1] + A[3] * P[9] + A[4] * P[10] + A[5] * P[11]
            pz = pw[a, 2] + A[6] * P[9] + A[7] * P[10] + A[8] * P[11]
            ux, uy, uz = axis[i, 0], axis[i, 1], axis[i, 2]
            zx = b00 * ux + b01 * uy + b02 * uz
            zy = b10 * ux + b11 * uy + b12 * uz
            zz = b20 * ux + b21 * uy + b22 * uz
            z[i, 0], z[i, 1], z[i, 2] = zx, zy, zz
            q = Q[k, index[i]]
            R = Rw[i]
            px, py, pz = joint_frame(R, b00, b01, b02, b10, b11, b12, b20, b21, b22, ux, uy, uz,
                                     zx, zy, zz, q, revolute[i], px, py, pz)
            pw[i, 0], pw[i, 1], pw[i, 2] = px, py, pz
            m, c0, c1, c2 = body[i, 0], body[i, 1], body[i, 2], body[i, 3]
            Ms[i] = m
            S[i, 0] = m * (px + R[0] * c0 + R[1] * c1 + R[2] * c2)
            S[i, 1] = m * (py + R[3] * c0 + R[4] * c1 + R[5] * c2)
            S[i, 2] = m * (pz + R[6] * c0 + R[7] * c1 + R[8] * c2)
        # children have larger indices than their parent: by the time joint i is reached, its
        # subtree's mass and first moment are complete
        for i in range(n - 1, 0, -1):
            if revolute[i]:
                rx = S[i, 0] - Ms[i] * pw[i, 0]
                ry = S[i, 1] - Ms[i] * pw[i, 1]
                rz = S[i, 2] - Ms[i] * pw[i, 2]
                out[k, index[i]] = -(z[i, 0] * (ry * g2 - rz * g1) + z[i, 1] * (rz * g0 - rx * g2)
                                     + z[i, 2] * (rx * g1 - ry * g0))
            else:
                out[k, index[i]] = -Ms[i] * (z[i, 0] * g0 + z[i, 1] * g1 + z[i, 2] * g2)
            a = parent[i]
            if a > 0:
                Ms[a] += Ms[i]
                S[a, 0] += S[i, 0]
                S[a, 1] += S[i, 1]
                S[a, 2] += S[i, 2]


# --- sampling and per-column peaks -----------------------------------------------------------------
