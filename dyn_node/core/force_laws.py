"""Per-sample laws of the frame, energy, base-wrench, tipping and grasp constraints (NumPy).

Each law takes per-sample arrays (kinematics and wrenches computed elsewhere) and returns a
:class:`LawResult`: the value at the given timing (k = 1), its ratio to the limit, and the
per-sample ``time_scale`` k: the smallest k such that the sample is feasible at every k′ ≥ k
(s = 1/k²; k′ ≥ k ⇔ s′ ∈ (0, s]). 0: feasible at any timing; inf: no slowdown helps. A
trajectory's share of ``time_scale`` for a kind is the largest per-sample k. Non-finite inputs
give NaN values, ratios and k (never a silent "feasible").
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LawResult:
    """One constraint over N samples. ``value`` and ``static_value`` (the k → ∞ limit: the still
    pose) are in the limit's unit; ``ratio`` = value / limit (tipping: the ``tipping_ratio``
    gauge, limit 1); ``time_scale`` as in the module docstring."""

    value: np.ndarray
    static_value: np.ndarray
    ratio: np.ndarray
    time_scale: np.ndarray
    limit: float

    @property
    def max_time_scale(self) -> float:
        """The largest per-sample k (NaN if any sample is NaN; 0 for no samples)."""
        return float(np.max(self.time_scale)) if self.time_scale.size else 0.0

    @property
    def peak_index(self) -> int:
        """Sample of the largest ratio (the first NaN if any)."""
        return int(np.argmax(self.ratio)) if self.ratio.size else 0


@dataclass(frozen=True)
class TippingResult(LawResult):
    """:class:`LawResult` of the tipping law plus, at k = 1, the centre of pressure (N×2, m, root
    x–y; NaN at lift-off) and the floor's normal force (N, > 0 while standing)."""

    centre_of_pressure: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    normal_force: np.ndarray = field(default_factory=lambda: np.empty(0))


@dataclass(frozen=True)
class ScaledWrench:
    """A wrench per sample as static + s·dynamic (N×3 each; force N, moment N·m)."""

    force_static: np.ndarray
    force_dynamic: np.ndarray
    moment_static: np.ndarray
    moment_dynamic: np.ndarray


@dataclass(frozen=True)
class SupportPolygon:
    """Convex polygon in the root z = 0 plane: counter-clockwise ``vertices`` (n×2, m), each edge
    i (vertex i to i + 1) as the half-plane normals[i]·p ≤ offsets[i] (unit outward normals), and
    the area ``centroid``. Build it with :meth:`from_ccw` from validated vertices."""

    vertices: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    centroid: np.ndarray

    @classmethod
    def from_ccw(cls, vertices: np.ndarray) -> "SupportPolygon":
        v = np.array(vertices, dtype=float)
        e = np.roll(v, -1, axis=0) - v
        n = np.column_stack([e[:, 1], -e[:, 0]]) / np.linalg.norm(e, axis=1)[:, None]
        w = np.roll(v, -1, axis=0)
        cross = v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1]
        centroid = ((v + w) * cross[:, None]).sum(axis=0) / (3.0 * cross.sum())
        arrays = (v, n, np.einsum("ij,ij->i", n, v), centroid)
        for a in arrays:
            a.setflags(write=False)
        return cls(*arrays)

    def gauge(self, points: np.ndarray) -> np.ndarray:
        """|p − c| / |boundary point on the ray from the centroid c through p − c| per point
        (…×2): 1 on the edge, < 1 inside, 0 at the centroid."""
        d = np.asarray(points, dtype=float) - self.centroid
        reach = self.offsets - self.normals @ self.centroid       # > 0: c is inside
        return np.maximum((d @ self.normals.T / reach).max(axis=-1), 0.0)


def _finite_rows(*arrays: np.ndarray) -> np.ndarray:
    ok = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        ok &= np.isfinite(a).reshape(len(a), -1).all(axis=1)
    return ok


def _limit(limit: float, *, positive: bool) -> float:
    L = float(limit)
    if not (np.isfinite(L) and (L > 0 if positive else L >= 0)):
        raise ValueError(f"limit must be finite and {'> 0' if positive else '≥ 0'}, got {limit!r}")
    return L


def power_law(value: np.ndarray, limit: float, *, power: int) -> LawResult:
    """A magnitude ≥ 0 that goes as k^−power under time scaling: k = (value / limit)^(1/power)."""
    L = _limit(limit, positive=True)
    v = np.asarray(value, dtype=float).reshape(-1)
    if np.any(v < 0):
        raise ValueError("power_law: values are magnitudes (≥ 0)")
    ratio = v / L
    return LawResult(value=v, static_value=np.zeros_like(v), ratio=ratio,
                     time_scale=ratio ** (1.0 / power), limit=L)


