"""The press scene: the Panda's hand pressed on a table, shared by the physics check, tests and demo.

The table is the shipped ``config/press_scene.yaml`` (a test checks the file parses to
:data:`PRESS_SCENE`). The press is planned with a damped least-squares IK on MuJoCo's own
kinematics: from the 'ready' pose the tool point (``panda_hand_tcp``) goes to ``approach_height_m``
above the table top at x = ``x_m``, keeping the ready orientation (fingers down), then straight
down to ``press_depth_m`` below the top face; the joint controller holding that unreachable reference
is what presses the fingers onto the table.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from dyn_node.core.robot.model import RobotModel
from dyn_node.errors import ModelError
from dyn_node.sim.contact_truth import ContactTruth
from dyn_node.sim.scene import Scene, SceneObject
from dyn_node.sim.simulator import Simulator

#: Panda 'ready' (rad, model order), the demo's start pose: nothing touches the table there.
READY = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
TABLE_TOP_Z = 0.40
PRESS_SCENE = Scene(
    objects=(SceneObject(name="table", type="box", size=(0.4, 0.8, 0.4), position=(0.6, 0.0, 0.2),
                         quat_xyzw=(0.0, 0.0, 0.0, 1.0), friction=(0.8, 0.005, 0.0001)),),
    collide_links=("panda_link5", "panda_link6", "panda_link7", "panda_link8", "panda_hand",
                   "panda_leftfinger", "panda_rightfinger"),
    source="dyn_node.sim.press.PRESS_SCENE")
TOOL = "panda_hand_tcp"


@dataclass(frozen=True)
class PressPlan:
    """Joint-space waypoints (model order) and their times from the start (s)."""

    q_ready: np.ndarray
    q_approach: np.ndarray
    q_press: np.ndarray
    t_approach: float
    t_press: float

    def waypoints(self) -> tuple[list[float], list[list[float]], list[list[float]]]:
        """(times, positions, velocities) for :meth:`Simulator.execute`: cubic, at rest at each."""
        zero = [0.0] * len(self.q_ready)
        return ([self.t_approach, self.t_press], [self.q_approach.tolist(), self.q_press.tolist()],
                [zero, zero])


def solve_ik(sim: Simulator, body: str, position: np.ndarray, rotation: np.ndarray,
             q_init: np.ndarray, *, iterations: int = 200, tol: float = 1e-10) -> np.ndarray:
    """q placing ``body`` at (position, rotation) in the world, by damped least squares on
    MuJoCo's body Jacobian; ModelError (``ik_failed``) when it does not converge."""
    mj, robot = sim.mj, sim.robot
    d = mujoco.MjData(mj)
    b = mj.body(body).id
    q = np.asarray(q_init, dtype=float).copy()
    jp, jr = np.zeros((3, mj.nv)), np.zeros((3, mj.nv))
    for _ in range(iterations):
        robot.set_state(d, q)
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        R = d.xmat[b].reshape(3, 3)
        err = np.concatenate([position - d.xpos[b],
                              0.5 * sum(np.cross(R[:, k], rotation[:, k]) for k in range(3))])
        if np.linalg.norm(err) < tol:
            return q
        mujoco.mj_jacBody(mj, d, jp, jr, b)
        J = np.vstack([jp, jr])[:, robot.dof_ids]
        q = q + J.T @ np.linalg.solve(J @ J.T + 1e-8 * np.eye(6), err)
    raise ModelError(f"IK for {body} at {position.tolist()} did not converge", code="ik_failed")


def plan_press(sim: Simulator, *, x_m: float = 0.5, approach_height_m: float = 0.03,
               press_depth_m: float = 0.005, t_approach: float = 1.5, t_press: float = 2.5) -> PressPlan:
    """The press from READY on ``sim`` (its model must be the Panda)."""
    q0 = np.asarray(READY, dtype=float)
    d = mujoco.MjData(sim.mj)
    sim.robot.set_state(d, q0)
    mujoco.mj_kinematics(sim.mj, d)
    b = sim.mj.body(TOOL).id
    R = d.xmat[b].reshape(3, 3).copy()
    above = solve_ik(sim, TOOL, np.array([x_m, 0.0, TABLE_TOP_Z + approach_height_m]), R, q0)
    press = solve_ik(sim, TOOL, np.array([x_m, 0.0, TABLE_TOP_Z - press_depth_m]), R, above)
    return PressPlan(q_ready=q0, q_approach=above, q_press=press, t_approach=t_approach, t_press=t_press)


@dataclass(frozen=True)
class Balance:
    """Static balance of a held press (N·m, model order): ``contact_torque`` = Σ J_linkᵀ·W_link
    (Pinocchio's LOCAL frame Jacobians, the truth's link wrenches), ``actuator_torque`` the
    applied τ, ``gravity_torque`` g(q); at rest contact + actuator = gravity."""

    contact_torque: np.ndarray
    actuator_torque: np.ndarray
    gravity_torque: np.ndarray

    @property
    def residual_rel(self) -> float:
        """max|Σ Jᵀ·W + τ − g| ÷ max|g|."""
        r = self.contact_torque + self.actuator_torque - self.gravity_torque
        return float(np.abs(r).max() / max(np.abs(self.gravity_torque).max(), 1e-12))


def static_balance(model: RobotModel, q: np.ndarray, tau: np.ndarray, truth: ContactTruth) -> Balance:
    """:class:`Balance` of ``truth`` (a :class:`~dyn_node.sim.contact_truth.ContactTruth`) at q
    under actuator torque ``tau``, with Pinocchio (not MuJoCo) kinematics and gravity."""
    pm = model.pin_model
    data = pm.createData()
    pin.computeJointJacobians(pm, data, q)
    pin.framesForwardKinematics(pm, data, q)
    tau_c = np.zeros(model.nv)
    for w in truth.link_wrenches:
        J = pin.getFrameJacobian(pm, data, pm.getFrameId(w.link), pin.ReferenceFrame.LOCAL)
        tau_c += J.T @ w.wrench
    g = pin.computeGeneralizedGravity(pm, data, q)
    return Balance(contact_torque=tau_c, actuator_torque=np.asarray(tau, float), gravity_torque=np.asarray(g))
