"""Compiled batched frame kinematics, joint-space inertia and base wrench (Numba, no rclpy).

Pinocchio's Python API has no batched Jacobian or CRBA: a Python loop over 10,000 samples
costs more than the whole check may. One pass per state here gives every configured frame's
point motion and task torque, M(q), its Cholesky factor and the robot's momentum rate, from the
tables :mod:`dyn_node.core.check.frames` builds from Pinocchio's model. ``nogil``/``cache``/explicit
signatures as in :mod:`dyn_node.core.compiled.kernels`: the node's worker thread does not hold the GIL, and
no call stops to compile.

Everything is computed in world axes at the world origin; the base wrench is moved to the base
frame's origin and axes at the end.

:func:`frame_rows`, per state k of Q, V, A (N×nv) and per frame f (F of them):

* ``pos[f, k]``, ``vel``, ``acc`` (F×N×3, world axes): the frame point's position, linear
  velocity J_v·q̇ and classical acceleration J_v·q̈ + J̇_v·q̇ (no gravity); ``omega``,
  ``alpha``: the frame's angular velocity and acceleration; ``rot[f, k]`` (F×N×9) the
  frame-to-world rotation, row-major (Pinocchio's oMf rotation);
* ``tau[ftau[f], k]`` (·×N×nv) for the frames with ``ftau[f]`` ≥ 0: J_localᵀ·W for the
  frame's wrench W = ``fwrench[f]`` ([force; torque] in the frame's axes, at its origin:
  Pinocchio's LOCAL Jacobian);
* with ``with_inertia``: ``Mout[k]`` = M(q) (CRBA, ``armature`` on the diagonal; Mout may
  be sized 0 when M itself is not wanted), ``ke[k]`` = ½·q̇ᵀMq̇, ``gq[k]`` = g(q) (the
  generalized gravity, from the same subtree sums), ``mu[f, k]`` = 1/(uᵀJ_vM⁻¹J_vᵀu)
  with u = vel/|vel| (by the Cholesky factor of M) for the frames with ``fmass[f]`` (the
  other rows are not written); 0 where |vel| = 0, NaN where M is not positive definite;
  with ``fcouple`` ≥ 0 (a
  frame index c) also ``couple[f, k]`` = J_c·M⁻¹·J_vᵀu (3; 0 where |vel| = 0) and
  ``couple_inertia[k]`` = J_c·M⁻¹·J_cᵀ (xx, xy, xz, yy, yz, zz), J_c the linear Jacobian
  of frame c's point: what a point mass added there does to m_u (Woodbury);
* with ``with_base``: the wrench [force; moment] the mounting exerts on the robot at the
  origin of a frame fixed to the world (``root``) in its axes, split into ``wstatic[k]``
  (gravity: q̇ = q̈ = 0) and ``wdynamic[k]`` (the momentum rate dh/dt, quadratic in q̇ and
  linear in q̈), and ``com[k]``, the centre of mass of every body (root link's included),
  in that frame;
* with ``funit`` ≥ 0 (a frame index u) and ``unit`` sized N: ``unit[k]`` (N×nv) =
  J_uᵀ·(a_u − g), the joint torque 1 kg more at frame u's point adds (a point mass: its
  force m·(a_u − g), J_u the point's linear Jacobian);
* with ``rnea`` and ``grav`` sized N: ``rnea[k]`` = the rigid-body inverse dynamics
  M(q)q̈ + C(q, q̇)q̇ + g(q) + armature·q̈ and ``grav[k]`` = g(q) (N×nv), by a backward pass
  over the bodies' momentum rates and weights (:func:`_rnea_backward`).

Model tables (rows 0..n−1, row 0 the world and the bodies fixed to it): ``parent``,
``revolute``, ``index``, ``placement``, ``axis`` as :func:`dyn_node.core.compiled.rigid_kernels.gravity_rows`;
``inertia[i]`` = mass, centre of mass (3, joint frame), rotational inertia about it (xx, xy,
xz, yy, yz, zz, joint axes); ``gravity`` (3, world); ``root`` that frame's placement in
the world (12). Frames: ``fjoint[f]`` its joint, ``fplace[f]`` its placement in the joint
(12), ``fpoint[f]`` the point in frame axes. Arrays sized 0 along N are not written (the
parts switched off).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.rigid_kernels import joint_frame

_JIT = dict(cache=True, nogil=True, error_model="numpy")

_f8 = types.float64
_V = types.Array(_f8, 1, "A", readonly=True)
_M = types.Array(_f8, 2, "A", readonly=True)
_B = types.Array(types.boolean, 1, "A", readonly=True)
_I = types.Array(types.int64, 1, "A", readonly=True)
_C1 = types.Array(_f8, 1, "C")
_C2 = types.Array(_f8, 2, "C")
_C3 = types.Array(_f8, 3, "C")
_A2 = types.Array(_f8, 2, "A")
_A = np.ndarray


@njit(inline="always", **_JIT)
def _cross(ax: float, ay: float, az: float, bx: float, by: float,
           bz: float) -> tuple[float, float, float]:
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(inline="always", **_JIT)
def _carried(w: np.ndarray, al: np.ndarray, vo: np.ndarray, ao: np.ndarray, a: int, rx: float,
             ry: float, rz: float) -> tuple[float, float, float, float, float, float]:
    # velocity and classical acceleration of a point at r from body a's origin, moving with it:
    # v = v_a + ω×r, a = a_a + α×r + ω×(ω×r)
    wx, wy, wz = w[a, 0], w[a, 1], w[a, 2]
    cx, cy, cz = _cross(wx, wy, wz, rx, ry, rz)
    dx, dy, dz = _cross(al[a, 0], al[a, 1], al[a, 2], rx, ry, rz)
    ex, ey, ez = _cross(wx, wy, wz, cx, cy, cz)
    return (vo[a, 0] + cx, vo[a, 1] + cy, vo[a, 2] + cz,
            ao[a, 0] + dx + ex, ao[a, 1] + dy + ey, ao[a, 2] + dz + ez)


@njit(inline="always", **_JIT)
def _rot(R: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    # R (row-major 9) times a vector
    return (R[0] * x + R[1] * y + R[2] * z, R[3] * x + R[4] * y + R[5] * z,
            R[6] * x + R[7] * y + R[8] * z)


@njit(inline="always", **_JIT)
def _rot_t(R: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    # Rᵀ times a vector
    return (R[0] * x + R[3] * y + R[6] * z, R[1] * x + R[4] * y + R[7] * z,
            R[2] * x + R[5] * y + R[8] * z)


@njit(inline="always", **_JIT)
def _mul9(A: np.ndarray, P: np.ndarray) -> tuple[float, float, float, float, float, float,
                                                 float, float, float]:
    # A · (rotation part of P), both row-major, as 9 values
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A[0], A[1], A[2], A[3], A[4], A[5], A[6], A[7], A[8]
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = P[0], P[1], P[2], P[3], P[4], P[5], P[6], P[7], P[8]
    return (a0 * p0 + a1 * p3 + a2 * p6, a0 * p1 + a1 * p4 + a2 * p7, a0 * p2 + a1 * p5 + a2 * p8,
            a3 * p0 + a4 * p3 + a5 * p6, a3 * p1 + a4 * p4 + a5 * p7, a3 * p2 + a4 * p5 + a5 * p8,
            a6 * p0 + a7 * p3 + a8 * p6, a6 * p1 + a7 * p4 + a8 * p7, a6 * p2 + a7 * p5 + a8 * p8)


@njit(inline="always", **_JIT)   # inlined: one call per joint and state
def joint_step(Rw: np.ndarray, pw: np.ndarray, z: np.ndarray, parent: np.ndarray,
               placement: np.ndarray, axis: np.ndarray, revolute: np.ndarray, i: int,
               q: float) -> tuple[float, float, float, float, float, float]:
    """Joint i at coordinate q from its parent's pose: writes its world rotation (Rw[i]), origin
    (pw[i]) and axis (z[i]) and returns the origin and the axis. Shared by the frame and the
    observer kernels."""
    a, P = parent[i], placement[i]
    Ra = Rw[a]
    # B = R_parent · R_placement in locals (arrays here could alias: no registers)
    b00, b01, b02, b10, b11, b12, b20, b21, b22 = _mul9(Ra, P)
    tx, ty, tz = _rot(Ra, P[9], P[10], P[11])
    px, py, pz = pw[a, 0] + tx, pw[a, 1] + ty, pw[a, 2] + tz
    ux, uy, uz = axis[i, 0], axis[i, 1], axis[i, 2]
    zx = b00 * ux + b01 * uy + b02 * uz
    zy = b10 * ux + b11 * uy + b12 * uz
    zz = b20 * ux + b21 * uy + b22 * uz
    px, py, pz = joint_frame(Rw[i], b00, b01, b02, b10, b11, b12, b20, b21, b22, ux, uy, uz,
                             zx, zy, zz, q, revolute[i], px, py, pz)
    pw[i, 0], pw[i, 1], pw[i, 2] = px, py, pz
    z[i, 0], z[i, 1], z[i, 2] = zx, zy, zz
    return px, py, pz, zx, zy, zz


@njit(inline="always", **_JIT)
def _world_inertia(R: np.ndarray, I6: np.ndarray, out: np.ndarray) -> None:
    """out (6: xx, xy, xz, yy, yz, zz) = R·I·Rᵀ for a symmetric I given the same way."""
    a, b, c, d, e, f = I6[0], I6[1], I6[2], I6[3], I6[4], I6[5]
    t = 0
    for r in range(3):
        # row r of R·I
        x = R[3 * r] * a + R[3 * r + 1] * b + R[3 * r + 2] * c
        y = R[3 * r] * b + R[3 * r + 1] * d + R[3 * r + 2] * e
        z = R[3 * r] * c + R[3 * r + 1] * e + R[3 * r + 2] * f
        for s in range(r, 3):
            out[t] = x * R[3 * s] + y * R[3 * s + 1] + z * R[3 * s + 2]
            t += 1


@njit(inline="always", **_JIT)
def _sym_mul(S: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    # symmetric 3×3 (xx, xy, xz, yy, yz, zz) times a vector
    return (S[0] * x + S[1] * y + S[2] * z, S[1] * x + S[3] * y + S[4] * z,
            S[2] * x + S[4] * y + S[5] * z)


@njit(inline="always", **_JIT)
def _cholesky(Mk: np.ndarray, L: np.ndarray, inv: np.ndarray) -> bool:
    """Lower factor L of Mk = L·Lᵀ, the reciprocals of its diagonal in ``inv``; False when a
    pivot is not positive (M not positive definite: a massless chain)."""
    n = Mk.shape[0]
    for i in range(n):
        for j in range(i):
            s = Mk[i, j]
            for p in range(j):
                s -= L[i, p] * L[j, p]
            L[i, j] = s * inv[j]
        s = Mk[i, i]
        for p in range(i):
            s -= L[i, p] * L[i, p]
        if not s > 0:
            return False
        inv[i] = 1.0 / math.sqrt(s)
    return True


@njit(inline="always", **_JIT)
def _crba(parent: np.ndarray, revolute: np.ndarray, index: np.ndarray, pw: np.ndarray,
          z: np.ndarray, cm: np.ndarray, ch: np.ndarray, cJ: np.ndarray, armature: np.ndarray,
          sv: np.ndarray, g0: float, g1: float, g2: float, Mk: np.ndarray,
          gq: np.ndarray) -> None:
    """M(q) into Mk from the bodies' mass, first moment and inertia about the world origin
    (cm, ch, cJ, overwritten by the subtree sums): M[j, i] = S_j·(I_i^c S_i) for j = i and its
    ancestors, S the joint's motion in world axes at the origin ([p × z; z] revolute, [z; 0]
    prismatic: its linear part goes to the scratch ``sv``), I_i^c the subtree's spatial
    inertia. The same subtree sums give the generalized gravity g(q) = −S_iᵀ I_i^c [g; 0]
    into gq: −z·((h − m·p) × g) revolute, −m·z·g prismatic."""
    n = len(parent)
    Mk[:, :] = 0.0     # joints on different branches: never written below
    for i in range(1, n):
        zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
        if revolute[i]:
            sv[i, 0], sv[i, 1], sv[i, 2] = _cross(pw[i, 0], pw[i, 1], pw[i, 2], zx, zy, zz)
        else:
            sv[i, 0], sv[i, 1], sv[i, 2] = zx, zy, zz
    for i in range(n - 1, 0, -1):
        svx, svy, svz = sv[i, 0], sv[i, 1], sv[i, 2]
        # momentum of the subtree moving with S_i: f = m·v + ω × h, n = h × v + J·ω
        hx, hy, hz = ch[i, 0], ch[i, 1], ch[i, 2]
        mi = cm[i]
        bx, by, bz = _cross(hx, hy, hz, svx, svy, svz)
        if revolute[i]:
            zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
            ax, ay, az = _cross(zx, zy, zz, hx, hy, hz)
            fx, fy, fz = mi * svx + ax, mi * svy + ay, mi * svz + az
            jx, jy, jz = _sym_mul(cJ[i], zx, zy, zz)
            nx, ny, nz = bx + jx, by + jy, bz + jz
        else:
            fx, fy, fz = mi * svx, mi * svy, mi * svz
            nx, ny, nz = bx, by, bz
        c = index[i]
        e = svx * fx + svy * fy + svz * fz
        if revolute[i]:
            e += zx * nx + zy * ny + zz * nz
            rx, ry, rz = hx - mi * pw[i, 0], hy - mi * pw[i, 1], hz - mi * pw[i, 2]
            tx, ty, tz = _cross(rx, ry, rz, g0, g1, g2)
            gq[c] = -(zx * tx + zy * ty + zz * tz)
        else:
            gq[c] = -mi * (svx * g0 + svy * g1 + svz * g2)
        Mk[c, c] = e + armature[c]
        j = parent[i]
        while j > 0:
            e = sv[j, 0] * fx + sv[j, 1] * fy + sv[j, 2] * fz
            if revolute[j]:
                e += z[j, 0] * nx + z[j, 1] * ny + z[j, 2] * nz
            d = index[j]
            Mk[d, c] = e
            Mk[c, d] = e
            j = parent[j]
        a = parent[i]
        if a > 0:
            cm[a] += mi
            for r in range(3):
                ch[a, r] += ch[i, r]
            for r in range(6):
                cJ[a, r] += cJ[i, r]


@njit(inline="always", **_JIT)
def _effective_mass(L: np.ndarray, inv: np.ndarray, b: np.ndarray, y: np.ndarray,
                    speed: float, positive: bool) -> float:
    """1/(bᵀM⁻¹b) = 1/|L⁻¹b|² (b = J_vᵀu, M = LLᵀ, inv: 1/diag L) by forward substitution
    (y: scratch); 0 for a still point, NaN for a factor that failed."""
    if not speed > 0:
        return 0.0
    if not positive:
        return np.nan
    nv = len(b)
    s = 0.0
    for r in range(nv):
        t = b[r]
        for p in range(r):
            t -= L[r, p] * y[p]
        y[r] = t * inv[r]
        s += y[r] * y[r]
    return 1.0 / s


@njit(inline="always", **_JIT)
def _couple(L: np.ndarray, inv: np.ndarray, Jc: np.ndarray, Yf: np.ndarray, positive: bool,
            out: np.ndarray, lam: np.ndarray, fmass: np.ndarray) -> None:
    """Y = L⁻¹·J_cᵀ in place of Jc (forward substitution per column), lam = YᵀY (6) and
    out[f] = Yᵀ·Yf[f] (F×3) for the frames with ``fmass``; NaN for a factor that failed."""
    nv = Jc.shape[0]
    if not positive:
        out[:, :] = np.nan
        lam[:] = np.nan
        return
    for a in range(3):
        for r in range(nv):
            t = Jc[r, a]
            for p in range(r):
                t -= L[r, p] * Jc[p, a]
            Jc[r, a] = t * inv[r]
    t = 0
    for a in range(3):
        for b in range(a, 3):
            s = 0.0
            for r in range(nv):
                s += Jc[r, a] * Jc[r, b]
            lam[t] = s
            t += 1
    for f in range(Yf.shape[0]):
        if not fmass[f]:
            continue
        for a in range(3):
            s = 0.0
            for r in range(nv):
                s += Jc[r, a] * Yf[f, r]
            out[f, a] = s


@njit(inline="always", **_JIT)
def _base(root: np.ndarray, Mt: float, Sx: float, Sy: float, Sz: float, g0: float, g1: float,
          g2: float, fx: float, fy: float, fz: float, nx: float, ny: float, nz: float,
          ws: np.ndarray, wd: np.ndarray, com: np.ndarray) -> None:
    """The mounting's wrench on the robot, at the base frame's origin in its axes: static
    −(M·g; S × g) (S = Σ m·c), dynamic (f; n) the momentum rate, both about the world origin
    before the move; and the centre of mass S/M."""
    R = root[:9]
    rx, ry, rz = root[9], root[10], root[11]
    sfx, sfy, sfz = -Mt * g0, -Mt * g1, -Mt * g2
    snx, sny, snz = _cross(Sx, Sy, Sz, g0, g1, g2)
    # moment about the root origin r: n_O − r × f
    ax, ay, az = _cross(rx, ry, rz, sfx, sfy, sfz)
    ws[0], ws[1], ws[2] = _rot_t(R, sfx, sfy, sfz)
    ws[3], ws[4], ws[5] = _rot_t(R, -snx - ax, -sny - ay, -snz - az)
    bx, by, bz = _cross(rx, ry, rz, fx, fy, fz)
    wd[0], wd[1], wd[2] = _rot_t(R, fx, fy, fz)
    wd[3], wd[4], wd[5] = _rot_t(R, nx - bx, ny - by, nz - bz)
    if Mt > 0:
        com[0], com[1], com[2] = _rot_t(R, Sx / Mt - rx, Sy / Mt - ry, Sz / Mt - rz)
    else:
        com[0] = com[1] = com[2] = np.nan


@njit(inline="always", **_JIT)
def _rnea_backward(parent: np.ndarray, revolute: np.ndarray, index: np.ndarray, pw: np.ndarray,
                   z: np.ndarray, armature: np.ndarray, a: np.ndarray, bm: np.ndarray,
                   bg: np.ndarray, tau: np.ndarray, g: np.ndarray) -> None:
    """RNEA's backward pass in world axes at the world origin: each joint carries its
    subtree's momentum rate minus its weight (bm, bg: per body, [force; moment], overwritten by
    the subtree sums); τ = S·(ḣ − w) + armature·a, g = −S·w, with S·(f; n) = z·(n − p × f)
    revolute, z·f prismatic."""
    for i in range(len(parent) - 1, 0, -1):
        c = index[i]
        zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
        fx, fy, fz = bm[i, 0] - bg[i, 0], bm[i, 1] - bg[i, 1], bm[i, 2] - bg[i, 2]
        wx, wy, wz = bg[i, 0], bg[i, 1], bg[i, 2]
        if revolute[i]:
            px, py, pz = pw[i, 0], pw[i, 1], pw[i, 2]
            tx, ty, tz = _cross(px, py, pz, fx, fy, fz)
            tau[c] = (zx * (bm[i, 3] - bg[i, 3] - tx) + zy * (bm[i, 4] - bg[i, 4] - ty)
                      + zz * (bm[i, 5] - bg[i, 5] - tz)) + armature[c] * a[c]
            ux, uy, uz = _cross(px, py, pz, wx, wy, wz)
            g[c] = -(zx * (bg[i, 3] - ux) + zy * (bg[i, 4] - uy) + zz * (bg[i, 5] - uz))
        else:
            tau[c] = (zx * fx + zy * fy + zz * fz) + armature[c] * a[c]
            g[c] = -(zx * wx + zy * wy + zz * wz)
        j = parent[i]
        if j > 0:
            for r in range(6):
                bm[j, r] += bm[i, r]
                bg[j, r] += bg[i, r]


@njit(inline="always", **_JIT)
def _joint_motion(Rw: np.ndarray, pw: np.ndarray, z: np.ndarray, w: np.ndarray, al: np.ndarray,
                  vo: np.ndarray, ao: np.ndarray, parent: np.ndarray, placement: np.ndarray,
                  axis: np.ndarray, revolute: np.ndarray, i: int, q: float, qd: float,
                  qdd: float) -> tuple[float, float, float, float, float, float]:
    """Joint i's pose (:func:`joint_step`), then its frame's ω, α (w[i], al[i]) and its origin's
    velocity and classical acceleration (vo[i], ao[i]) from the parent's; returns the origin
    and that acceleration."""
    a = parent[i]
    px, py, pz, zx, zy, zz = joint_step(Rw, pw, z, parent, placement, axis, revolute, i, q)
    # motion of the joint origin from the parent's: r = p_i − p_a moves rigidly with the
    # parent, plus the prismatic stroke along z
    wax, way, waz = w[a, 0], w[a, 1], w[a, 2]
    vx, vy, vz, ax_, ay_, az_ = _carried(w, al, vo, ao, a, px - pw[a, 0], py - pw[a, 1],
                                         pz - pw[a, 2])
    hx, hy, hz = _cross(wax, way, waz, zx, zy, zz)
    if revolute[i]:
        w[i, 0], w[i, 1], w[i, 2] = wax + zx * qd, way + zy * qd, waz + zz * qd
        al[i, 0] = al[a, 0] + zx * qdd + hx * qd
        al[i, 1] = al[a, 1] + zy * qdd + hy * qd
        al[i, 2] = al[a, 2] + zz * qdd + hz * qd
    else:
        w[i, 0], w[i, 1], w[i, 2] = wax, way, waz
        al[i, 0], al[i, 1], al[i, 2] = al[a, 0], al[a, 1], al[a, 2]
        vx, vy, vz = vx + zx * qd, vy + zy * qd, vz + zz * qd
        ax_ += zx * qdd + 2 * hx * qd
        ay_ += zy * qdd + 2 * hy * qd
        az_ += zz * qdd + 2 * hz * qd
    vo[i, 0], vo[i, 1], vo[i, 2] = vx, vy, vz
    ao[i, 0], ao[i, 1], ao[i, 2] = ax_, ay_, az_
    return px, py, pz, ax_, ay_, az_


@njit(inline="always", **_JIT)
def _momentum_rate(w: np.ndarray, al: np.ndarray, i: int, m: float, lx: float, ly: float,
                   lz: float, cwx: float, cwy: float, cwz: float, Icw: np.ndarray, ax_: float,
                   ay_: float, az_: float) -> tuple[float, float, float, float, float, float,
                                                    float, float, float, float, float, float]:
    """Body i's momentum rate about the world origin: m·a_c (3), and the three parts of its
    moment c × m·a_c, I·α and ω × I·ω (3 each, summed by the caller in that order)."""
    wix, wiy, wiz = w[i, 0], w[i, 1], w[i, 2]
    t1x, t1y, t1z = _cross(al[i, 0], al[i, 1], al[i, 2], lx, ly, lz)
    t2x, t2y, t2z = _cross(wix, wiy, wiz, lx, ly, lz)
    t3x, t3y, t3z = _cross(wix, wiy, wiz, t2x, t2y, t2z)
    mx = m * (ax_ + t1x + t3x)
    my = m * (ay_ + t1y + t3y)
    mz = m * (az_ + t1z + t3z)
    kx, ky, kz = _cross(cwx, cwy, cwz, mx, my, mz)
    ix, iy, iz = _sym_mul(Icw, al[i, 0], al[i, 1], al[i, 2])
    jx, jy, jz = _sym_mul(Icw, wix, wiy, wiz)
    ox, oy, oz = _cross(wix, wiy, wiz, jx, jy, jz)
    return mx, my, mz, kx, ky, kz, ix, iy, iz, ox, oy, oz


@njit(inline="always", **_JIT)
def _body_rates(bm: np.ndarray, bg: np.ndarray, i: int, m: float, g0: float, g1: float,
                g2: float, cwx: float, cwy: float, cwz: float, mx: float, my: float, mz: float,
                nx: float, ny: float, nz: float) -> None:
    """Body i's momentum rate (m, n) and weight with its moment into bm[i] and bg[i]."""
    bm[i, 0], bm[i, 1], bm[i, 2] = mx, my, mz
    bm[i, 3], bm[i, 4], bm[i, 5] = nx, ny, nz
    gfx, gfy, gfz = m * g0, m * g1, m * g2
    bg[i, 0], bg[i, 1], bg[i, 2] = gfx, gfy, gfz
    bg[i, 3], bg[i, 4], bg[i, 5] = _cross(cwx, cwy, cwz, gfx, gfy, gfz)


