"""The contact monitor's per-sample arithmetic, compiled (Numba, no rclpy): the momentum
observer's model terms and recursion, the damped least-squares wrench at the contact frame, the
detector's threshold tests and the power balance's running sums, for N joint states in one call.

Why our own code: the live node calls it with one row per joint_states and the audit with
thousands; the per-row arithmetic is the same compiled code, so a replay gives the node's bits.
Written with Pinocchio and NumPy calls it cost ~65 µs a sample (docs/OBSERVER.md); numba's
``np.linalg.svd`` needs SciPy (0.4 s more at every import) and costs 14.5 µs for a 6×7 matrix,
so the wrench uses a cyclic Jacobi eigensolver on the 6×6 (or nv×nv) Gram matrix instead.

Model terms, per joint i with world axis z through p (revolute) or along z (prismatic), ω_i and
v_i the angular velocity and the velocity of p of body i, H_i = (L, P) the momentum of the
subtree from body i about the world origin:

* p_i = z·(L − p×P) (revolute), z·P (prismatic), + armature·q̇: the generalized momentum M(q)q̇;
* (Cᵀq̇)_i = (ω_i×z)·(L − p×P) + (v_i×z)·P (revolute), (ω_i×z)·P (prismatic): from
  ṗ = Mq̈ + Ṁq̇ with Ṁ = C + Cᵀ, p_i = S_i·H_i and Ṡ_i = v_i×S_i, so Cᵀq̇ = Ṁq̇ − Cq̇ = (v_i×S_i)·H_i;
* g_i from the subtree's mass and first moment, as :func:`dyn_node.core.compiled.rigid_kernels.gravity_rows`.

:func:`observer_rows`: N joint states (rows of Q, V, E in model order; T stamps in s) through the momentum
observer, the contact wrench, the contact-level test and the power balance.

``valid[k]``: the row has velocity and effort, all finite, and a finite stamp (else
NO_ESTIMATE: the history is dropped and the power period restarted); ``reset[k]``: a restart
was asked before row k (the observer restarts at the next valid row, the power period
restarts). Observer: r exact over each step for the lag ṙ = K(τ_ext − r), the model terms
trapezoidal, the effort held (``held``) or trapezoidal; restarts on a step back
(BACKWARDS) or longer than ``max_gap`` (STAMP_GAP); a repeated stamp gives the estimate
again without integrating (SAME_INSTANT). ``wopt`` = (ε, β, λ_max) of the wrench,
``contact_at`` the detector's contact level per joint (N·m|N). State carried between
calls: ``state`` (4×nv: r, p, s, e), ``clock`` (C_*), ``power`` (P_*).

Out per row: ``TAU`` τ̂_ext (NaN without estimate), ``W`` the wrench at the frame (its
axes, [force; moment]), ``info`` (I_*: since the restart, σ_min, λ, misfit, ‖force‖, dt,
some joint over its contact level (1.0/0.0), the power balance's step (what
:func:`power_step` returned; −1 without estimate), the observer's history dropped here
(1.0)), ``code`` (ESTIMATE …).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.frame_kernels import _mul9, _rot, joint_step, linear_column
from dyn_node.core.compiled.jit import _B, _I, _JIT, _M, _V, _f8

_C1 = types.Array(_f8, 1, "C")
_C2 = types.Array(_f8, 2, "C")
_IC = types.Array(types.int64, 1, "C")

#: row codes (``code`` output)
ESTIMATE, RESTART, BACKWARDS, STAMP_GAP, SAME_INSTANT, NO_ESTIMATE, RESTART_AFTER_INVALID = range(7)
#: columns of ``info``
(I_SINCE, I_SIGMA, I_DAMPING, I_MISFIT, I_FORCE, I_DT, I_OVER, I_POWER_STEP,
 I_DROPPED) = range(9)
INFO_COLUMNS = 9
#: the observer's clock state (``clock``): last stamp, restart stamp, history kept (1.0),
#: a sample without estimate since the history was dropped (1.0)
C_T, C_T0, C_HAS, C_AFTER_INVALID = range(4)
#: the power balance's state (``power``): last stamp, its power, |power| and friction power,
#: the period's work, gross work and friction work, samples, periods broken (cumulative)
P_T, P_POW, P_APOW, P_FPOW, P_WORK, P_GROSS, P_FRICTION, P_N, P_BROKEN = range(9)
STATE_ROWS = 4   # r, p, s (Cᵀq̇ − g − friction), e: the observer's last sample


@njit(**_JIT)
def _jacobi_eigh(G: np.ndarray, U: np.ndarray, lam: np.ndarray) -> None:
    """Eigenvalues (lam) and eigenvectors (U's columns) of the symmetric k×k G (destroyed):
    cyclic Jacobi rotations until the off-diagonal part is below rounding."""
    k = G.shape[0]
    for i in range(k):
        for j in range(k):
            U[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(60):
        off = 0.0
        diag = 0.0
        for i in range(k):
            diag += G[i, i] * G[i, i]
            for j in range(i + 1, k):
                off += G[i, j] * G[i, j]
        if off <= 1e-34 * diag or off == 0.0:
            break
        for p in range(k - 1):
            for q in range(p + 1, k):
                apq = G[p, q]
                if apq == 0.0:
                    continue
                theta = (G[q, q] - G[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(k):  # G ← G·Rot
                    grp, grq = G[r, p], G[r, q]
                    G[r, p] = c * grp - s * grq
                    G[r, q] = s * grp + c * grq
                for r in range(k):  # G ← Rotᵀ·G
                    gpr, gqr = G[p, r], G[q, r]
                    G[p, r] = c * gpr - s * gqr
                    G[q, r] = s * gpr + c * gqr
                G[p, q] = G[q, p] = 0.0
                for r in range(k):
                    urp, urq = U[r, p], U[r, q]
                    U[r, p] = c * urp - s * urq
                    U[r, q] = s * urp + c * urq
    for i in range(k):
        lam[i] = G[i, i]


@njit(**_JIT)
def damped_solve(J: np.ndarray, tau: np.ndarray, eps: float, band: float, lam_max: float,
                 G: np.ndarray, U: np.ndarray, ev: np.ndarray, y: np.ndarray,
                 F: np.ndarray) -> tuple[float, float, float]:
    """F = argmin ‖JᵀF − τ‖² + λ²‖F‖² for the 6×nv J into F (6), by the eigenvectors of the
    smaller Gram matrix (JJᵀ, or JᵀJ when nv < 6); λ² = (1 − (σ_min/β)²)·λ_max² below the band
    β, 0 above. Returns (σ_min, λ, ‖JᵀF − τ‖). G, U (k×k), ev, y (k) are scratch."""
    nv = J.shape[1]
    k = G.shape[0]
    wide = nv >= 6
    for i in range(k):
        for j in range(k):
            s = 0.0
            if wide:
                for c in range(nv):
                    s += J[i, c] * J[j, c]
            else:
                for r in range(6):
                    s += J[r, i] * J[r, j]
            G[i, j] = s
    _jacobi_eigh(G, U, ev)
    smin2 = ev[0]
    for i in range(1, k):
        if ev[i] < smin2:
            smin2 = ev[i]
    sigma = math.sqrt(smin2) if smin2 > 0 else 0.0
    lam2 = 0.0 if sigma >= band else (1.0 - (sigma / band) ** 2) * lam_max * lam_max
    # coordinates of the right-hand side on U: Uᵀ·J·τ (wide) or Uᵀ·τ (narrow)
    for i in range(k):
        s = 0.0
        if wide:
            for r in range(6):
                jt = 0.0
                for c in range(nv):
                    jt += J[r, c] * tau[c]
                s += U[r, i] * jt
        else:
            for c in range(nv):
                s += U[c, i] * tau[c]
        e = ev[i] if ev[i] > 0 else 0.0
        y[i] = s / (e + lam2)
    for r in range(6):
        s = 0.0
        if wide:
            for i in range(k):
                s += U[r, i] * y[i]
        else:
            for c in range(nv):
                u = 0.0
                for i in range(k):
                    u += U[c, i] * y[i]
                s += J[r, c] * u
        F[r] = s
    m = 0.0
    for c in range(nv):
        s = -tau[c]
        for r in range(6):
            s += J[r, c] * F[r]
        m += s * s
    return sigma, math.sqrt(lam2), math.sqrt(m)


@njit(inline="always", **_JIT)
def _cross(ax: float, ay: float, az: float, bx: float, by: float,
           bz: float) -> tuple[float, float, float]:
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(inline="always", **_JIT)
def _body_momentum(R: np.ndarray, inertia: np.ndarray, i: int, px: float, py: float, pz: float,
                   vx: float, vy: float, vz: float, w: np.ndarray, H: np.ndarray) -> None:
    """Body i's momentum about the world origin into H[i]: L = c × P + I_c·ω, P = m·v_c, then
    its mass and first moment (origin p, origin velocity v, rotation R)."""
    m = inertia[i, 0]
    l0, l1, l2 = inertia[i, 1], inertia[i, 2], inertia[i, 3]
    lx = R[0] * l0 + R[1] * l1 + R[2] * l2
    ly = R[3] * l0 + R[4] * l1 + R[5] * l2
    lz = R[6] * l0 + R[7] * l1 + R[8] * l2
    cwx, cwy, cwz = px + lx, py + ly, pz + lz
    wix, wiy, wiz = w[i, 0], w[i, 1], w[i, 2]
    ex, ey, ez = _cross(wix, wiy, wiz, lx, ly, lz)
    Px, Py, Pz = m * (vx + ex), m * (vy + ey), m * (vz + ez)
    # I_c·ω in world axes: R·I·Rᵀ·ω
    I6 = inertia[i, 4:]
    bx = R[0] * wix + R[3] * wiy + R[6] * wiz
    by = R[1] * wix + R[4] * wiy + R[7] * wiz
    bz = R[2] * wix + R[5] * wiy + R[8] * wiz
    jx = I6[0] * bx + I6[1] * by + I6[2] * bz
    jy = I6[1] * bx + I6[3] * by + I6[4] * bz
    jz = I6[2] * bx + I6[4] * by + I6[5] * bz
    kx, ky, kz = _cross(cwx, cwy, cwz, Px, Py, Pz)
    H[i, 0] = kx + R[0] * jx + R[1] * jy + R[2] * jz
    H[i, 1] = ky + R[3] * jx + R[4] * jy + R[5] * jz
    H[i, 2] = kz + R[6] * jx + R[7] * jy + R[8] * jz
    H[i, 3], H[i, 4], H[i, 5] = Px, Py, Pz
    H[i, 6] = m
    H[i, 7], H[i, 8], H[i, 9] = m * cwx, m * cwy, m * cwz


@njit(inline="always", **_JIT)
def _contact_jacobian(parent: np.ndarray, revolute: np.ndarray, index: np.ndarray,
                      Rw: np.ndarray, pw: np.ndarray, z: np.ndarray, fjoint: int,
                      fplace: np.ndarray, J: np.ndarray) -> None:
    """J (6×nv): the contact frame's Jacobian in its own axes, linear rows first (Pinocchio's
    LOCAL), from the joints' world poses: column c = [Rfᵀ(z × (o − p)); Rfᵀz] (revolute)."""
    A = Rw[fjoint]
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = _mul9(A, fplace)
    tx, ty, tz = _rot(A, fplace[9], fplace[10], fplace[11])
    ox, oy, oz = pw[fjoint, 0] + tx, pw[fjoint, 1] + ty, pw[fjoint, 2] + tz
    for r in range(6):
        for c in range(J.shape[1]):
            J[r, c] = 0.0
    i = fjoint
    while i > 0:
        c = index[i]
        zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
        if revolute[i]:
            J[3, c] = f00 * zx + f10 * zy + f20 * zz
            J[4, c] = f01 * zx + f11 * zy + f21 * zz
            J[5, c] = f02 * zx + f12 * zy + f22 * zz
        lx, ly, lz = linear_column(z, pw, revolute, i, ox, oy, oz)
        J[0, c] = f00 * lx + f10 * ly + f20 * lz
        J[1, c] = f01 * lx + f11 * ly + f21 * lz
        J[2, c] = f02 * lx + f12 * ly + f22 * lz
        i = parent[i]


