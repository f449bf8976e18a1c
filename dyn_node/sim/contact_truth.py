"""The contact truth of a MuJoCo step: robot–scene contacts and the wrench they put on each link.

MuJoCo's contact frame has its first row along the normal from geom1 to geom2, and
``mj_contactForce`` gives the force geom1 exerts on geom2 in that frame; the force in the
world is ``frameᵀ·f``. Here every contact is re-expressed from the robot's side: ``body1`` the
robot link, ``body2`` the scene object, the normal from body1 towards body2, the force (and
torsional/rolling torque, zero with condim 3) ON body1 from body2. Base frame = MuJoCo's world
(the URDF root link is placed at the world origin). The arrays are those of the last
``mj_forward``/``mj_step`` (``mj_step`` computes contacts at the state it starts from).
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class Contact:
    """One active robot–scene contact; vectors in the base frame (m, unit, N, N·m)."""

    body1: str
    body2: str
    position: np.ndarray
    normal: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    penetration_depth: float


@dataclass(frozen=True)
class LinkWrench:
    """Summed contact wrench on ``link``: ``force`` (N) and ``torque`` (N·m) about the link's
    origin, in the link's axes (as ``~/external_wrench`` and ``~/apply_wrench``)."""

    link: str
    force: np.ndarray
    torque: np.ndarray

    @property
    def wrench(self) -> np.ndarray:
        return np.concatenate([self.force, self.torque])


@dataclass(frozen=True)
class ContactTruth:
    contacts: tuple[Contact, ...]
    link_wrenches: tuple[LinkWrench, ...]

    @property
    def active(self) -> bool:
        return bool(self.contacts)

    @property
    def max_penetration_m(self) -> float:
        return max((c.penetration_depth for c in self.contacts), default=0.0)

    @property
    def normal_force_n(self) -> float:
        """Total force component along the normals, pressing the robot out of the scene (N)."""
        return float(sum(-c.force @ c.normal for c in self.contacts))

    def link(self, name: str) -> LinkWrench | None:
        return next((w for w in self.link_wrenches if w.link == name), None)


def scene_geom_ids(mj: mujoco.MjModel, names: tuple[str, ...]) -> frozenset[int]:
    """MuJoCo geom ids of the scene objects (named after them)."""
    return frozenset(mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names)


def contact_truth(mj: mujoco.MjModel, data: mujoco.MjData, scene_geoms: frozenset[int]) -> ContactTruth:
    """Every active contact between a robot geom and a scene geom (ids ``scene_geoms``)."""
    contacts: list[Contact] = []
    sums: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    f6 = np.zeros(6)
    for i in range(data.ncon):
        c = data.contact[i]
        g1, g2 = int(c.geom1), int(c.geom2)
        if (g1 in scene_geoms) == (g2 in scene_geoms) or c.efc_address < 0:
            continue  # not robot–scene, or excluded from the solver (no force)
        robot_is_1 = g2 in scene_geoms
        frame = c.frame.reshape(3, 3)
        mujoco.mj_contactForce(mj, data, i, f6)
        sign = -1.0 if robot_is_1 else 1.0  # world force is on geom2; flip when the robot is geom1
        force, torque = sign * (frame.T @ f6[:3]), sign * (frame.T @ f6[3:])
        normal = -sign * frame[0]
        rg, sg = (g1, g2) if robot_is_1 else (g2, g1)
        body = int(mj.geom_bodyid[rg])
        pos = c.pos.copy()
        contacts.append(Contact(body1=mj.body(body).name, body2=mj.geom(sg).name, position=pos,
                                normal=normal.copy(), force=force, torque=torque,
                                penetration_depth=float(-c.dist)))
        # moment about the body's origin (a URDF link origin: every link is a MuJoCo body)
        f_sum, m_sum = sums.get(body, (np.zeros(3), np.zeros(3)))
        sums[body] = (f_sum + force, m_sum + np.cross(pos - data.xpos[body], force) + torque)
    wrenches = []
    for body, (f, m) in sums.items():
        R = data.xmat[body].reshape(3, 3)
        wrenches.append(LinkWrench(link=mj.body(body).name, force=R.T @ f, torque=R.T @ m))
    return ContactTruth(contacts=tuple(contacts), link_wrenches=tuple(wrenches))
