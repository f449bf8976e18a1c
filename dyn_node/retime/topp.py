"""TOPP-RA (toppra 0.6.10) over the exact check's first- and second-order joint kinds.

Along q(s) with x = ṡ² and u = s̈ (ṡ ≥ 0): q̇ = q'ṡ, q̈ = q'u + q''x, and the torque the check
computes is τ = a(s)·u + b(s)·x + c(s) + w(s)·ṡ with a = M q' (+armature), b = M q'' + C(q, q')q'
(+armature), c = g + Coulomb·sign(q') (payload in the model) and w = damping·q'. Rows, all linear
in (u, x): ±q̈ ≤ acceleration; −sign(q')·q̈ ≤ deceleration (the check's |q̈| where q̇·q̈ < 0:
exact, the row is slack when q̇·q̈ ≥ 0); ±τ ≤ effort; and x ≤ (velocity/|q'|)². The viscous
term w·ṡ is not linear in x: the retiming drops it (the exact check afterwards sees it), the
lower bound relaxes it to its most favourable value over the velocity-limited ṡ range, so the
bound stays a bound.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.retime import reach
from dyn_node.retime.path import Path


@dataclass(frozen=True)
class Rows:
    """a·u + b·x + c ≤ g at every grid point (arrays (N+1)×m, g (m,)), and x ≤ xmax (N+1,)."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    g: np.ndarray
    xmax: np.ndarray


@dataclass(frozen=True)
class Terms:
    """The path's derivatives and torque coefficients at a grid (see the module docstring):
    computed once per grid, shared by the lower bound's rows and the retiming's."""

    d1: np.ndarray
    d2: np.ndarray
    a: np.ndarray | None
    b: np.ndarray | None
    c: np.ndarray | None
    w: np.ndarray | None
    #: the first-order task kinds per unit ṡ (:func:`_frame_speeds`)
    speeds: tuple = ()
    #: vectors a·u + b·x + c under a norm limit: the frames' linear accelerations
    #: (:func:`_frame_accelerations`), the mounting's force and moment (:func:`_mounting`),
    #: the grasp's tangential force (:func:`_grasp`)
    accels: tuple = ()
    #: the floor's normal force and N·(centre of pressure) as a·u + b·x + c, and the support
    #: polygon (:func:`_floor`), or None
    floor: tuple | None = None


def joint_terms(dynamics: Dynamics, path: Path, grid: np.ndarray) -> Terms:
    from dyn_node.core.check import task_motion

    q, d1, d2 = path.derivatives(grid)
    # the check's own frame pass at q̇ = q', q̈ = q'' (None without task limits): speeds and
    # energy per unit ṡ (they see q̇ only), a frame's acceleration's ṡ² part
    task = task_motion.build(dynamics, q, d1, d2)
    tl = dynamics.model.task_limits
    speeds = _frame_speeds(tl, task)
    # the mounting's wrench a·u + b·x + c: its momentum rate is linear in q̈ and quadratic in
    # q̇, so b is the dynamic part at q̇ = q', q̈ = q'' (``task``'s pass), a at q̇ = 0, q̈ = q'
    # (one more pass), c the static part (gravity, a task wrench's reaction)
    first = None if task is None or (task.base is None and tl.grasp is None) else \
        task_motion.build(dynamics, q, np.zeros_like(q), d1)
    wrench = None if task is None or task.base is None else (
        first.base.dynamic, task.base.dynamic, task.base.static)
    accels = _frame_accelerations(tl, task) + _mounting(tl, wrench) + _grasp(tl, task, first)
    floor = _floor(tl, task, wrench)
    if not np.any(np.isfinite(dynamics.model.limits.effort)):
        return Terms(d1, d2, None, None, None, None, speeds, accels, floor)
    a = dynamics.terms_batch(q, np.zeros_like(q), d1).inertial
    terms = dynamics.terms_batch(q, d1, d2)
    c = terms.static
    if task is not None and task.task_torque is not None:
        # a task wrench's torque depends on q only: part of c, as the check's effort has it
        c = c + task.task_torque
    return Terms(d1, d2, a, terms.inertial, c, dynamics.friction_coefficients[0] * d1, speeds,
                 accels, floor)


