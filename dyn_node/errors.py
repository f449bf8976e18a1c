"""Error types and the failure-label vocabulary shared by every part of dyn_node.

Every error the core raises for bad input carries a ``failure_label`` from the DESIGN vocabulary
and a short machine-readable ``code``, so the ROS adapter and the audit can report it without
parsing the message text.
"""
from __future__ import annotations

from pathlib import Path

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


class SettingsError(DynNodeError):
    """A parameter value that cannot be used; the message names the parameter and the rule."""

    failure_label = EVALUATION_ERROR


class TrajectoryFileError(DynNodeError):
    """A trajectory file that cannot be read; ``str()`` is ``file:line: field: problem``."""

    failure_label = STATE_ERROR

    def __init__(self, path: str | Path, line: int | None, field: str, problem: str):
        where = f"{path}:{line}" if line else f"{path}"
        super().__init__(f"{where}: {field}: {problem}" if field else f"{where}: {problem}",
                         code="unreadable_file")
        self.path, self.line, self.field, self.problem = str(path), line, field, problem


class CheckError(DynNodeError):
    """dyn-check cannot run at all (no usable model, bad options)."""

    failure_label = STATE_ERROR


class RecordingError(DynNodeError):
    """Bad recorder configuration (raised at construction, never from write())."""


class RecoverError(DynNodeError):
    """A clear, user-facing dyn-bag-recover failure (bad input path, not an MCAP file,
    unwritable output)."""


class FleetError(DynNodeError):
    """The fleet run cannot start (no bags, a missing file, Ray unavailable or off loopback);
    one bag's failure never raises it, it becomes that bag's row."""
