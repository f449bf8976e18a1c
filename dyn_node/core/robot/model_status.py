"""The ``dyn_node: model`` diagnostic status: the running model's figures, waiting for a
description, or a rejected one."""
from __future__ import annotations

from dyn_node.errors import EVALUATION_ERROR, STATE_ERROR
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, STALE, WARN, Status

MODEL = NAME_PREFIX + "model"


def _model_values(model: RobotModel) -> dict:
    vals = {"robot_name": model.name, "dof": model.nv, "joints": " ".join(model.joint_names),
            "total_mass_kg": model.total_mass, "payload_mass_kg": model.payload.mass,
            "payload_frame": model.payload_frame, "gravity_m_s2": " ".join(repr(float(g)) for g in model.gravity),
            "source": model.source, "urdf_sha256": model.urdf_hash, "warnings": len(model.warnings)}
    for i, w in enumerate(model.warnings, 1):
        vals[f"warning_{i}"] = w
    return vals


def model_status(model: RobotModel, hardware_id: str) -> Status:
    """OK with the model's figures, WARN when its limits look suspicious."""
    vals = _model_values(model)
    if model.warnings:
        vals["failure_label"] = EVALUATION_ERROR
        more = f" (+{len(model.warnings) - 1} more)" if len(model.warnings) > 1 else ""
        return Status(MODEL, WARN, f"check the limits: {model.warnings[0]}{more}", hardware_id, vals)
    return Status(MODEL, OK, f"{model.name}: {model.nv} DoF, {model.total_mass:.3f} kg", hardware_id, vals)


def waiting_model_status(hardware_id: str) -> Status:
    return Status(MODEL, STALE, "waiting for robot_description", hardware_id,
                  {"source": "topic:robot_description", "failure_label": STATE_ERROR})


def model_error_status(error: Exception, hardware_id: str, running: RobotModel | None) -> Status:
    """ERROR: a description or model parameter was rejected; the running model (if any) stays."""
    vals = _model_values(running) if running is not None else {}
    vals["error"] = str(error)
    vals["failure_label"] = EVALUATION_ERROR
    keep = f"; still using {running.name} ({running.urdf_hash[:12]})" if running else ""
    return Status(MODEL, ERROR, f"robot description rejected: {error}{keep}", hardware_id, vals)


__all__ = ["MODEL", "model_status", "waiting_model_status", "model_error_status"]