@njit(**_JIT)
def model_terms(q: np.ndarray, v: np.ndarray, parent: np.ndarray, revolute: np.ndarray,
                index: np.ndarray, placement: np.ndarray, axis: np.ndarray, inertia: np.ndarray,
                armature: np.ndarray, gravity: np.ndarray, fjoint: int, fplace: np.ndarray,
                Rw: np.ndarray, pw: np.ndarray, z: np.ndarray, w: np.ndarray, vo: np.ndarray,
                H: np.ndarray, p: np.ndarray, ctv: np.ndarray, g: np.ndarray,
                J: np.ndarray) -> None:
    """One state: p = M(q)q̇ (armature included), Cᵀq̇ and g(q) (nv each), and J (6×nv) the
    contact frame's Jacobian (:func:`_contact_jacobian`); the rest are scratch (n rows each:
    rotations, origins, axes, ω, origin velocities, subtree momentum and mass sums
    [Lx Ly Lz Px Py Pz M Sx Sy Sz])."""
    n = len(parent)
    Rw[0, :] = 0.0
    Rw[0, 0] = Rw[0, 4] = Rw[0, 8] = 1.0
    g0, g1, g2 = gravity[0], gravity[1], gravity[2]
    for i in range(1, n):
        a = parent[i]
        c = index[i]
        qd = v[c]
        px, py, pz, zx, zy, zz = joint_step(Rw, pw, z, parent, placement, axis, revolute, i, q[c])
        # velocity of this origin: the parent's origin velocity carried by ω_a, plus a stroke
        wax, way, waz = w[a, 0], w[a, 1], w[a, 2]
        cx, cy, cz = _cross(wax, way, waz, px - pw[a, 0], py - pw[a, 1], pz - pw[a, 2])
        vx, vy, vz = vo[a, 0] + cx, vo[a, 1] + cy, vo[a, 2] + cz
        if revolute[i]:
            w[i, 0], w[i, 1], w[i, 2] = wax + zx * qd, way + zy * qd, waz + zz * qd
        else:
            w[i, 0], w[i, 1], w[i, 2] = wax, way, waz
            vx, vy, vz = vx + zx * qd, vy + zy * qd, vz + zz * qd
        vo[i, 0], vo[i, 1], vo[i, 2] = vx, vy, vz
        _body_momentum(Rw[i], inertia, i, px, py, pz, vx, vy, vz, w, H)
    # children have larger indices than their parent: subtree sums complete when i is reached
    for i in range(n - 1, 0, -1):
        c = index[i]
        zx, zy, zz = z[i, 0], z[i, 1], z[i, 2]
        Px, Py, Pz = H[i, 3], H[i, 4], H[i, 5]
        ox, oy, oz = _cross(w[i, 0], w[i, 1], w[i, 2], zx, zy, zz)
        if revolute[i]:
            px, py, pz = pw[i, 0], pw[i, 1], pw[i, 2]
            tx, ty, tz = _cross(px, py, pz, Px, Py, Pz)
            Lx, Ly, Lz = H[i, 0] - tx, H[i, 1] - ty, H[i, 2] - tz
            p[c] = zx * Lx + zy * Ly + zz * Lz + armature[c] * v[c]
            ux, uy, uz = _cross(vo[i, 0], vo[i, 1], vo[i, 2], zx, zy, zz)
            ctv[c] = ox * Lx + oy * Ly + oz * Lz + ux * Px + uy * Py + uz * Pz
            M = H[i, 6]
            rx, ry, rz = H[i, 7] - M * px, H[i, 8] - M * py, H[i, 9] - M * pz
            g[c] = -(zx * (ry * g2 - rz * g1) + zy * (rz * g0 - rx * g2) + zz * (rx * g1 - ry * g0))
        else:
            p[c] = zx * Px + zy * Py + zz * Pz + armature[c] * v[c]
            ctv[c] = ox * Px + oy * Py + oz * Pz
            g[c] = -H[i, 6] * (zx * g0 + zy * g1 + zz * g2)
        a = parent[i]
        if a > 0:
            for r in range(10):
                H[a, r] += H[i, r]
    _contact_jacobian(parent, revolute, index, Rw, pw, z, fjoint, fplace, J)


