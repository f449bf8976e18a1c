"""A MuJoCo model of a :class:`~dyn_node.core.robot.model.RobotModel`: independent oracle and simulator plant.

MuJoCo parses the same URDF text with its own parser and computes dynamics with its own
algorithms, so agreement with Pinocchio checks dyn_node's model loading against code we did not
write. How the URDF is adapted (meshes, locked joints, point masses, payload, constraints off)
and how indices map to model order: docs/SIMULATOR.md.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin

from dyn_node.errors import ModelError
from dyn_node.core.robot.model import RobotModel, example_robot_data_dir
from dyn_node.sim.scene import Scene, SolverSettings, add_scene

#: Inertia (kg·m²) temporarily added to near-singular inertia tensors so MuJoCo compiles them.
INERTIA_EPS = 1e-9
#: Principal inertia below which a link is treated as a point mass needing the eps patch.
_SMALL_INERTIA = 1e-12
_PAYLOAD_BODY = "dyn_node_payload"


@dataclass(frozen=True)
class MujocoRobot:
    """A compiled MuJoCo model plus index arrays in dyn_node model order.

    ``qpos_ids[i]``, ``dof_ids[i]``, ``actuator_ids[i]``, ``joint_ids[i]`` are the MuJoCo
    indices for model joint ``joint_names[i]``. The MjModel is mutable by MuJoCo's design; treat
    it as read-only once built (or copy it).
    """

    model: mujoco.MjModel
    joint_names: tuple[str, ...]
    joint_ids: np.ndarray
    qpos_ids: np.ndarray
    dof_ids: np.ndarray
    actuator_ids: np.ndarray
    patched_bodies: tuple[str, ...]

    @property
    def nv(self) -> int:
        return len(self.joint_names)

    def make_data(self) -> mujoco.MjData:
        return mujoco.MjData(self.model)

    def set_state(self, data: mujoco.MjData, q: np.ndarray, v: np.ndarray | None = None) -> None:
        """Write q (rad|m) and v (rad/s|m/s), model order, into ``data``; other DoFs are zeroed."""
        data.qpos[:] = self.model.qpos0
        data.qvel[:] = 0.0
        data.qpos[self.qpos_ids] = np.asarray(q, dtype=float)
        if v is not None:
            data.qvel[self.dof_ids] = np.asarray(v, dtype=float)

    def get_q(self, data: mujoco.MjData) -> np.ndarray:
        return data.qpos[self.qpos_ids].copy()

    def get_v(self, data: mujoco.MjData) -> np.ndarray:
        return data.qvel[self.dof_ids].copy()

    def get_qacc(self, data: mujoco.MjData) -> np.ndarray:
        return data.qacc[self.dof_ids].copy()

    def apply_torque(self, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Joint torques (N·m|N, model order) as generalized applied forces (not clamped)."""
        data.qfrc_applied[:] = 0.0
        data.qfrc_applied[self.dof_ids] = np.asarray(tau, dtype=float)

    def set_ctrl(self, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Joint torques through the motor actuators (clamped by effort limits if enabled)."""
        data.ctrl[self.actuator_ids] = np.asarray(tau, dtype=float)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    return pin.AngleAxis(angle, axis / np.linalg.norm(axis)).toRotationMatrix()


def _bake_lock(joint: ET.Element, value: float) -> None:
    """Turn ``joint`` into a fixed joint whose origin includes the locked displacement."""
    origin = joint.find("origin")
    xyz = np.array([float(x) for x in (origin.get("xyz", "0 0 0") if origin is not None
                                       else "0 0 0").split()])
    rpy = np.array([float(x) for x in (origin.get("rpy", "0 0 0") if origin is not None
                                       else "0 0 0").split()])
    axis_el = joint.find("axis")
    axis = np.array([float(x) for x in (axis_el.get("xyz", "1 0 0") if axis_el is not None
                                        else "1 0 0").split()])
    R = pin.rpy.rpyToMatrix(rpy)
    if joint.get("type") == "prismatic":
        xyz = xyz + R @ (axis / np.linalg.norm(axis) * value)
    elif value != 0.0:
        rpy = pin.rpy.matrixToRpy(R @ _rot(axis, value))
    if origin is None:
        origin = ET.SubElement(joint, "origin")
    origin.set("xyz", " ".join(repr(float(x)) for x in xyz))
    origin.set("rpy", " ".join(repr(float(x)) for x in rpy))
    joint.set("type", "fixed")
    for tag in ("axis", "limit", "mimic", "dynamics", "safety_controller", "calibration"):
        for el in joint.findall(tag):
            joint.remove(el)


def _patch_inertia(link: ET.Element) -> bool:
    """Add INERTIA_EPS·I to a link's near-singular inertia; True if patched."""
    inertial = link.find("inertial")
    if inertial is None:
        return False
    mass_el = inertial.find("mass")
    if mass_el is None or float(mass_el.get("value", "0")) <= 0.0:
        return False
    inertia = inertial.find("inertia")
    if inertia is None:
        inertia = ET.SubElement(inertial, "inertia")
    keys = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    v = {k: float(inertia.get(k, "0")) for k in keys}
    I = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]],
                  [v["ixz"], v["iyz"], v["izz"]]])
    if np.linalg.eigvalsh(I).min() >= _SMALL_INERTIA:
        return False
    for k in ("ixx", "iyy", "izz"):
        inertia.set(k, repr(v[k] + INERTIA_EPS))
    for k in ("ixy", "ixz", "iyz"):
        inertia.set(k, repr(v[k]))
    return True


