"""Each bag topic's role in the audit (by its type and name): an input the replay takes, a
recorded output the re-check compares, or None (not used)."""
from __future__ import annotations

from typing import Sequence

from dyn_node.audit.replay.contact import contact_role
from dyn_node.audit.replay.gates import ROLE_GATE, gate_role
from dyn_node.audit.replay.services import ROLE_SERVICE_EVENT, service_role
from dyn_node.bag.reader import BagMessage

ROLE_JOINT_STATES, ROLE_TRAJECTORY = "joint_states", "joint_trajectory"
ROLE_CHECK = "check_trajectory"  # ~/check_trajectory: checked like joint_trajectory, never tracked
ROLE_STATES = "inverse_dynamics_request"  # ~/inverse_dynamics_request: torques for given states
ROLE_GRAVITY, ROLE_ID, ROLE_FEAS = "gravity_torque", "inverse_dynamics", "feasibility"
ROLE_TRAJ_EFFORT, ROLE_CTRL, ROLE_DESC = "trajectory_effort", "controller_status", "robot_description"


def role_of(topic: str, schema: str) -> str | None:
    """The role of a topic of this type and name (None: the audit does not use it)."""
    contact = contact_role(topic, schema)  # ~/external_torque, ~/external_wrench, ~/observer_events
    if contact is not None:
        return contact
    if service_role(topic, schema) is not None:  # the question services' events
        return ROLE_SERVICE_EVENT
    if gate_role(topic, schema) is not None:  # the FollowJointTrajectory gate's decisions
        return ROLE_GATE
    last = topic.rstrip("/").rsplit("/", 1)[-1]
    if schema == "sensor_msgs/msg/JointState":
        if last == ROLE_GRAVITY:
            return ROLE_GRAVITY
        if last == ROLE_ID:
            return ROLE_ID
        return ROLE_JOINT_STATES if last == ROLE_JOINT_STATES else None
    if schema == "trajectory_msgs/msg/JointTrajectory":
        if last == ROLE_TRAJ_EFFORT:
            return ROLE_TRAJ_EFFORT
        return last if last in (ROLE_TRAJECTORY, ROLE_CHECK, ROLE_STATES) else None
    if schema == "diagnostic_msgs/msg/DiagnosticArray" and last == ROLE_FEAS:
        return ROLE_FEAS
    if schema == "diagnostic_msgs/msg/DiagnosticStatus" and last == ROLE_CTRL:
        return ROLE_CTRL
    if schema == "std_msgs/msg/String" and last == ROLE_DESC:
        return ROLE_DESC
    return None



class Roles:
    """Each topic's role (by type and name; None: not used), restricted to ``wanted`` if given."""

    def __init__(self, wanted: Sequence[str] = ()):
        self.wanted = set(wanted)
        self.seen: dict[str, str | None] = {}

    def of(self, m: BagMessage) -> str | None:
        role = self.seen.get(m.topic, "?")
        if role == "?":
            role = role_of(m.topic, m.channel.schema_name)
            if self.wanted and m.topic not in self.wanted:
                role = None
            self.seen[m.topic] = role
        return role