@njit(inline="always", **_JIT)
def _composite(cm: np.ndarray, ch: np.ndarray, cJ: np.ndarray, Icw: np.ndarray, i: int,
               m: float, cwx: float, cwy: float, cwz: float) -> None:
    """Body i's mass, first moment and inertia about the world origin (CRBA's leaves)."""
    cm[i] = m
    ch[i, 0], ch[i, 1], ch[i, 2] = m * cwx, m * cwy, m * cwz
    c2 = cwx * cwx + cwy * cwy + cwz * cwz
    cJ[i, 0] = Icw[0] + m * (c2 - cwx * cwx)
    cJ[i, 1] = Icw[1] - m * cwx * cwy
    cJ[i, 2] = Icw[2] - m * cwx * cwz
    cJ[i, 3] = Icw[3] + m * (c2 - cwy * cwy)
    cJ[i, 4] = Icw[4] - m * cwy * cwz
    cJ[i, 5] = Icw[5] + m * (c2 - cwz * cwz)


@njit(inline="always", **_JIT)
def _kinetic(Mk: np.ndarray, V: np.ndarray, k: int) -> float:
    """½·q̇ᵀMq̇ of state k."""
    nv = Mk.shape[0]
    e = 0.0
    for r in range(nv):
        t = 0.0
        for s in range(nv):
            t += Mk[r, s] * V[k, s]
        e += V[k, r] * t
    return 0.5 * e