def speed_law(speed: np.ndarray, limit: float) -> LawResult:
    """Linear or angular speed (m/s, rad/s) ≤ limit; speeds go as 1/k, so k = v / v_max."""
    return power_law(speed, limit, power=1)


def acceleration_law(value: np.ndarray, limit: float) -> LawResult:
    """A value that goes as s = 1/k² ≤ limit: linear acceleration (m/s², gravity excluded),
    kinetic energy and transferred energy (J; m_u does not change with k). k = √(value/limit)."""
    return power_law(value, limit, power=2)


def _norm_time_scale(a: np.ndarray, b: np.ndarray, L: float) -> np.ndarray:
    """Per row, smallest k with |a + s·b| ≤ L for every s ∈ (0, 1/k²].

    |a + s·b|² − L² = A s² + 2B s + C (A = |b|², B = a·b, C = |a|² − L²) is convex in s, so the
    feasible s form one interval; it contains (0, ε] only if C ≤ 0 (and B < 0 when C = 0). Then
    s_max is the larger root, in the cancellation-free form for the sign of B.
    """
    A = np.einsum("ij,ij->i", b, b)
    B = np.einsum("ij,ij->i", a, b)
    an = np.linalg.norm(a, axis=1)
    C = (an - L) * (an + L)
    k = np.full(len(a), np.inf)
    k[(C <= 0) & (A == 0)] = 0.0
    m = (C <= 0) & (A > 0)
    Am, Bm, Cm = A[m], B[m], C[m]
    sq = np.sqrt(Bm * Bm - Am * Cm)                   # C ≤ 0: no cancellation under the root
    with np.errstate(divide="ignore", invalid="ignore"):
        s_max = np.where(Bm <= 0, (sq - Bm) / Am, -Cm / (Bm + sq))
    # s_max = 0 (C = 0: tangent, or leaving at once; also −0.0): no s > 0 is feasible
    k[m] = np.where(s_max > 0, 1.0 / np.sqrt(np.where(s_max > 0, s_max, 1.0)), np.inf)
    return k


def norm_law(static: np.ndarray, dynamic: np.ndarray, limit: float) -> LawResult:
    """|static + s·dynamic| ≤ limit per sample (N×d vectors): the base force and moment, the
    grasp's tangential force. At k = 1, s = 1; the still pose is s → 0. A sample already over the
    limit in the still pose gets k = inf (no slowdown helps), even where a band of k in between
    would be feasible (a dynamic term opposing gravity)."""
    L = _limit(limit, positive=False)
    a = np.atleast_2d(np.asarray(static, dtype=float))
    b = np.atleast_2d(np.asarray(dynamic, dtype=float))
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"norm_law: static {a.shape} and dynamic {b.shape} must be equal N×d")
    ok = _finite_rows(a, b)
    value = np.linalg.norm(a + b, axis=1)
    static_value = np.linalg.norm(a, axis=1)
    k = np.full(len(a), np.nan)
    k[ok] = _norm_time_scale(a[ok], b[ok], L)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(value == 0, 0.0, value / L)
    value[~ok] = static_value[~ok] = ratio[~ok] = np.nan
    return LawResult(value=value, static_value=static_value, ratio=ratio, time_scale=k, limit=L)


# --- grasp ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GraspForce:
    """The force the grasp must supply to the payload, static + s·dynamic (N×3, N, in the grasp
    frame's axes)."""

    static: np.ndarray
    dynamic: np.ndarray