def mujoco_urdf(model: RobotModel, contacts: bool = False) -> tuple[str, tuple[str, ...]]:
    """The URDF text MuJoCo compiles, and the links whose inertia got the eps patch."""
    root = ET.fromstring(model.urdf)
    for child in list(root):
        if child.tag not in ("link", "joint"):
            root.remove(child)  # transmissions, gazebo and material tags are not dynamics
    for link in root.findall("link"):
        for v in link.findall("visual"):
            link.remove(v)
        for c in link.findall("collision"):
            geom = c.find("geometry")
            mesh = geom.find("mesh") if geom is not None else None
            path = resolve_mesh(mesh.get("filename", "")) if contacts and mesh is not None else None
            if not contacts or geom is None or (mesh is not None and path is None):
                link.remove(c)
            elif path is not None:
                mesh.set("filename", path)
    for joint in root.findall("joint"):
        if joint.get("name") in model.locked_joints:
            _bake_lock(joint, float(model.locked_joints[joint.get("name")]))
    patched = tuple(link.get("name") for link in root.findall("link") if _patch_inertia(link))
    if contacts:
        # absolute mesh paths: MuJoCo's URDF reader would otherwise keep only the file name
        ET.SubElement(ET.SubElement(root, "mujoco"), "compiler", strippath="false")
    return ET.tostring(root, encoding="unicode"), patched


def resolve_mesh(filename: str) -> str | None:
    """An existing STL/OBJ file for a URDF mesh reference, or None (the collision is dropped).

    ``package://example-robot-data/...`` resolves into example-robot-data's install, other
    ``package://PKG/...`` through the ament index when ROS is sourced; ``file://`` and absolute
    paths as they are. MuJoCo reads STL and OBJ only (not COLLADA .dae).
    """
    if not filename.lower().endswith((".stl", ".obj")):
        return None
    path: Path | None = None
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://"):].partition("/")
        if pkg == "example-robot-data":
            path = example_robot_data_dir().parent / rest
        else:
            try:
                from ament_index_python.packages import get_package_share_directory
                path = Path(get_package_share_directory(pkg)) / rest
            except Exception:  # not installed, or ROS not sourced: no mesh
                path = None
    elif filename.startswith("file://"):
        path = Path(filename[len("file://"):])
    elif Path(filename).is_absolute():
        path = Path(filename)
    return str(path) if path is not None and path.is_file() else None


