"""Error types and the failure-label vocabulary shared by every part of dyn_node.

Every error the core raises for bad input carries a ``failure_label`` from the DESIGN vocabulary
and a short machine-readable ``code``, so the ROS adapter and the audit can report it without
parsing the message text.
"""
from __future__ import annotations

STATE_ERROR = "state error"
PLANNING_ERROR = "planning error"
CONTROL_ERROR = "control error"
EVALUATION_ERROR = "evaluation error"
PERCEPTION_ERROR = "perception error"

FAILURE_LABELS = (STATE_ERROR, PLANNING_ERROR, CONTROL_ERROR, EVALUATION_ERROR, PERCEPTION_ERROR)


class DynNodeError(ValueError):
    """Base class: a clear, reportable error caused by input, never by a bug."""

    failure_label: str = EVALUATION_ERROR

    def __init__(self, message: str, code: str = "error", failure_label: str | None = None):
        super().__init__(message)
        self.code = code
        if failure_label is not None:
            self.failure_label = failure_label


class ModelError(DynNodeError):
    """The robot description, a built-in name or a limits file cannot be used."""

    failure_label = EVALUATION_ERROR


class InputError(DynNodeError):
    """A joint state (or other per-message input) is malformed or inconsistent with the model."""

    failure_label = STATE_ERROR


class TrajectoryError(DynNodeError):
    """A trajectory is malformed: the robot cannot be asked to execute it."""

    failure_label = PLANNING_ERROR
