"""The node's start-up lines: one INFO line when a model is ready (on every path: a model
parameter, the robot_description topic, a parameter change) and one at the first accepted
joint_states of each model, so a correct start is visible in the log (README "Quick start")."""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from dyn_node.core.robot.limits_file import limits_sha256
from dyn_node.core.robot.model import RobotModel

_MAX_JOINTS = 12  # joint names listed in full; beyond, the count of the rest


def _limits_source(limits_file: str, limits_text: str | None) -> str:
    if not limits_file or limits_text is None:
        return "limits URDF"
    return f"limits {limits_file} (sha256 {limits_sha256(limits_text)[:12]}) over the URDF"


def _payload(model: RobotModel) -> str:
    p = model.payload
    if p.mass <= 0.0:
        return "payload none"
    com = ", ".join(f"{c:g}" for c in p.com)
    return f"payload {p.mass:g} kg at [{com}] m in {model.payload_frame}"


def _friction(model: RobotModel, on: bool) -> str:
    if not on:
        return "friction off"
    pm = model.pin_model
    return "friction on" if np.any(pm.damping) or np.any(pm.friction) else \
        "friction on (the URDF has none)"


def model_ready_line(model: RobotModel, *, limits_file: str, limits_text: str | None,
                     friction: bool, recording: str) -> str:
    """``model ready: ...``. ``limits_text``: the limits file text the model was built from
    (None: URDF limits only); ``friction``: include_friction; ``recording``: "off" or the bag
    directory."""
    names = list(model.joint_names)
    shown = ", ".join(names[:_MAX_JOINTS]) + (
        f" (+{len(names) - _MAX_JOINTS} more)" if len(names) > _MAX_JOINTS else "")
    return (f"model ready: {model.name} from {model.source}, {model.nv} DoF, joints {shown}; "
            f"{_limits_source(limits_file, limits_text)}; {_payload(model)}; "
            f"{_friction(model, friction)}; recording {recording}")


def first_joint_state_line(model: RobotModel, n_names: int, stamp_s: float) -> str:
    """``first joint_states accepted: ...`` for ``model``; ``n_names`` names in the message."""
    ignored = n_names - model.nv
    extra = f" ({ignored} other names ignored: locked or unknown joints)" if ignored > 0 else ""
    return (f"first joint_states accepted for {model.name}: stamp {stamp_s:.6f} s, "
            f"{model.nv} model joints{extra}; answering on ~/gravity_torque and "
            "~/inverse_dynamics")


class FirstStateAnnouncer:
    """Says :func:`first_joint_state_line` once per model (a rebuilt model says it again)."""

    def __init__(self, log: Callable[[str], Any]):
        self._log = log
        self._model: RobotModel | None = None

    def accepted(self, model: RobotModel, n_names: int, stamp_s: float) -> None:
        if model is not self._model:  # one identity test per message
            self._model = model
            self._log(first_joint_state_line(model, n_names, stamp_s))


__all__ = ["FirstStateAnnouncer", "first_joint_state_line", "model_ready_line"]