@njit([types.void(_C1)], **_JIT)
def _power_restart(power: np.ndarray) -> None:
    """Discard the open period; a period with two samples or more counts as broken."""
    if power[P_N] > 1:
        power[P_BROKEN] += 1.0
    power[P_N] = 0.0
    power[P_WORK] = power[P_GROSS] = power[P_FRICTION] = 0.0


@njit([types.int64(_C1, _f8, _f8, _f8)], **_JIT)
def power_step(power: np.ndarray, t: float, pw: float, fw: float) -> int:
    """One sample at stamp t with power τ_mᵀq̇ = ``pw`` and friction power ``fw`` into the
    period's trapezoid sums (P_*): 0 added, 1 the period's first sample (after a restart, or a
    step back, which restarts it), 2 the same instant again (ignored)."""
    if power[P_N] > 0 and t <= power[P_T]:
        if t == power[P_T]:
            return 2
        _power_restart(power)
    first = power[P_N] == 0
    if not first:
        h = t - power[P_T]
        power[P_WORK] += 0.5 * h * (power[P_POW] + pw)
        power[P_GROSS] += 0.5 * h * (abs(power[P_POW]) + abs(pw))
        power[P_FRICTION] += 0.5 * h * (power[P_FPOW] + fw)
    power[P_T], power[P_POW], power[P_APOW], power[P_FPOW] = t, pw, abs(pw), fw
    power[P_N] += 1.0
    return 1 if first else 0