def _frame_accelerations(tl, task) -> tuple:
    """Each configured frame's linear acceleration J q̈ + J̇ q̇ = a·s̈ + b·ṡ² (m/s², gravity
    excluded, at the frame's point), from the frame pass at q̇ = q', q̈ = q'': a = J q' (the
    point's velocity there), b = J q'' + J̇ q' (its acceleration there); (a, b, limit)."""
    from dyn_node.core.check import task_motion

    if task is None:
        return ()
    out = []
    for f in tl.frame_limits:
        if math.isfinite(f.max_linear_acceleration):
            terms = task.frame(task_motion.FRAME_ROLE + f.frame)
            a = np.asarray(terms.linear_velocity, dtype=float)
            out.append((a, np.asarray(terms.linear_acceleration, dtype=float),
                        np.zeros_like(a), float(f.max_linear_acceleration)))
    return tuple(out)


def _mounting(tl, wrench: tuple | None) -> tuple:
    """The mounting's force and moment on the robot (the check's base_force and base_moment,
    root origin and axes), (a, b, c, limit) for each configured limit."""
    bl = tl.base_limits
    if wrench is None or bl is None:
        return ()
    return tuple((wrench[0][:, sl], wrench[1][:, sl], wrench[2][:, sl], float(lim))
                 for sl, lim in ((slice(0, 3), bl.max_force), (slice(3, 6), bl.max_moment))
                 if math.isfinite(lim))


def _grasp(tl, task, first) -> tuple:
    """The check's grasp slip: the grasp's force on the payload m·(a − g) in the grasp's axes,
    its part across the normal axis within μ·grip_force·faces; a from the payload point's
    acceleration at q̇ = 0, q̈ = q' (``first``), b at q̇ = q', q̈ = q'' (``task``), c = −m·g."""
    from dyn_node.core.check import base_constraints, force_laws

    g = tl.grasp
    if task is None or g is None:
        return ()
    n = np.asarray(g.normal_axis, dtype=float)
    n = n / np.linalg.norm(n)

    def force(tm):
        return base_constraints.grasp_force(tm.frame("payload"), tm.rotation[tm.roles["grasp"]],
                                            tm.gravity, float(task.payload_mass))

    fa, fb = force(first), force(task)
    return ((force_laws.tangential(fa.dynamic, n), force_laws.tangential(fb.dynamic, n),
             force_laws.tangential(fb.static, n), float(g.max_tangential_force)),)


def _floor(tl, task, wrench: tuple | None) -> tuple | None:
    """The check's tipping terms (force_laws.tipping_law): the floor pushes on the base with
    F = F_r − m_b·g, M = M_r − c_b × m_b·g; N = F_z and P = N·p = (−M_y, M_x), each
    a·u + b·x + c ((a, b, c) of N, then of P: N×2), and the support polygon."""
    from dyn_node.core.check import force_laws

    bl = tl.base_limits
    if wrench is None or bl is None or bl.support_polygon is None:
        return None
    com = np.zeros(3) if bl.base_com is None else bl.base_com
    weight, moment = force_laws.base_weight(base_mass=bl.base_mass, base_com=com,
                                            gravity=task.gravity)
    N, P = [], []
    # the base's weight is static: only in c
    for w, fw, mw in zip(wrench, (0.0, 0.0, weight), (0.0, 0.0, moment)):
        F, M = w[:, :3] - fw, w[:, 3:] - mw
        N.append(F[:, 2])
        P.append(np.column_stack([-M[:, 1], M[:, 0]]))
    return tuple(N), tuple(P), bl.support_polygon


def _floor_rows(floor: tuple, share: float) -> tuple[np.ndarray, ...]:
    """The floor's rows ≤ 0: each edge n_i·P ≤ (n_i·c₀ + share·reach_i)·N (the centre of
    pressure within ``share`` of the way from the centroid c₀ to the edge: the check's gauge ≤
    share, exactly, while N > 0) and N ≥ 0 (no lift-off)."""
    N, P, poly = floor
    off = poly.normals @ poly.centroid + share * poly.reach
    rows = [X @ poly.normals.T - n[:, None] * off[None, :] for n, X in zip(N, P)]
    rows = [np.column_stack([r, -n]) for r, n in zip(rows, N)]
    return (*rows, np.zeros(rows[0].shape[1]))


