"""The unit of each joint quantity: rad-based for revolute and continuous joints, m-based for
prismatic ones. The one place that decides it; the feasibility verdicts, the live statuses and
their key names all read it from here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only
    from dyn_node.core.robot.model import RobotModel

#: quantity → unit for a revolute (or continuous) joint
ROTARY: dict[str, str] = {
    "position": "rad", "velocity": "rad/s", "acceleration": "rad/s²", "deceleration": "rad/s²",
    "jerk": "rad/s³", "effort": "N·m", "effort_rate": "N·m/s", "rms_effort": "N·m",
    "power": "W", "effort_speed": "N·m", "inertia": "kg·m²"}
#: quantity → unit for a prismatic joint
LINEAR: dict[str, str] = {
    "position": "m", "velocity": "m/s", "acceleration": "m/s²", "deceleration": "m/s²",
    "jerk": "m/s³", "effort": "N", "effort_rate": "N/s", "rms_effort": "N",
    "power": "W", "effort_speed": "N", "inertia": "kg"}

# unit → the suffix it gives a diagnostic key ("N·m" → "_nm", as in effort_limit_nm)
_KEY = {"rad": "rad", "rad/s": "rad_s", "rad/s²": "rad_s2", "rad/s³": "rad_s3", "N·m": "nm",
        "N·m/s": "nm_s", "m": "m", "m/s": "m_s", "m/s²": "m_s2", "m/s³": "m_s3", "N": "n",
        "N/s": "n_s", "W": "w", "kg·m²": "kg_m2", "kg": "kg"}


def prismatic_joints(model: "RobotModel") -> list[bool]:
    """Per model joint (model order): True for a prismatic joint (Pinocchio's PX/PY/PZ and
    unaligned prismatic joint models)."""
    pm = model.pin_model
    return [pm.joints[i].shortname().startswith("JointModelP") for i in range(1, pm.njoints)]


def joint_units(model: "RobotModel") -> dict[str, list[str]]:
    """quantity → the unit of each model joint (model order), for every quantity in
    :data:`ROTARY`."""
    tables = [LINEAR if p else ROTARY for p in prismatic_joints(model)]
    return {q: [t[q] for t in tables] for q in ROTARY}


def unit_key(unit: str) -> str:
    """The key suffix for ``unit``: ``f"{joint}_effort_limit_{unit_key('N')}"`` is
    ``<joint>_effort_limit_n``."""
    return _KEY[unit]