@njit(**_JIT)
def _no_estimate(k: int, clock: np.ndarray, power: np.ndarray, TAU: np.ndarray, W: np.ndarray,
                 info: np.ndarray, code: np.ndarray) -> None:
    """Row k without an estimate (invalid): the history dropped, the power period restarted,
    NaN outputs."""
    code[k] = NO_ESTIMATE
    if clock[C_HAS] != 0.0:
        clock[C_HAS] = 0.0
        clock[C_AFTER_INVALID] = 1.0
        info[k, I_DROPPED] = 1.0
    _power_restart(power)
    for c in range(TAU.shape[1]):
        TAU[k, c] = np.nan
    for c in range(6):
        W[k, c] = np.nan
    info[k, I_SINCE] = info[k, I_SIGMA] = info[k, I_FORCE] = np.nan
    info[k, I_POWER_STEP] = -1.0


@njit(inline="always", **_JIT)
def _observe(t: float, held: bool, max_gap: float, gain: np.ndarray, p: np.ndarray,
             s: np.ndarray, e: np.ndarray, r_: np.ndarray, p_: np.ndarray, s_: np.ndarray,
             e_: np.ndarray, clock: np.ndarray) -> tuple[int, float]:
    """One valid sample at stamp t into the observer (r_ and the last sample p_, s_, e_ and
    ``clock`` updated): (its row code, dt)."""
    kind = ESTIMATE
    dt = 0.0
    if clock[C_HAS] == 0.0:
        kind = RESTART_AFTER_INVALID if clock[C_AFTER_INVALID] != 0.0 else RESTART
    else:
        dt = t - clock[C_T]
        if dt < 0:
            kind = BACKWARDS
        elif dt > max_gap:
            kind = STAMP_GAP
        elif dt == 0.0:
            kind = SAME_INSTANT
    if kind == ESTIMATE:
        for c in range(len(p)):
            ei = dt * e[c] if held else 0.5 * dt * (e_[c] + e[c])
            mean = (p[c] - p_[c] - 0.5 * dt * (s_[c] + s[c]) - ei) / dt
            a = math.exp(-gain[c] * dt)
            r_[c] = a * r_[c] + (1.0 - a) * mean
    elif kind != SAME_INSTANT:
        for c in range(len(p)):
            r_[c] = 0.0
        clock[C_T0] = t
        clock[C_HAS] = 1.0
        clock[C_AFTER_INVALID] = 0.0
    if kind != SAME_INSTANT:
        clock[C_T] = t
        for c in range(len(p)):
            p_[c], s_[c], e_[c] = p[c], s[c], e[c]
    return kind, dt


