"""MuJoCo's mj_inverse on the same robot: damping, armature and friction loss zeroed, contacts and
all constraints off, so it computes the same rigid-body inverse dynamics as RNEA. The MJCF comes
from ``dyn_node.sim.mujoco_model`` (the simulator's URDF loader, which compiles point-mass links by
adding and then removing a small inertia, so the compiled model keeps the URDF's inertias).
"""
from __future__ import annotations

import mujoco
import numpy as np

from dyn_node.sim import mujoco_model


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
        robot = mujoco_model.mujoco_from_model(model, damping=False, armature=False, contacts=False)
        self.mj = _zeroed(robot.model, np.asarray(model.pin_model.gravity.linear, dtype=float))
        self.data = robot.make_data()
        self._robot = robot
        self.source = "dyn_node.sim.mujoco_model"

    def rnea(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        return mujoco_model.inverse_dynamics(self._robot, q, v, a, self.data)
