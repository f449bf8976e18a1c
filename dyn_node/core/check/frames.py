"""Batched frame motion, task torque, joint-space inertia, energy and base wrench over N states.

Pinocchio's Python API has no batched Jacobian or mass matrix, so these quantities, which the
frame, energy, base and grasp constraints need at every trajectory sample, come from one
compiled pass (:func:`dyn_node.core.compiled.frame_kernels.frame_rows`) over tables built here from
Pinocchio's model. Units SI; vectors of a frame in world axes (Pinocchio's
LOCAL_WORLD_ALIGNED); the base wrench in the URDF root link's axes at its origin (or in those
of a frame fixed to it).
"""
from __future__ import annotations

import difflib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from dyn_node.core.robot.dynamics import joint_axis
from dyn_node.errors import InputError, ModelError
from dyn_node.core.robot.model import RobotModel


@dataclass(frozen=True)
class FramePoint:
    """A point to follow: ``frame`` (a URDF link or any Pinocchio frame of the model),
    ``point`` the offset in the frame's axes (m), ``wrench`` [force (N); torque (N·m)] in the
    frame's axes at its origin, whose joint torque J_localᵀ·wrench is reported
    (:attr:`FrameTerms.task_torque`)."""

    frame: str
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wrench: tuple[float, float, float, float, float, float] = (0.0,) * 6