@njit(inline="always", **_JIT)
def _row_outputs(k: int, r_: np.ndarray, contact_at: np.ndarray, J: np.ndarray,
                 wopt: np.ndarray, G: np.ndarray, U: np.ndarray, ev: np.ndarray, y: np.ndarray,
                 F: np.ndarray, TAU: np.ndarray, W: np.ndarray, info: np.ndarray) -> None:
    """Row k's estimate r_ into TAU, the contact-level test and the wrench (damped_solve) into
    W and info."""
    over = False
    for c in range(len(r_)):
        TAU[k, c] = r_[c]
        over = over or abs(r_[c]) > contact_at[c]
    info[k, I_OVER] = 1.0 if over else 0.0
    sigma, lam, misfit = damped_solve(J, r_, wopt[0], wopt[1], wopt[2], G, U, ev, y, F)
    f2 = 0.0
    for c in range(6):
        W[k, c] = F[c]
    for c in range(3):
        f2 += F[c] * F[c]
    info[k, I_SIGMA], info[k, I_DAMPING], info[k, I_MISFIT] = sigma, lam, misfit
    info[k, I_FORCE] = math.sqrt(f2)


# One compiled call per batch (or per live sample): per-row overhead of separate calls is what
# this module removes.
@njit([types.void(_M, _M, _M, _V, _B, _B, _I, _B, _I, _M, _M, _M, _V, _V, _V, _V,
                  types.int64, _V, _V, _f8, types.boolean, _V, _V, _C2, _C1, _C1,
                  _C2, _C2, _C2, _IC)], **_JIT)