@njit(inline="always", **_JIT)
def _frame_motion(Rw: np.ndarray, pw: np.ndarray, w: np.ndarray, al: np.ndarray,
                  vo: np.ndarray, ao: np.ndarray, j: int, fplace: np.ndarray,
                  fpoint: np.ndarray, f: int, k: int, Rf: np.ndarray, rot: np.ndarray,
                  pos: np.ndarray, vel: np.ndarray, omega: np.ndarray, acc: np.ndarray,
                  alpha: np.ndarray) -> tuple[tuple[float, float, float],
                                              tuple[float, float, float],
                                              tuple[float, float, float]]:
    """Frame f (on joint j) at state k: its rotation (into Rf and rot[f, k], 9), its point's
    position, velocity and classical acceleration and the frame's ω and α (3 each, [f, k]);
    returns the frame origin, the point and its velocity."""
    Rj, P = Rw[j], fplace[f]
    Rf[0], Rf[1], Rf[2], Rf[3], Rf[4], Rf[5], Rf[6], Rf[7], Rf[8] = _mul9(Rj, P)
    for r in range(9):
        rot[f, k, r] = Rf[r]
    tx, ty, tz = _rot(Rj, P[9], P[10], P[11])
    ox, oy, oz = pw[j, 0] + tx, pw[j, 1] + ty, pw[j, 2] + tz
    qx, qy, qz = _rot(Rf, fpoint[f, 0], fpoint[f, 1], fpoint[f, 2])
    px, py, pz = ox + qx, oy + qy, oz + qz
    vx, vy, vz, ax_, ay_, az_ = _carried(w, al, vo, ao, j, px - pw[j, 0], py - pw[j, 1],
                                         pz - pw[j, 2])
    pos[f, k, 0], pos[f, k, 1], pos[f, k, 2] = px, py, pz
    vel[f, k, 0], vel[f, k, 1], vel[f, k, 2] = vx, vy, vz
    omega[f, k, 0], omega[f, k, 1], omega[f, k, 2] = w[j, 0], w[j, 1], w[j, 2]
    acc[f, k, 0], acc[f, k, 1], acc[f, k, 2] = ax_, ay_, az_
    alpha[f, k, 0], alpha[f, k, 1], alpha[f, k, 2] = al[j, 0], al[j, 1], al[j, 2]
    return (ox, oy, oz), (px, py, pz), (vx, vy, vz)


