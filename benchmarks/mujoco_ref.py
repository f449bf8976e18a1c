"""MuJoCo's mj_inverse on the same robot: damping, armature and friction loss zeroed, contacts and
all constraints off, so it computes the same rigid-body inverse dynamics as RNEA. MuJoCo refuses
bodies without rotational inertia (the 2-link arm's point masses); for such a model only, principal
inertias are bounded below by 1e-12 kg·m², far under the 1e-9 N·m agreement tolerance at the states used.

Uses ``dyn_node.mujoco_model`` (mujoco_from_model + inverse_dynamics) when that module exists;
otherwise loads the model's URDF into MuJoCo here (visuals and collisions dropped, locked joints
made fixed).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np

_COMPILER = ('<mujoco><compiler discardvisual="true" fusestatic="false" balanceinertia="false" '
             'strippath="true" angle="radian"/></mujoco>')


def _urdf_for_mujoco(model, boundinertia: float = 0.0) -> str:
    root = ET.fromstring(model.urdf)
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for el in link.findall(tag):
                link.remove(el)
    for j in root.iter("joint"):
        name = j.get("name")
        if name in model.locked_joints:
            value = float(model.locked_joints[name])
            if value != 0.0:
                # A locked joint at a non-zero position would need its motion folded into the
                # origin; the built-in models lock at 0 only, so refuse rather than guess.
                raise ValueError(f"locked joint {name} at {value} != 0 is not supported here")
            j.set("type", "fixed")
        elif j.get("type") == "continuous":
            j.set("type", "revolute")
            lim = j.find("limit")
            if lim is None:
                lim = ET.SubElement(j, "limit", effort="0", velocity="0")
            lim.set("lower", "-1e10")
            lim.set("upper", "1e10")
    compiler = ET.fromstring(_COMPILER)
    if boundinertia:
        compiler.find("compiler").set("boundinertia", repr(boundinertia))
    root.insert(0, compiler)
    return ET.tostring(root, encoding="unicode")


def _zeroed(mj: mujoco.MjModel, gravity: np.ndarray) -> mujoco.MjModel:
    mj.dof_damping[:] = 0.0
    mj.dof_armature[:] = 0.0
    mj.dof_frictionloss[:] = 0.0
    mj.opt.gravity[:] = gravity
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    return mj


class MujocoInverse:
    """mj_inverse wrapped to take and return arrays in dyn_node's model joint order."""

    def __init__(self, model):
        self.source = "benchmarks/mujoco_ref.py URDF loader"
        self._helper = None
        try:
            from dyn_node import mujoco_model  # written by another helper; may be absent
        except ImportError:
            mujoco_model = None
        if mujoco_model is not None:
            robot = mujoco_model.mujoco_from_model(model, damping=False, armature=False,
                                                   contacts=False)
            self.mj = _zeroed(robot.model, np.asarray(model.pin_model.gravity.linear, dtype=float))
            self.data = robot.make_data()
            self._robot, self._helper = robot, mujoco_model.inverse_dynamics
            self.source = "dyn_node.mujoco_model"
            return
        try:
            mj = mujoco.MjModel.from_xml_string(_urdf_for_mujoco(model))
        except ValueError as exc:
            if "mass and inertia" not in str(exc):
                raise
            mj = mujoco.MjModel.from_xml_string(_urdf_for_mujoco(model, boundinertia=1e-12))
            self.source += " (inertia bounded at 1e-12 kg·m²)"
        self.mj = _zeroed(mj, np.asarray(model.pin_model.gravity.linear, dtype=float))
        self.data = mujoco.MjData(self.mj)
        qadr, dadr = [], []
        for name in model.joint_names:
            jid = mujoco.mj_name2id(self.mj, mujoco.mjtObj.mjOBJ_JOINT, name)
            if jid < 0:
                raise ValueError(f"MuJoCo model has no joint {name}")
            qadr.append(int(self.mj.jnt_qposadr[jid]))
            dadr.append(int(self.mj.jnt_dofadr[jid]))
        if self.mj.nv != len(dadr):
            raise ValueError(f"MuJoCo model has {self.mj.nv} DoF, dyn_node's has {len(dadr)}")
        self.qadr = np.array(qadr)
        self.dadr = np.array(dadr)

    def rnea(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        if self._helper is not None:
            return self._helper(self._robot, q, v, a, self.data)
        d = self.data
        d.qpos[self.qadr] = q
        d.qvel[self.dadr] = v
        d.qacc[self.dadr] = a
        mujoco.mj_inverse(self.mj, d)
        return d.qfrc_inverse[self.dadr].copy()
