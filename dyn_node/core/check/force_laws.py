"""Per-sample laws of the frame, energy, base-wrench, tipping and grasp constraints.

Each law takes per-sample arrays (kinematics and wrenches computed elsewhere) and returns a
:class:`LawResult`: the value at the given timing (k = 1), its ratio to the limit, and the
per-sample ``time_scale`` k: the smallest k such that the sample is feasible at every k′ ≥ k
(s = 1/k²; k′ ≥ k ⇔ s′ ∈ (0, s]). 0: feasible at any timing; inf: no slowdown helps. A
trajectory's share of ``time_scale`` for a kind is the largest per-sample k. Non-finite inputs
give NaN values, ratios and k (never a silent "feasible"). The per-sample loops of the power,
norm, grasp and tipping laws are compiled (:mod:`dyn_node.core.compiled.law_kernels`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dyn_node.core.compiled import law_kernels


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
        return np.maximum((d @ self.normals.T / self.reach).max(axis=-1), 0.0)

    @property
    def reach(self) -> np.ndarray:
        """Per edge, offset − normal·centroid: the centroid's distance to it (> 0: inside)."""
        return self.offsets - self.normals @ self.centroid


def _limit(limit: float, *, positive: bool) -> float:
    L = float(limit)
    if not (np.isfinite(L) and (L > 0 if positive else L >= 0)):
        raise ValueError(f"limit must be finite and {'> 0' if positive else '≥ 0'}, got {limit!r}")
    return L


def power_law(value: np.ndarray, limit: float, *, power: int) -> LawResult:
    """A magnitude ≥ 0 that goes as k^−power under time scaling: k = (value / limit)^(1/power)."""
    L = _limit(limit, positive=True)
    v = np.asarray(value, dtype=float).reshape(-1)
    ratio, k, negative = law_kernels.power_rows(v, L, int(power))
    if negative:
        raise ValueError("power_law: values are magnitudes (≥ 0)")
    return LawResult(value=v, static_value=np.zeros_like(v), ratio=ratio, time_scale=k, limit=L)


def speed_law(speed: np.ndarray, limit: float) -> LawResult:
    """Linear or angular speed (m/s, rad/s) ≤ limit; speeds go as 1/k, so k = v / v_max."""
    return power_law(speed, limit, power=1)


def acceleration_law(value: np.ndarray, limit: float) -> LawResult:
    """A value that goes as s = 1/k² ≤ limit: linear acceleration (m/s², gravity excluded),
    kinetic energy and transferred energy (J; m_u does not change with k). k = √(value/limit)."""
    return power_law(value, limit, power=2)


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
    # one compiled pass per row. |a + s·b|² − L² = A s² + 2B s + C (A = |b|², B = a·b,
    # C = |a|² − L²) is convex in s, so the feasible s form one interval; it contains (0, ε] only
    # if C ≤ 0 (and B < 0 when C = 0); then s_max is the larger root, cancellation-free
    value, static_value, ratio, k = law_kernels.norm_rows(a, b, L)
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
    R = np.asarray(rotation, dtype=float)
    return law_kernels.rotate_back(R.reshape(len(R), 9), np.asarray(gravity, float).reshape(1, 3))


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
    return norm_law(tangential(force.static, n), tangential(force.dynamic, n), limit)


def tangential(force: np.ndarray, normal_axis: np.ndarray) -> np.ndarray:
    """The component of each force (N×3) perpendicular to the unit ``normal_axis``."""
    f = np.atleast_2d(np.asarray(force, dtype=float))
    return law_kernels.tangential(f, np.asarray(normal_axis, dtype=float))


# --- tipping -------------------------------------------------------------------------------------

def base_weight(*, base_mass: float, base_com: np.ndarray, gravity: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The base's weight m_b·g (N) and its moment c_b × m_b·g about the root origin (N·m)."""
    w = float(base_mass) * np.asarray(gravity, dtype=float)
    c = np.asarray(base_com, dtype=float)
    # np.cross's formula, written out: np.cross costs more than the check's use of it
    return w, np.array([c[1] * w[2] - c[2] * w[1], c[2] * w[0] - c[0] * w[2],
                        c[0] * w[1] - c[1] * w[0]])


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
    weight, weight_moment = base_weight(base_mass=base_mass, base_com=base_com, gravity=gravity)
    p = polygon
    # one compiled pass: the edge columns [N, b_i·N − n_i·P], their time scale and the gauge per sample
    k, ratio, static_ratio, normal = law_kernels.tipping_rows(
        Fs, Fd, Ms, Md, weight, weight_moment, p.normals, p.offsets, p.centroid, p.reach)
    cop = law_kernels.centre_of_pressure(Fs, Fd, Ms, Md, weight, weight_moment)
    return TippingResult(value=ratio, static_value=static_ratio, ratio=ratio.copy(), time_scale=k,
                         limit=1.0, centre_of_pressure=cop, normal_force=normal)
