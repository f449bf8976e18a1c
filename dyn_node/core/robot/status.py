"""Diagnostic statuses as plain values, so the core and the audit build them without rclpy.

The ROS adapter turns a :class:`Status` into ``diagnostic_msgs/DiagnosticStatus`` one-to-one.
Levels follow diagnostic_msgs: OK=0, WARN=1, ERROR=2, STALE=3.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
NAME_PREFIX = "dyn_node: "


def format_value(value: Any) -> str:
    """Render a key/value for DiagnosticStatus: floats with enough digits to be re-read exactly."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    return str(value)


@dataclass(frozen=True)
class Status:
    """One diagnostic status. ``values`` keep insertion order; every non-OK status should carry a
    ``failure_label`` value from :mod:`dyn_node.errors`."""

    name: str
    level: int
    message: str
    hardware_id: str = ""
    values: Mapping[str, Any] = field(default_factory=dict)

    def key_values(self) -> list[tuple[str, str]]:
        return [(k, format_value(v)) for k, v in self.values.items()]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "level": LEVEL_NAMES.get(self.level, str(self.level)),
                "message": self.message, "hardware_id": self.hardware_id,
                "values": dict(self.key_values())}