def observer_rows(Q: np.ndarray, V: np.ndarray, E: np.ndarray, T: np.ndarray,
                  valid: np.ndarray, reset: np.ndarray, parent: np.ndarray,
                  revolute: np.ndarray, index: np.ndarray, placement: np.ndarray,
                  axis: np.ndarray, inertia: np.ndarray, armature: np.ndarray,
                  gravity: np.ndarray, damping: np.ndarray, coulomb: np.ndarray, fjoint: int,
                  fplace: np.ndarray, gain: np.ndarray, max_gap: float, held: bool,
                  wopt: np.ndarray, contact_at: np.ndarray, state: np.ndarray, clock: np.ndarray,
                  power: np.ndarray, TAU: np.ndarray, W: np.ndarray, info: np.ndarray,
                  code: np.ndarray) -> None:
    """N joint states through the momentum observer, the contact wrench, the contact-level test
    and the power balance: arguments and outputs as the module docstring says."""
    N, nv = Q.shape
    n = len(parent)
    Rw, pw, z, w, vo = (np.zeros((n, 9)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)),
                        np.zeros((n, 3)))
    H, p, ctv, g, s, J = (np.zeros((n, 10)), np.zeros(nv), np.zeros(nv), np.zeros(nv),
                          np.zeros(nv), np.zeros((6, nv)))
    k6 = 6 if nv >= 6 else nv
    G, U, ev, y, F = np.zeros((k6, k6)), np.zeros((k6, k6)), np.zeros(k6), np.zeros(k6), np.zeros(6)
    r_, p_, s_, e_ = state[0], state[1], state[2], state[3]
    for k in range(N):
        for j in range(INFO_COLUMNS):
            info[k, j] = 0.0
        if reset[k]:
            clock[C_HAS] = 0.0
            clock[C_AFTER_INVALID] = 0.0
            _power_restart(power)
        if not valid[k]:
            _no_estimate(k, clock, power, TAU, W, info, code)
            continue
        t = T[k]
        q, v, e = Q[k], V[k], E[k]
        model_terms(q, v, parent, revolute, index, placement, axis, inertia, armature, gravity,
                    fjoint, fplace, Rw, pw, z, w, vo, H, p, ctv, g, J)
        pw_ = 0.0
        fw_ = 0.0
        for c in range(nv):
            vc = v[c]
            sg = 1.0 if vc > 0 else (-1.0 if vc < 0 else 0.0)
            fr = damping[c] * vc + coulomb[c] * sg
            s[c] = ctv[c] - g[c] - fr
            pw_ += e[c] * vc
            fw_ += fr * vc
        code[k], info[k, I_DT] = _observe(t, held, max_gap, gain, p, s, e, r_, p_, s_, e_, clock)
        info[k, I_SINCE] = t - clock[C_T0]
        _row_outputs(k, r_, contact_at, J, wopt, G, U, ev, y, F, TAU, W, info)
        info[k, I_POWER_STEP] = power_step(power, t, pw_, fw_)