@njit(inline="always", **_JIT)
def linear_column(z: np.ndarray, pw: np.ndarray, revolute: np.ndarray, i: int, px: float,
                  py: float, pz: float) -> tuple[float, float, float]:
    """Joint i's column of the linear Jacobian of the world point p: z × (p − p_i) revolute, z
    prismatic (world axes). Shared by the frame and the observer kernels."""
    zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
    if revolute[i]:
        return _cross(zx, zy, zz, px - pw[i, 0], py - pw[i, 1], pz - pw[i, 2])
    return zx, zy, zz


@njit(inline="always", **_JIT)
def _frame_jacobian(parent: np.ndarray, revolute: np.ndarray, index: np.ndarray,
                    pw: np.ndarray, z: np.ndarray, j: int, f: int, k: int, Rf: np.ndarray,
                    fwrench: np.ndarray, o: tuple[float, float, float],
                    p: tuple[float, float, float], v: tuple[float, float, float],
                    acc: np.ndarray, gravity: np.ndarray, tau: np.ndarray, t: int,
                    b: np.ndarray, Jc: np.ndarray, unit: np.ndarray, couples: bool,
                    unitmass: bool) -> float:
    """Down the chain from frame f's joint j at state k, per joint column c: the task torque
    J_localᵀ·W (tau[t, k, c] where t ≥ 0; W = ``fwrench[f]`` at the frame origin o), J_vᵀu at
    the point p with u = v/|v| (b[c]; 0 for a still point), J_v's column (Jc[c], ``couples``)
    and J_vᵀ(a − g) (unit[k, c], ``unitmass``); zero off the chain. Returns |v|."""
    vx, vy, vz = v
    gx, gy, gz = acc[f, k, 0] - gravity[0], acc[f, k, 1] - gravity[1], acc[f, k, 2] - gravity[2]
    Fx, Fy, Fz = _rot(Rf, fwrench[f, 0], fwrench[f, 1], fwrench[f, 2])
    Tx, Ty, Tz = _rot(Rf, fwrench[f, 3], fwrench[f, 4], fwrench[f, 5])
    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
    uxx, uyy, uzz = (vx / speed, vy / speed, vz / speed) if speed > 0 else (0.0, 0.0, 0.0)
    for c in range(len(b)):
        if t >= 0:
            tau[t, k, c] = 0.0
        b[c] = 0.0
        if couples:
            Jc[c, 0] = Jc[c, 1] = Jc[c, 2] = 0.0
        if unitmass:
            unit[k, c] = 0.0
    i = j
    while i > 0:
        c = index[i]
        zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
        if t >= 0:
            # J column: [z × (o − p_i); z] (revolute), [z; 0]: its product with the world wrench
            if revolute[i]:
                mx, my, mz = _cross(o[0] - pw[i, 0], o[1] - pw[i, 1], o[2] - pw[i, 2],
                                    Fx, Fy, Fz)
                tau[t, k, c] = zx * (mx + Tx) + zy * (my + Ty) + zz * (mz + Tz)
            else:
                tau[t, k, c] = zx * Fx + zy * Fy + zz * Fz
        jx, jy, jz = linear_column(z, pw, revolute, i, p[0], p[1], p[2])
        b[c] = jx * uxx + jy * uyy + jz * uzz
        if couples:
            Jc[c, 0], Jc[c, 1], Jc[c, 2] = jx, jy, jz
        if unitmass:
            unit[k, c] = jx * gx + jy * gy + jz * gz
        i = parent[i]
    return speed


