"""ROS parameter descriptors, built one way for dyn_node, dyn_sim and the recording bridge."""
from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

#: ParameterType of each kind name :class:`dyn_node.core.robot.settings.ParamSpec` uses.
KINDS = {"string": ParameterType.PARAMETER_STRING, "double": ParameterType.PARAMETER_DOUBLE,
         "integer": ParameterType.PARAMETER_INTEGER, "bool": ParameterType.PARAMETER_BOOL,
         "double_array": ParameterType.PARAMETER_DOUBLE_ARRAY}


def parameter_descriptor(name: str, ptype: int, description: str, *, low: float | None = None,
                         high: float | None = None, read_only: bool = False,
                         constraints: str = "") -> ParameterDescriptor:
    """The descriptor of parameter ``name`` of type ``ptype`` (a ParameterType). ``low``/``high``
    give a double parameter an inclusive floating-point range (step 0) and an integer one an
    inclusive integer range (step 1); ``constraints`` is the human-readable note."""
    d = ParameterDescriptor(name=name, type=ptype, description=description, read_only=read_only,
                            additional_constraints=constraints)
    if low is not None and ptype == ParameterType.PARAMETER_DOUBLE:
        d.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                     step=0.0)]
    elif low is not None and ptype == ParameterType.PARAMETER_INTEGER:
        d.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    return d


__all__ = ["KINDS", "parameter_descriptor"]