@dataclass(frozen=True)
class FrameTerms:
    """One :class:`FramePoint` over N states (N×3 world axes unless said).

    ``linear_velocity`` J_v·q̇ (m/s) and ``linear_acceleration`` J_v·q̈ + J̇_v·q̇ (m/s², the
    classical acceleration, no gravity) are the point's; ``angular_velocity`` (rad/s) and
    ``angular_acceleration`` (rad/s²) the frame's; ``rotation`` (N×3×3) the frame-to-world
    rotation (Pinocchio's oMf). ``task_torque`` (N×nv, N·m|N) is
    J_localᵀ·wrench. ``effective_mass`` (N, kg) is m_u = 1/(uᵀJ_vM⁻¹J_vᵀu) along the direction
    of motion u = v/|v|, defined as 0 where the point is still (|v| = 0: the energy ½·m_u·v²
    is then 0 whatever the direction, and stays 0 under any time scaling), NaN only where M(q)
    is not positive definite (a chain of massless links); None unless the inertia terms were
    asked for."""

    frame: str
    point: np.ndarray
    position: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    angular_acceleration: np.ndarray
    rotation: np.ndarray
    task_torque: np.ndarray
    effective_mass: np.ndarray | None
    #: J_c·M⁻¹·J_vᵀu (N×3, 1/kg; 0 where the point is still) with J_c the linear Jacobian of
    #: the kinematics' ``couple_point``: with :attr:`InertiaTerms.couple_inertia` it gives m_u
    #: for a point mass added there (:meth:`effective_mass_with`); None unless asked for
    coupling: np.ndarray | None = None

    def effective_mass_with(self, mass: float, couple_inertia: np.ndarray) -> np.ndarray:
        """m_u (N, kg) with ``mass`` kg more at the couple point: Woodbury's identity,
        1/m_u' = 1/m_u − Δm·cᵀ(I + Δm·Λ)⁻¹c (c = :attr:`coupling`, Λ = J_cM⁻¹J_cᵀ)."""
        if self.coupling is None or self.effective_mass is None:
            raise ValueError("effective_mass_with needs the inertia terms and a couple_point")
        c, m_u = self.coupling, self.effective_mass
        A = np.eye(3) + mass * couple_inertia
        x = np.linalg.solve(A, c[..., None])[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / m_u - mass * np.einsum("ij,ij->i", c, x)
            return np.where(m_u > 0, 1.0 / inv, m_u)

    @property
    def speed(self) -> np.ndarray:
        """|J_v·q̇| (N, m/s)."""
        return np.linalg.norm(self.linear_velocity, axis=1)

    @property
    def transferred_energy(self) -> np.ndarray:
        """½·m_u·|v|² (N, J); needs the inertia terms."""
        if self.effective_mass is None:
            raise ValueError("transferred_energy needs the inertia terms (inertia=True)")
        from dyn_node.core.compiled import law_kernels  # compiled: ~5× NumPy's einsum

        return 0.5 * self.effective_mass * law_kernels.row_squares(self.linear_velocity, False)


@dataclass(frozen=True)
class InertiaTerms:
    """``kinetic_energy`` ½·q̇ᵀMq̇ (N, J), ``gravity_torque`` g(q) (N×nv, N·m|N: the
    generalized gravity, a by-product of the CRBA's subtree sums) and, when asked for,
    ``mass_matrix`` M(q) (N×nv×nv, kg·m², armature on the diagonal when included; else
    None)."""

    kinetic_energy: np.ndarray
    gravity_torque: np.ndarray
    mass_matrix: np.ndarray | None
    #: J_c·M⁻¹·J_cᵀ (N×3×3, 1/kg) at the couple point (see FrameTerms.coupling), or None
    couple_inertia: np.ndarray | None = None


@dataclass(frozen=True)
class BaseWrench:
    """The wrench [force (N); moment (N·m)] the mounting exerts ON the robot at ``frame``'s
    origin, in its axes (the mounting is loaded with the opposite), N×6. ``frame``: the URDF
    root link, or another frame fixed to it (:class:`FrameKinematics`'s ``base_frame``).

    ``static``: gravity alone (q̇ = q̈ = 0); ``dynamic``: the momentum rate dh/dt of the states
    as given, quadratic in q̇ and linear in q̈, so a trajectory stretched in time by k has
    ``static + dynamic/k²`` (:meth:`at`). Joint friction and armature are internal to the
    robot and do not enter. ``mass`` (kg) and ``com`` (N×3, root axes) cover every body the
    mounting carries (payload and the root link included), ``com`` in ``frame``'s axes from
    its origin."""

    frame: str
    static: np.ndarray
    dynamic: np.ndarray
    mass: float
    com: np.ndarray

    def at(self, k: float = 1.0) -> np.ndarray:
        """The wrench with the trajectory stretched by k (s = 1/k²)."""
        return self.static + self.dynamic / (k * k)


@dataclass(frozen=True)
class FrameBatch:
    """What :meth:`FrameKinematics.compute` returns: one :class:`FrameTerms` per configured
    frame point (in order), and the inertia and base terms when asked for (else None)."""

    frames: tuple[FrameTerms, ...]
    inertia: InertiaTerms | None
    base: BaseWrench | None
    #: every frame's ``rotation`` in one F×N×3×3 array (the frames' are views of it)
    rotations: np.ndarray | None = None
    #: J_uᵀ·(a_u − g) (N×nv column-major, N·m|N per kg): the joint torque of 1 kg more at the
    #: kinematics' ``unit_mass_point`` u; None unless asked for
    unit_mass_torque: np.ndarray | None = None
    #: (rigid-body RNEA τ incl. armature·q̈, g(q)), each N×nv row-major (N·m|N), from the same
    #: pass; None unless asked for (``rnea=True``)
    rnea: tuple[np.ndarray, np.ndarray] | None = None

    def frame(self, name: str) -> FrameTerms:
        """The first terms of frame ``name``."""
        for f in self.frames:
            if f.frame == name:
                return f
        raise KeyError(name)


@dataclass(frozen=True)
class JointTables:
    """The model arrays of :func:`dyn_node.core.compiled.frame_kernels.frame_rows` (see there)."""

    parent: np.ndarray
    revolute: np.ndarray
    index: np.ndarray
    placement: np.ndarray
    axis: np.ndarray
    inertia: np.ndarray
    armature: np.ndarray
    gravity: np.ndarray
    root: np.ndarray


def _sym33(x: np.ndarray) -> np.ndarray:
    """N×3×3 symmetric matrices from their (xx, xy, xz, yy, yz, zz) rows."""
    return x[:, [[0, 1, 2], [1, 3, 4], [2, 4, 5]]]


def _inertia_row(Y: pin.Inertia) -> list[float]:
    I = np.asarray(Y.inertia)
    return [Y.mass, *np.asarray(Y.lever), I[0, 0], I[0, 1], I[0, 2], I[1, 1], I[1, 2], I[2, 2]]


def _se3_row(M: pin.SE3) -> np.ndarray:
    return np.concatenate([np.asarray(M.rotation).reshape(9), np.asarray(M.translation)])


def joint_tables(pm: pin.Model, root_frame: str) -> JointTables:
    """Tables of a model of one-DoF revolute and prismatic joints; ``root_frame`` the frame on
    the world whose origin and axes the base wrench is given in. Raises :class:`ModelError` for
    any other joint kind."""
    n = pm.njoints
    revolute = np.zeros(n, dtype=bool)
    index = np.zeros(n, dtype=np.int64)
    placement = np.zeros((n, 12))
    axis = np.zeros((n, 3))
    inertia = np.zeros((n, 10))
    for i in range(n):
        inertia[i] = _inertia_row(pm.inertias[i])
        if i == 0:
            continue
        found = joint_axis(pm.joints[i])
        if found is None:
            raise ModelError(f"joint '{pm.names[i]}' is a {pm.joints[i].shortname()}; the frame "
                             "kernels take one-DoF revolute and prismatic joints",
                             code="urdf_joint_type")
        revolute[i], axis[i] = found
        index[i] = pm.joints[i].idx_v
        placement[i] = _se3_row(pm.jointPlacements[i])
    fid = pm.getFrameId(root_frame)
    if fid >= len(pm.frames) or pm.frames[fid].parentJoint != 0:
        raise ModelError(f"base frame '{root_frame}' is not fixed to the root link (it moves "
                         "with a joint)", code="bad_frame")
    tables = JointTables(parent=np.array(pm.parents, dtype=np.int64), revolute=revolute,
                         index=index, placement=placement, axis=axis, inertia=inertia,
                         armature=np.array(pm.armature, dtype=float),
                         gravity=np.array(pm.gravity.linear, dtype=float),
                         root=_se3_row(pm.frames[fid].placement))
    for x in vars(tables).values():
        x.setflags(write=False)
    return tables


def root_link(urdf: str) -> str:
    """The URDF's root link: the one link that is no joint's child."""
    root = ET.fromstring(urdf)
    children = {j.find("child").get("link") for j in root.findall("joint")}
    roots = [link.get("name") for link in root.findall("link") if link.get("name") not in children]
    if len(roots) != 1:
        raise ModelError(f"the URDF has {len(roots)} root links ({', '.join(roots)}); expected 1",
                         code="urdf_root")
    return roots[0]


def _vector(value: Sequence[float], size: int, what: str) -> np.ndarray:
    try:
        x = np.array(value, dtype=float)
    except (TypeError, ValueError):
        x = np.full(1, np.nan)
    if x.shape != (size,) or not np.all(np.isfinite(x)):
        raise ModelError(f"{what} must be {size} finite numbers, got {value!r}",
                         code="bad_frame_point")
    return x


def _frame_id(pm: pin.Model, name: str) -> int:
    if not isinstance(name, str) or not pm.existFrame(name):
        names = [f.name for f in pm.frames]
        near = difflib.get_close_matches(str(name), names, n=1)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ModelError(f"frame '{name}' is not a link or frame of the model{hint}",
                         code="bad_frame")
    return pm.getFrameId(name)


class FrameKinematics:
    """Batched frame terms of one model and a fixed list of :class:`FramePoint`.

    ``include_armature``: armature (limits' reflected rotor inertia) on M's diagonal, so in the
    kinetic energy and the effective masses, as :class:`~dyn_node.core.robot.dynamics.DynamicsOptions`.
    ``base_frame``: where the base wrench is given (None: the URDF root link; else a frame
    fixed to it, e.g. a mounting flange). ``mass_points``: the indices of the points whose
    effective mass (and coupling) is computed (None: every point; the others' are None).
    ``unit_mass_point``: the point whose per-kg payload torque :meth:`compute` can give.
    Stateless after construction: :meth:`compute` may run in several threads at once.
    """

    def __init__(self, model: RobotModel, frames: Sequence[FramePoint] = (), *,
                 include_armature: bool = True, base_frame: str | None = None,
                 couple_point: int | None = None, mass_points: Sequence[int] | None = None,
                 unit_mass_point: int | None = None):
        pm = model.pin_model.copy()
        if not include_armature:
            pm.armature = np.zeros(pm.nv)
        self.root_link = root_link(model.urdf)
        self.base_frame = self.root_link if base_frame is None else base_frame
        _frame_id(pm, self.base_frame)
        self._tables = joint_tables(pm, self.base_frame)
        self._pm = pm
        self.nv = pm.nv
        self.points = tuple(frames)
        F = len(self.points)
        if couple_point is not None and not 0 <= couple_point < F:
            raise ValueError(f"couple_point {couple_point} is not one of the {F} frame points")
        self.couple_point = couple_point
        if unit_mass_point is not None and not 0 <= unit_mass_point < F:
            raise ValueError(f"unit_mass_point {unit_mass_point} is not one of the {F} points")
        self.unit_mass_point = unit_mass_point
        self._fmass = np.ones(F, dtype=bool) if mass_points is None else \
            np.isin(np.arange(F), np.asarray(mass_points, dtype=np.int64))
        self._fjoint = np.zeros(F, dtype=np.int64)
        self._fplace = np.zeros((F, 12))
        self._fpoint = np.zeros((F, 3))
        self._fwrench = np.zeros((F, 6))
        for f, spec in enumerate(self.points):
            fr = pm.frames[_frame_id(pm, spec.frame)]
            self._fjoint[f] = fr.parentJoint
            self._fplace[f] = _se3_row(fr.placement)
            self._fpoint[f] = _vector(spec.point, 3, f"point of frame '{spec.frame}'")
            self._fwrench[f] = _vector(spec.wrench, 6, f"wrench at frame '{spec.frame}'")
        # a point without a wrench has no task torque: no row, no Jacobian product
        wrenched = np.flatnonzero(np.any(self._fwrench != 0.0, axis=1))
        self._ftau = np.full(F, -1, dtype=np.int64)
        self._ftau[wrenched] = np.arange(len(wrenched))
        for x in (self._fjoint, self._fplace, self._fpoint, self._fwrench, self._fmass,
                  self._ftau):
            x.setflags(write=False)   # shared by concurrent compute() calls
        # every body's mass: the root link's and payload's included (Pinocchio keeps bodies
        # fixed to the world on joint 0)
        self.mass = float(self._tables.inertia[:, 0].sum())

    @property
    def base_placement(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, r): the base frame's rotation (3×3) and origin (3) in world axes."""
        root = self._tables.root
        return root[:9].reshape(3, 3), root[9:]

    def _states(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, ...]:
        out = []
        for name, X in (("q", Q), ("v", V), ("a", A)):
            X = np.asarray(X, dtype=float)
            if X.ndim != 2 or X.shape[1] != self.nv:
                raise InputError(f"{name} must be N×{self.nv} (one state per row), got shape "
                                 f"{X.shape}", code="length_mismatch")
            out.append(X)
        if not out[0].shape == out[1].shape == out[2].shape:
            raise InputError(f"q, v, a have different numbers of states ({len(out[0])}, "
                             f"{len(out[1])}, {len(out[2])})", code="length_mismatch")
        for name, X in zip("qva", out):
            if not np.isfinite(X).all():
                row = int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0])
                raise InputError(f"{name} is not finite in state {row}", code="non_finite")
        return tuple(out)

    def compute(self, Q: np.ndarray, V: np.ndarray, A: np.ndarray, *, inertia: bool = True,
                base: bool = True, mass_matrix: bool = False,
                unit_mass: bool = False, rnea: bool = False,
                couple: bool = True) -> FrameBatch:
        """Every frame point's terms over the N states Q, V, A (N×nv, model joint order);
        ``inertia``: also the kinetic energy and the effective masses (M(q) is formed per
        state either way; ``mass_matrix`` keeps it, N×nv×nv, and needs ``inertia``); ``base``:
        also the base wrench; ``unit_mass``: also :attr:`FrameBatch.unit_mass_torque` (needs
        a ``unit_mass_point``); ``rnea``: also :attr:`FrameBatch.rnea`; ``couple``: the
        ``couple_point``'s terms when it has one (only a payload margin reads them). Raises
        :class:`InputError` for wrong shapes or non-finite states."""
        from dyn_node.core.compiled import frame_kernels  # here, not at import: Numba only for batched checks

        if mass_matrix and not inertia:
            raise ValueError("mass_matrix=True needs inertia=True")
        if unit_mass and self.unit_mass_point is None:
            raise ValueError("unit_mass=True needs a unit_mass_point")

        Q, V, A = self._states(Q, V, A)
        N, nv, F = len(Q), self.nv, len(self.points)
        Ni, Nb = (N if inertia else 0), (N if base else 0)
        pos, vel, omega, acc, alpha = (np.empty((F, N, 3)) for _ in range(5))
        rot = np.empty((F, N, 9))
        Nc = Ni if self.couple_point is not None and couple else 0
        couple, couple_inertia = np.empty((F, Nc, 3)), np.empty((Nc, 6))
        tau = np.empty((int(np.count_nonzero(self._ftau >= 0)), N, nv))
        zero = np.broadcast_to(np.zeros(nv), (N, nv))
        mu = np.empty((F, Ni))
        M = np.empty((Ni if mass_matrix else 0, nv, nv))
        ke = np.empty(Ni)
        gq = np.empty((Ni, nv))
        ws, wd, com = np.empty((Nb, 6)), np.empty((Nb, 6)), np.empty((Nb, 3))
        unit = np.empty((nv, N if unit_mass else 0)).T      # column-major, as the torque terms
        trq, grv = (np.empty((N if rnea else 0, nv)) for _ in range(2))
        t = self._tables
        frame_kernels.frame_rows(Q, V, A, t.parent, t.revolute, t.index, t.placement, t.axis,
                                 t.inertia, t.armature, t.gravity, t.root, self._fjoint,
                                 self._fplace, self._fpoint, self._fwrench, self._fmass,
                                 self._ftau, -1 if Nc == 0 else self.couple_point,
                                 -1 if self.unit_mass_point is None else self.unit_mass_point,
                                 inertia, base, pos, vel, omega, acc, alpha, rot, tau, mu, couple,
                                 couple_inertia, M, ke, gq, ws, wd, com, unit, trq, grv)
        frames = tuple(FrameTerms(frame=p.frame, point=self._fpoint[f].copy(), position=pos[f],
                                  linear_velocity=vel[f], angular_velocity=omega[f],
                                  linear_acceleration=acc[f], angular_acceleration=alpha[f],
                                  rotation=rot[f].reshape(N, 3, 3),
                                  task_torque=tau[self._ftau[f]] if self._ftau[f] >= 0 else zero,
                                  effective_mass=mu[f] if inertia and self._fmass[f] else None,
                                  coupling=couple[f] if Nc and self._fmass[f] else None)
                       for f, p in enumerate(self.points))
        return FrameBatch(
            frames=frames,
            inertia=InertiaTerms(kinetic_energy=ke, gravity_torque=gq,
                                 mass_matrix=M if mass_matrix else None,
                                 couple_inertia=_sym33(couple_inertia) if Nc else None)
            if inertia else None,
            base=BaseWrench(frame=self.base_frame, static=ws, dynamic=wd, mass=self.mass,
                            com=com) if base else None, rotations=rot.reshape(F, N, 3, 3),
            unit_mass_torque=unit if unit_mass else None, rnea=(trq, grv) if rnea else None)