def mujoco_from_model(model: RobotModel, *, damping: bool = True, armature: bool = True,
                      frictionloss: bool = False, contacts: bool = False,
                      joint_limits: bool = False, effort_limits: bool = False,
                      payload: bool = True, timestep: float = 0.001, scene: Scene | None = None,
                      solver: SolverSettings | None = None) -> MujocoRobot:
    """Compile ``model``'s URDF with MuJoCo (see the module docstring for every adaptation).

    ``damping``: URDF viscous damping (N·m·s/rad) on; ``armature``: limits' armature (kg·m²) on;
    ``frictionloss``: URDF Coulomb friction as MuJoCo frictionloss; ``contacts``/``joint_limits``:
    enable those constraints; ``effort_limits``: clamp actuator force to the URDF effort;
    ``payload``: include ``model.payload``; ``timestep`` in s. ``scene``: static objects the
    robot collides with (contacts on, self-collisions off, :func:`dyn_node.sim.scene.add_scene`)
    under ``solver`` (default :class:`SolverSettings`: dyn_sim's, RK4; without a scene the
    integrator stays MuJoCo's Euler).
    """
    contacts = contacts or scene is not None
    text, patched = mujoco_urdf(model, contacts=contacts)
    try:
        spec = mujoco.MjSpec.from_string(text)
    except Exception as exc:  # MuJoCo raises ValueError with its parser message
        raise ModelError(f"MuJoCo could not parse the robot description: {exc}",
                         code="mujoco_parse") from exc
    spec.compiler.fusestatic = False
    spec.compiler.discardvisual = True
    spec.compiler.balanceinertia = False
    spec.compiler.boundinertia = 0.0
    spec.compiler.boundmass = 0.0
    spec.option.timestep = timestep
    spec.option.gravity = np.asarray(model.gravity, dtype=float)
    if payload and model.payload.mass > 0.0:
        parent = spec.body(model.payload_frame)
        if parent is None:
            raise ModelError(f"payload frame '{model.payload_frame}' is not a MuJoCo body",
                             code="bad_frame")
        body = parent.add_body(name=_PAYLOAD_BODY, pos=list(model.payload.com))
        body.mass = float(model.payload.mass)
        body.ipos = [0.0, 0.0, 0.0]
        body.inertia = [INERTIA_EPS] * 3
        body.explicitinertial = True
        patched = patched + (_PAYLOAD_BODY,)
    if scene is not None:
        add_scene(spec, scene, solver or SolverSettings())
    for name in model.joint_names:
        act = spec.add_actuator(name=f"{name}_motor", target=name,
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_motor()
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    try:
        mj = spec.compile()
    except Exception as exc:
        raise ModelError(f"MuJoCo could not compile the robot description: {exc}",
                         code="mujoco_compile") from exc
    for name in patched:
        mj.body_inertia[mj.body(name).id] -= INERTIA_EPS
    joint_ids = np.array([mj.joint(n).id for n in model.joint_names], dtype=np.intp)
    dof_ids = mj.jnt_dofadr[joint_ids].astype(np.intp)
    qpos_ids = mj.jnt_qposadr[joint_ids].astype(np.intp)
    actuator_ids = np.array([mj.actuator(f"{n}_motor").id for n in model.joint_names], dtype=np.intp)
    if scene is not None:
        (solver or SolverSettings()).apply(mj)
    if not damping:
        mj.dof_damping[:] = 0.0
    mj.dof_armature[:] = 0.0
    if armature:
        mj.dof_armature[dof_ids] = model.limits.armature
    if not frictionloss:
        mj.dof_frictionloss[:] = 0.0
    if not joint_limits:
        mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    if not contacts:
        mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    if not effort_limits:
        mj.jnt_actfrclimited[:] = 0
    for a in (joint_ids, dof_ids, qpos_ids, actuator_ids):
        a.setflags(write=False)
    return MujocoRobot(model=mj, joint_names=tuple(model.joint_names), joint_ids=joint_ids,
                       qpos_ids=qpos_ids, dof_ids=dof_ids, actuator_ids=actuator_ids,
                       patched_bodies=patched)


def inverse_dynamics(robot: MujocoRobot, q: np.ndarray, v: np.ndarray, a: np.ndarray,
                     data: mujoco.MjData | None = None) -> np.ndarray:
    """MuJoCo's ``mj_inverse`` torque (N·m|N) at (q, v, a), all in dyn_node model order."""
    d = data if data is not None else robot.make_data()
    robot.set_state(d, q, v)
    d.qacc[:] = 0.0
    d.qacc[robot.dof_ids] = np.asarray(a, dtype=float)
    mujoco.mj_inverse(robot.model, d)
    return d.qfrc_inverse[robot.dof_ids].copy()


def mass_matrix(robot: MujocoRobot, q: np.ndarray, data: mujoco.MjData | None = None) -> np.ndarray:
    """MuJoCo's joint-space inertia (armature included) at q, model order (kg·m²)."""
    d = data if data is not None else robot.make_data()
    robot.set_state(d, q)
    mujoco.mj_forward(robot.model, d)
    full = np.zeros((robot.model.nv, robot.model.nv))
    mujoco.mj_fullM(robot.model, d, full)
    return full[np.ix_(robot.dof_ids, robot.dof_ids)]
