"""Declaring ROS parameters with descriptions and ranges, and failing fast on bad ones."""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor


class ParameterError(ValueError):
    """A parameter value the node cannot start with; the message names it."""


def declare(node, name: str, default, description: str, lo=None, hi=None, choices=None, read_only: bool = True):
    """Declare one parameter with a descriptor and return its validated value."""
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if lo is not None and hi is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    if choices:
        desc.additional_constraints = f"one of: {', '.join(choices)}"
    try:
        if default == []:  # rclpy would take an empty list for bytes: an empty default is a list of strings
            from rcl_interfaces.msg import ParameterType
            from rclpy.parameter import Parameter

            desc.type = ParameterType.PARAMETER_STRING_ARRAY
            value = node.declare_parameter(name, Parameter.Type.STRING_ARRAY, desc).value
            value = [] if value is None else list(value)
        else:
            value = node.declare_parameter(name, default, desc).value
    except Exception as e:  # rclpy raises several types; all mean "this value is unusable"
        raise ParameterError(f"parameter '{name}': {e}") from None
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not type(default):
        raise ParameterError(f"parameter '{name}' must be of type {type(default).__name__}, got {value!r}")
    if lo is not None and hi is not None and not isinstance(value, (str, bool)) and not lo <= value <= hi:
        raise ParameterError(f"parameter '{name}'={value!r} is outside [{lo}, {hi}]")
    if choices and value not in choices:
        raise ParameterError(f"parameter '{name}'={value!r} is invalid: expected one of {', '.join(choices)}")
    return value
