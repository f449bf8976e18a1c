"""dyn_sim's scene, contact truth and physics status on ROS (the math: :mod:`dyn_node.sim`).

Parameters (:data:`SCENE_PARAMETERS`, read at start-up): ``scene_file`` and the MuJoCo solver
settings. Publications: ``~/contact_truth`` (dyn_node_interfaces/ContactTruth) with every
joint_states message while some robot–scene contact is active, stamped like it, and a
``dyn_sim: physics`` status on ``/diagnostics`` every ``physics_diagnostics_period`` s of
simulation time (solver iterations and residual, MuJoCo warnings, largest penetration, energy
budget and its error; a diverging step is an ERROR labelled ``evaluation error``). When the
simulator's divergence guard stops the physics (:attr:`Simulator.fault`) the ERROR is published at
once, with the fault's line (joint, quantity, step), and repeated each period until ``~/reset``.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any, Callable

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Vector3, Wrench
from rclpy.node import Node

from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.settings import ParamSpec
from dyn_node.ros.qos import LATCHED_HISTORY
from dyn_node.sim.contact_truth import ContactTruth
from dyn_node.sim.scene import SolverSettings, load_scene
from dyn_node.sim.simulator import Simulator

_DEF = SolverSettings()
SCENE_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("scene_file", "string", "", "YAML of static objects the robot collides with "
              "(docs/SIMULATOR.md); empty: no scene, contacts off"),
    ParamSpec("integrator", "string", "auto", "MuJoCo integrator: auto (rk4, or implicitfast when the URDF's "
              "damping is too stiff for it at the timestep), rk4, euler, implicit, implicitfast"),
    ParamSpec("solver", "string", _DEF.solver, "MuJoCo constraint solver (with a scene): newton, cg, pgs"),
    ParamSpec("solver_iterations", "integer", _DEF.iterations, "solver iteration limit", 1, 10000),
    ParamSpec("solver_tolerance", "double", _DEF.tolerance, "solver tolerance (MuJoCo's)", 0.0, 1.0),
    ParamSpec("solver_noslip_iterations", "integer", _DEF.noslip_iterations,
              "no-slip passes (0: MuJoCo's default, soft contacts creep)", 0, 1000),
    ParamSpec("contact_solref", "double_array", list(_DEF.solref),
              "contact [time constant (s), damping ratio] (MuJoCo solref)"),
    ParamSpec("contact_solimp", "double_array", list(_DEF.solimp),
              "contact [d0, d_width, width (m), midpoint, power] (MuJoCo solimp)"),
    ParamSpec("physics_diagnostics_period", "double", 1.0,
              "simulation seconds per 'dyn_sim: physics' status", 0.01, 3600.0),
)


def sim_config_extras(p: dict[str, Any], model: RobotModel) -> dict[str, Any]:
    """SimConfig keyword arguments from the parameters: scene (validated), solver, energy on."""
    auto = p["integrator"] == "auto"
    solver = SolverSettings(integrator=_DEF.integrator if auto else p["integrator"], solver=p["solver"],
                            iterations=int(p["solver_iterations"]), tolerance=float(p["solver_tolerance"]),
                            noslip_iterations=int(p["solver_noslip_iterations"]),
                            solref=tuple(p["contact_solref"]), solimp=tuple(p["contact_solimp"]))
    scene = None
    if p["scene_file"]:
        links = [el.get("name") for el in ET.fromstring(model.urdf).findall("link")]
        scene = load_scene(p["scene_file"], link_names=links)
    return {"scene": scene, "solver": solver, "energy": True, "integrator_auto": auto}


def truth_message(truth: ContactTruth, stamp: TimeMsg, frame_id: str) -> Any:
    """dyn_node_interfaces/ContactTruth of ``truth`` (base frame ``frame_id``)."""
    from dyn_node_interfaces.msg import Contact, ContactTruth as ContactTruthMsg

    msg = ContactTruthMsg()
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    for c in truth.contacts:
        msg.contacts.append(Contact(
            body1=c.body1, body2=c.body2, position=Point(x=float(c.position[0]), y=float(c.position[1]), z=float(c.position[2])),
            normal=_vec(c.normal), force=_vec(c.force), penetration_depth=float(c.penetration_depth)))
    for w in truth.link_wrenches:
        msg.link_names.append(w.link)
        msg.link_wrenches.append(Wrench(force=_vec(w.force), torque=_vec(w.torque)))
    return msg


def _root_link(model: RobotModel) -> str:
    """The URDF link no joint moves (the base frame; MuJoCo's world)."""
    root = ET.fromstring(model.urdf)
    children = {j.find("child").get("link") for j in root.findall("joint") if j.find("child") is not None}
    return next(el.get("name") for el in root.findall("link") if el.get("name") not in children)


def _vec(v: Any) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


class SimPhysics:
    """Publishers of the contact truth and the physics status, driven from the simulation thread."""

    def __init__(self, node: Node, sim: Simulator, stamp: Callable[[int], TimeMsg], *, period_s: float):
        self.node, self.sim, self._stamp = node, sim, stamp
        self.base_frame = _root_link(sim.model)
        self.truth_pub = None
        self.truth_published = 0
        if sim.config.scene is not None:
            sc = sim.config.scene
            node.get_logger().info(
                f"scene {sc.source}: {', '.join(f'{o.type} {o.name}' for o in sc.objects) or 'no objects'}; "
                f"touching links: {', '.join(sc.collide_links) or 'all with collision geometry'}; "
                f"solver {sim.config.solver.to_dict()}")
            try:
                from dyn_node_interfaces.msg import ContactTruth as ContactTruthMsg
            except ImportError:  # interface package not built: the scene still simulates
                node.get_logger().error("dyn_node_interfaces is not importable: ~/contact_truth is off")
            else:
                self.truth_pub = node.create_publisher(ContactTruthMsg, "~/contact_truth", LATCHED_HISTORY)
        self.diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._period_steps = max(1, int(round(period_s / sim.config.timestep)))
        self._next_report = self._period_steps
        self._fault_said = None

    def on_publish(self) -> None:
        """After each joint_states publication: the truth while in contact, the status when due."""
        steps = self.sim.steps
        if self.truth_pub is not None:
            truth = self.sim.contact_truth()
            if truth.active:
                self.truth_pub.publish(truth_message(truth, self._stamp(steps), self.base_frame))
                self.truth_published += 1
        fault = self.sim.fault
        if fault is not None and fault is not self._fault_said:
            self._fault_said = fault
            self.node.get_logger().error(f"dyn_sim: {fault.text}")
            self._next_report = steps  # said now, not at the end of the period
        if self.sim.physics is not None and steps >= self._next_report:
            self._next_report = steps + self._period_steps
            st = self.sim.physics.report(self.sim.data)
            values = dict(st.values)
            if st.failure_label:
                values["failure_label"] = st.failure_label
            status = DiagnosticStatus(level=bytes([st.level]), name="dyn_sim: physics", message=st.message,
                                      hardware_id=self.sim.model.name,
                                      values=[KeyValue(key=k, value=v) for k, v in values.items()])
            arr = DiagnosticArray(status=[status])
            arr.header.stamp = self._stamp(steps)
            self.diag_pub.publish(arr)