def gravity_in_frame(rotation: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """Gravity (3, root axes, m/s²) in each sample's frame axes: Rᵀ·g for frame-to-root rotations
    ``rotation`` (N×3×3)."""
    return np.einsum("nji,j->ni", np.asarray(rotation, dtype=float), np.asarray(gravity, float))


def payload_grasp_force(mass: float, com_acceleration: np.ndarray,
                        gravity: np.ndarray) -> GraspForce:
    """Force on a point-mass payload: m·(a_com − g) = −m·g + s·m·a_com.

    ``com_acceleration`` (N×3) is the classical acceleration of the payload's centre of mass
    point (J·q̈ + J̇·q̇, gravity excluded) and ``gravity`` (3 or N×3) gravity, both in the grasp
    frame's axes. a_com of the CoM *point* already holds the rigid-body terms of its offset from
    the frame origin (tangential α×r, centripetal ω×(ω×r)), and all of a_com scales with s. The
    payload is a point mass (as ``payload.*``): no rotational inertia, so no Iα + ω×Iω; the
    moment the grasp must supply (r×F, torsional slip) is not part of this force.
    """
    m = float(mass)
    if not (np.isfinite(m) and m >= 0):
        raise ValueError(f"payload mass must be finite and ≥ 0, got {mass!r}")
    a = np.atleast_2d(np.asarray(com_acceleration, dtype=float))
    g = np.broadcast_to(np.asarray(gravity, dtype=float), a.shape)
    return GraspForce(static=-m * g, dynamic=m * a)


def grasp_slip_law(force: GraspForce, *, normal_axis: np.ndarray, limit: float) -> LawResult:
    """Friction cone: the component of the grasp force perpendicular to the grip's normal axis
    ≤ ``limit`` = μ·grip_force·faces (N). The normal component is the gripper's to carry."""
    n = np.asarray(normal_axis, dtype=float)
    if n.shape != (3,) or not (np.all(np.isfinite(n)) and np.any(n)):
        raise ValueError(f"grasp_slip_law: normal_axis must be a finite nonzero 3-vector, got {n}")
    n = n / np.linalg.norm(n)

    def tangential(f: np.ndarray) -> np.ndarray:
        f = np.atleast_2d(np.asarray(f, dtype=float))
        return f - np.outer(f @ n, n)

    return norm_law(tangential(force.static), tangential(force.dynamic), limit)


# --- tipping -------------------------------------------------------------------------------------

def _tipping_time_scale(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Per row, smallest k with alpha + s·beta ≥ 0 (> 0 in column 0, the normal force) in every
    column for every s ∈ (0, 1/k²]: each column holds near s = 0⁺ iff alpha > 0 or (alpha = 0 and
    beta ≥ 0; beta > 0 for the strict column); then it bounds s by alpha / −beta where beta < 0."""
    near0 = (alpha > 0) | ((alpha == 0) & (beta >= 0))
    near0[:, 0] = (alpha[:, 0] > 0) | ((alpha[:, 0] == 0) & (beta[:, 0] > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(beta < 0, alpha / -beta, np.inf)
        s_max = bound.min(axis=1)
        k = np.where(np.isinf(s_max), 0.0, 1.0 / np.sqrt(s_max))
    return np.where(near0.all(axis=1), k, np.inf)


def tipping_law(reaction: ScaledWrench, *, polygon: SupportPolygon, base_mass: float,
                base_com: np.ndarray, gravity: np.ndarray) -> TippingResult:
    """Centre of pressure on the floor (the root z = 0 plane) inside ``polygon``.

    ``reaction``: the wrench the base exerts on the robot at the root origin, root axes (a robot
    at rest: its weight, upward). The base (``base_mass`` kg at ``base_com``, root frame) stands
    still, so the floor pushes on it with F = F_r − m_b·g, M = M_r − c_b × m_b·g (about the root
    origin); the normal force is N = F_z and the centre of pressure p = (−M_y, M_x) / N. Gravity
    must be along −z (see task_limits.check_tipping_gravity). With P = N·p, each edge gives
    b_i·N − n_i·P ≥ 0, linear in s while N > 0. Floor friction (sliding) is not checked.
    ``ratio`` is the ``tipping_ratio`` gauge (inf at lift-off, N ≤ 0).
    """
    Fs, Fd, Ms, Md = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (
        reaction.force_static, reaction.force_dynamic, reaction.moment_static,
        reaction.moment_dynamic))
    if not Fs.shape == Fd.shape == Ms.shape == Md.shape or Fs.shape[1:] != (3,):
        raise ValueError("tipping_law: the reaction's four parts must be N×3 each")
    weight = float(base_mass) * np.asarray(gravity, dtype=float)
    Fs = Fs - weight
    Ms = Ms - np.cross(np.asarray(base_com, dtype=float), weight)
    ok = _finite_rows(Fs, Fd, Ms, Md)

    def normal_and_moment(F: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return F[:, 2], np.column_stack([-M[:, 1], M[:, 0]])      # N, P = N·p

    Ns, Ps = normal_and_moment(Fs, Ms)
    Nd, Pd = normal_and_moment(Fd, Md)
    alpha = np.column_stack([Ns, Ns[:, None] * polygon.offsets - Ps @ polygon.normals.T])
    beta = np.column_stack([Nd, Nd[:, None] * polygon.offsets - Pd @ polygon.normals.T])
    k = np.full(len(Fs), np.nan)
    k[ok] = _tipping_time_scale(alpha[ok], beta[ok])

    def gauge(N: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        up = N > 0
        cop = np.full(P.shape, np.nan)
        cop[up] = P[up] / N[up, None]
        g = np.full(len(N), np.inf)
        g[up] = polygon.gauge(cop[up])
        g[~ok] = np.nan
        return g, cop

    ratio, cop = gauge(Ns + Nd, Ps + Pd)
    static_ratio, _ = gauge(Ns, Ps)
    normal = np.where(ok, Ns + Nd, np.nan)
    return TippingResult(value=ratio, static_value=static_ratio, ratio=ratio.copy(), time_scale=k,
                         limit=1.0, centre_of_pressure=cop, normal_force=normal)