#: sides of the polygon that stands for a frame acceleration's disc (:func:`_disc_rows`)
_DISC_SIDES = 24


def _disc_rows(a: np.ndarray, b: np.ndarray, c: np.ndarray, limit: float, *, outer: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """|a·u + b·x + c| ≤ limit (a, b, c: N×3) as linear rows in (u, x), rows ≤ 0. The vector
    a·u + b·x lies in the plane of a and b: with its Gram matrix G = LLᵀ (the orthonormal
    basis e₁, e₂ of Gram–Schmidt on a, b), a·u + b·x = y₁e₁ + y₂e₂ with y = Lᵀ(u, x), and
    |a·u + b·x + c|² = |y + c̃|² + |c⊥|² (c̃: c in that basis, c⊥ the rest): a disc of radius
    r = √(limit² − |c⊥|²) about −c̃ (none where |c⊥| > limit: the row 1 ≤ 0). The rows are the
    tangents e_k·(y + c̃) ≤ r of a regular polygon of :data:`_DISC_SIDES` sides: ``outer``
    (the polygon holds the disc, a relaxation, so a lower bound stays one) or inner (radius
    r·cos(π/K): the disc holds the polygon, so every (u, x) the rows allow keeps the limit)."""
    g11 = np.einsum("ij,ij->i", a, a)
    g12 = np.einsum("ij,ij->i", a, b)
    g22 = np.einsum("ij,ij->i", b, b)
    l11 = np.sqrt(g11)
    live = l11 > 0
    # where a = 0 (no s̈ term) the vector is b·x: y = (|b|·x, 0), e₁ = b/|b|
    l21 = np.where(live, g12 / np.where(live, l11, 1.0), np.sqrt(g22))
    l22 = np.where(live, np.sqrt(np.maximum(g22 - l21**2, 0.0)), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        e1 = np.where(live[:, None], a / l11[:, None], b / np.sqrt(g22)[:, None])
        e2 = (b - l21[:, None] * e1) / l22[:, None]
    e1, e2 = (np.where(np.isfinite(e), e, 0.0) for e in (e1, e2))
    c1, c2 = np.einsum("ij,ij->i", c, e1), np.einsum("ij,ij->i", c, e2)
    room = limit**2 - (np.einsum("ij,ij->i", c, c) - c1**2 - c2**2)
    r = np.sqrt(np.maximum(room, 0.0)) * (1.0 if outer else math.cos(math.pi / _DISC_SIDES))
    phi = 2 * np.pi * np.arange(_DISC_SIDES) / _DISC_SIDES
    cos, sin = np.cos(phi)[None, :], np.sin(phi)[None, :]
    C = cos * c1[:, None] + sin * c2[:, None] - r[:, None]
    C[room < 0] = 1.0
    return (cos * l11[:, None], cos * l21[:, None] + sin * l22[:, None], C,
            np.zeros(_DISC_SIDES))


def _frame_speeds(tl, task) -> tuple:
    """The first-order task kinds per unit ṡ, from the frame pass at q̇ = q':
    (value, limit, p) with the bound x ≤ (limit/value)^p: frame speeds (|J q'|, p = 2) and the
    robot's kinetic energy (½ q'ᵀM q', p = 1)."""
    from dyn_node.core.check import task_motion

    entries = [(f, key) for f in tl.frame_limits
               for key in ("max_linear_speed", "max_angular_speed")
               if math.isfinite(getattr(f, key))]
    energy = tl.robot_limits.max_kinetic_energy if tl.robot_limits is not None else math.inf
    if task is None or (not entries and not math.isfinite(energy)):
        return ()
    out = []
    for f, key in entries:
        terms = task.frame(task_motion.FRAME_ROLE + f.frame)
        v = terms.linear_velocity if key == "max_linear_speed" else terms.angular_velocity
        out.append((np.sqrt(np.einsum("ij,ij->i", v, v)), float(getattr(f, key)), 2))
    if math.isfinite(energy):
        out.append((np.asarray(task.batch.inertia.kinetic_energy, dtype=float), energy, 1))
    return tuple(out)


def joint_rows(dynamics: Dynamics, path: Path, grid: np.ndarray, *, scale: float = 1.0,
               lower_bound: bool = False, terms: Terms | None = None) -> Rows:
    """The rows of the joint kinds at the grid, limits multiplied by ``scale`` (``terms``:
    :func:`joint_terms` of this path and grid, when already computed)."""
    lim = dynamics.model.limits
    t = joint_terms(dynamics, path, grid) if terms is None else terms
    d1, d2 = t.d1, t.d2
    with np.errstate(divide="ignore"):
        xv = np.min(np.where(np.abs(d1) > 0, (lim.velocity * scale / np.abs(d1)) ** 2, np.inf),
                    axis=1)
        for per_unit, limit, p in t.speeds:
            # a frame's speed is |J q'|·ṡ, the kinetic energy ½ q'ᵀM q'·ṡ²: bounds on ṡ²
            # (an energy goes as a speed squared: its margin is scale²)
            bound = (limit * scale / per_unit) ** 2 if p == 2 else limit * scale**2 / per_unit
            xv = np.minimum(xv, np.where(per_unit > 0, bound, np.inf))
    A, B, C, G = [], [], [], []

    def add(a, b, c, g):
        A.append(a), B.append(b), C.append(c), G.append(g)

    cols = np.isfinite(lim.acceleration)
    for sign in ((1.0, -1.0) if cols.any() else ()):
        add(sign * d1[:, cols], sign * d2[:, cols], 0 * d1[:, cols], lim.acceleration[cols] * scale)
    # |q̈| ≤ acceleration ≤ deceleration already bounds a joint's deceleration: no row for it
    cols = np.isfinite(lim.deceleration) & ~(lim.deceleration >= lim.acceleration)
    if cols.any():
        sg = -np.sign(d1[:, cols])
        add(sg * d1[:, cols], sg * d2[:, cols], 0 * d1[:, cols], lim.deceleration[cols] * scale)
    cols = np.isfinite(lim.effort)
    if cols.any():
        a, b, c, w = t.a, t.b, t.c, t.w
        lo_w = hi_w = np.zeros_like(w)
        if lower_bound and np.any(w):
            # w·ṡ lies between 0 and w·√xv: each side takes its most favourable end
            sq = np.sqrt(np.minimum(xv, 1e12))[:, None]
            lo_w, hi_w = np.minimum(0.0, w * sq), np.maximum(0.0, w * sq)
        L = lim.effort[cols] * scale
        add(a[:, cols], b[:, cols], (c + lo_w)[:, cols], L)
        add(-a[:, cols], -b[:, cols], -(c + hi_w)[:, cols], L)
    for fa, fb, fc, limit in t.accels:
        # the bound relaxes the disc (outer polygon), the retiming keeps inside it
        add(*_disc_rows(fa, fb, fc, limit * scale, outer=lower_bound))
    if t.floor is not None:
        add(*_floor_rows(t.floor, scale))
    if not A:
        z = np.zeros((len(grid), 1))
        return Rows(z, z, z, np.ones(1), xv)
    return Rows(np.hstack(A), np.hstack(B), np.hstack(C), np.concatenate(G), xv)


#: ṡ² below which a controllable set's lower end over a cap is taken as rounding
_ROUNDING = 1e-9
#: toppra's SMALL: how far the start's ṡ² may lie outside the first controllable set
_START_SLACK = 1e-5


class Reach:
    """TOPP-RA (its algorithm, :mod:`dyn_node.retime.reach`, compiled) on fixed rows, solved
    again under caps on ṡ². A cap is the bound x ≤ cap at a grid point: the controllable set
    there is TOPP-RA's intersected with it (the projection of the stage's polygon onto x is an
    interval, so this equals adding the cap to the rows), and only the sets at and below the
    highest changed cap are computed again; the forward pass then runs on them."""

    def __init__(self, path: Path, grid: np.ndarray, rows: Rows):
        self.path, self.grid, self.rows = path, grid, rows
        self._abc = (np.ascontiguousarray(rows.a, dtype=float),
                     np.ascontiguousarray(rows.b, dtype=float),
                     np.ascontiguousarray(rows.c - rows.g, dtype=float))
        self._xmax = np.minimum(rows.xmax, 1e12)
        self._deltas = np.diff(grid)
        self.cap = np.full(len(grid), np.inf)
        self._done: tuple | None = None      # (end, cap, K) of the last backward pass

    def controllable(self, sd_end: float) -> np.ndarray:
        """The controllable sets (N+1)×2 for ṡ = ``sd_end`` at the end, under ``self.cap``
        (NaN at and below a stage no timing reaches the end from)."""
        n = len(self.grid) - 1
        if self._done is not None and self._done[0] == sd_end:
            changed = np.flatnonzero(self._done[1] != self.cap)
            if changed.size == 0:
                return self._done[2].copy()
            K, top = self._done[2].copy(), min(int(changed[-1]), n - 1)
        else:
            K, top = np.zeros((n + 1, 2)), n - 1
        K[n] = [sd_end**2, min(sd_end**2, self.cap[n])]
        if K[n, 0] > K[n, 1]:
            K[:] = np.nan
        else:
            reach.controllable(*self._abc, self._xmax, self._deltas, self.cap, K, top,
                               _ROUNDING)
        self._done = (sd_end, self.cap.copy(), K.copy())
        return K

    def solve(self, *, cap: np.ndarray | None = None, sd_start: float = 0.0,
              free_ends: bool = False) -> np.ndarray | None:
        """TOPP-RA's time-optimal x = ṡ² at the grid (N+1,) under ``cap``, None when the path
        is not controllable (no timing meets the rows, e.g. gravity alone above an effort
        limit).

        ``free_ends``: where the path itself stops (q' = 0 at an end) the robot is at rest at
        any ṡ, so ṡ is left free there (the bound: else a first-order grid error of the forced
        ṡ = 0). The retiming keeps ṡ = 0 at the ends: its smoothing window starts from ṡ = 0."""
        self.cap = np.full(len(self.grid), np.inf) if cap is None else np.asarray(cap, float)
        ends = np.max(np.abs(self.path.derivatives(self.grid[[0, -1]])[1]), axis=1)
        sd_end = 0.0
        if free_ends and ends[1] == 0.0:
            # every row is free of u where q' = 0: ṡ² up to the tightest of them
            xmax = np.minimum(self.rows.xmax, self.cap)
            sd_end = math.sqrt(_free_end_x(self.rows, xmax)) * (1 - 1e-9)
        K = self.controllable(sd_end)
        if free_ends and ends[0] == 0.0 and sd_start == 0.0 and np.all(np.isfinite(K[0])):
            sd_start = math.sqrt(max(K[0, 1], 0.0)) * (1 - 1e-9)
        x0 = sd_start**2
        if np.isnan(K).any() or not (K[0, 0] - _START_SLACK <= x0 <= K[0, 1] + _START_SLACK):
            return None
        xs = reach.forward(*self._abc, self._deltas, K, x0)
        if not np.all(np.isfinite(xs)):
            return None
        return np.maximum(xs, 0.0)


def solve(path: Path, grid: np.ndarray, rows: Rows, *, cap: np.ndarray | None = None,
          sd_start: float = 0.0, free_ends: bool = False) -> np.ndarray | None:
    """One :meth:`Reach.solve` on a new instance."""
    return Reach(path, grid, rows).solve(cap=cap, sd_start=sd_start, free_ends=free_ends)


def _free_end_x(rows: Rows, xmax: np.ndarray) -> float:
    b, room = rows.b[-1], rows.g - rows.c[-1]
    if np.any(room < 0):
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        lim = np.where(b > 0, room / b, np.inf)
    return float(min(np.min(lim), xmax[-1], 1e12))


def duration(grid: np.ndarray, x: np.ndarray) -> float:
    """The time of x = ṡ² on the grid, ṡ affine in time per step (constant s̈)."""
    sd = np.sqrt(np.maximum(x, 0.0))
    den = sd[:-1] + sd[1:]
    if np.any(den <= 0):
        return math.inf
    return float(np.sum(2 * np.diff(grid) / den))