# One compiled pass per state over the joint tree: the helpers above are called per state,
# joint and frame with scalars in and out (no arrays made), so the pass stays one loop.
@njit([types.void(_M, _M, _M, _I, _B, _I, _M, _M, _M, _V, _V, _V, _I, _M, _M, _M, _B, _I,
                  types.int64, types.int64, types.boolean, types.boolean, _C3, _C3, _C3, _C3,
                  _C3, _C3, _C3, _C2, _C3, _C2, _C3, _C1, _C2, _C2, _C2, _C2, _A2, _C2,
                  _C2)], **_JIT)
def frame_rows(Q: _A, V: _A, A: _A, parent: _A, revolute: _A, index: _A, placement: _A, axis: _A,
               inertia: _A, armature: _A, gravity: _A, root: _A, fjoint: _A, fplace: _A,
               fpoint: _A, fwrench: _A, fmass: _A, ftau: _A, fcouple: int, funit: int,
               with_inertia: bool, with_base: bool, pos: _A, vel: _A, omega: _A, acc: _A,
               alpha: _A, rot: _A, tau: _A, mu: _A, couple: _A, couple_inertia: _A, Mout: _A,
               ke: _A, gq: _A, wstatic: _A, wdynamic: _A, com: _A, unit: _A, rnea: _A,
               grav: _A) -> None:
    """Per state k of Q, V, A (N×nv) and frame f, what the module docstring lists."""
    n, F = len(parent), len(fjoint)
    N, nv = Q.shape
    Rw, pw, z, w = np.zeros((n, 9)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    vo, al, ao = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    # CRBA's subtree sums; M (when Mout is not asked for), its factor; L⁻¹·J_vᵀu; J_cᵀ
    cm, ch, cJ, Icw, Rf = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 6)), np.zeros(6), np.zeros(9)
    L, Ms, sv = np.zeros((nv, nv)), np.zeros((nv, nv)), np.zeros((n, 3))
    b, y, inv = np.zeros(nv), np.zeros(nv), np.zeros(nv)
    Yf, Jc = np.zeros((F, nv)), np.zeros((nv, 3))
    bm, bg = np.zeros((n, 6)), np.zeros((n, 6))    # each body's momentum rate and weight
    coupled = with_inertia and fcouple >= 0
    # M's factor only for the effective masses (the kinetic energy needs M alone)
    factor = with_inertia and (coupled or np.any(fmass))
    positive, with_rnea, momentum = False, len(rnea) > 0, with_base or len(rnea) > 0
    Rw[0, 0] = Rw[0, 4] = Rw[0, 8] = 1.0
    g0, g1, g2 = gravity[0], gravity[1], gravity[2]
    m0 = inertia[0, 0]     # bodies fixed to the world: in the static sums only (never moving)
    s0x, s0y, s0z = m0 * inertia[0, 1], m0 * inertia[0, 2], m0 * inertia[0, 3]
    for k in range(N):
        Mt, Sx, Sy, Sz, fx, fy, fz, nx, ny, nz = m0, s0x, s0y, s0z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for i in range(1, n):
            c = index[i]
            px, py, pz, ax_, ay_, az_ = _joint_motion(Rw, pw, z, w, al, vo, ao, parent,
                                                      placement, axis, revolute, i, Q[k, c],
                                                      V[k, c], A[k, c])
            if not (with_inertia or momentum):
                continue
            R, m = Rw[i], inertia[i, 0]
            lx, ly, lz = _rot(R, inertia[i, 1], inertia[i, 2], inertia[i, 3])
            cwx, cwy, cwz = px + lx, py + ly, pz + lz
            _world_inertia(R, inertia[i, 4:], Icw)
            if momentum:
                Mt += m
                Sx, Sy, Sz = Sx + m * cwx, Sy + m * cwy, Sz + m * cwz
                mx, my, mz, kx, ky, kz, ix, iy, iz, ox, oy, oz = _momentum_rate(
                    w, al, i, m, lx, ly, lz, cwx, cwy, cwz, Icw, ax_, ay_, az_)
                fx, fy, fz = fx + mx, fy + my, fz + mz
                nx, ny, nz = nx + kx + ix + ox, ny + ky + iy + oy, nz + kz + iz + oz
                if with_rnea:
                    _body_rates(bm, bg, i, m, g0, g1, g2, cwx, cwy, cwz, mx, my, mz,
                                kx + ix + ox, ky + iy + oy, kz + iz + oz)
            if with_inertia:
                _composite(cm, ch, cJ, Icw, i, m, cwx, cwy, cwz)
        if with_inertia:
            Mk = Mout[k] if len(Mout) else Ms
            _crba(parent, revolute, index, pw, z, cm, ch, cJ, armature, sv, g0, g1, g2, Mk,
                  gq[k])
            ke[k] = _kinetic(Mk, V, k)
            if factor:
                positive = _cholesky(Mk, L, inv)
        if with_rnea:
            _rnea_backward(parent, revolute, index, pw, z, armature, A[k], bm, bg, rnea[k], grav[k])
        if with_base:
            _base(root, Mt, Sx, Sy, Sz, g0, g1, g2, fx, fy, fz, nx, ny, nz, wstatic[k],
                  wdynamic[k], com[k])
        for f in range(F):
            j, t = fjoint[f], ftau[f]
            o, p, v = _frame_motion(Rw, pw, w, al, vo, ao, j, fplace, fpoint, f, k, Rf, rot, pos,
                                    vel, omega, acc, alpha)
            # the Jacobian walk only where a torque, effective mass or coupling is wanted
            massed, couples = with_inertia and fmass[f], coupled and f == fcouple
            unitmass = f == funit and len(unit) > 0
            if not (t >= 0 or massed or couples or unitmass):
                continue
            speed = _frame_jacobian(parent, revolute, index, pw, z, j, f, k, Rf, fwrench, o, p,
                                    v, acc, gravity, tau, t, b, Jc, unit, couples, unitmass)
            if massed:
                mu[f, k] = _effective_mass(L, inv, b, y, speed, positive)
                for c in range(nv):
                    Yf[f, c] = y[c] if speed > 0 else 0.0
        if coupled:
            _couple(L, inv, Jc, Yf, positive, couple[:, k], couple_inertia[k], fmass)
