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


class NodeOwned:
    """A parameter that shows a value the node itself changes (e.g. policy_node's epsilon, set by each push): the
    node's `set(value)` goes through, anyone else's set (ros2 param set, Foxglove) is refused with `reason`. Declare
    the parameter with read_only=False; rclpy still refuses every other parameter as read-only."""

    def __init__(self, node, name: str, reason: str):
        from rcl_interfaces.msg import SetParametersResult

        self.node, self.name, self._own = node, name, False

        def check(params):
            for p in params:
                if p.name == self.name and not self._own:
                    return SetParametersResult(successful=False, reason=f"parameter '{name}' {reason}")
            return SetParametersResult(successful=True)

        node.add_on_set_parameters_callback(check)

    def set(self, value) -> None:
        """Take `value` (a set of the value it has is skipped: it would announce nothing new, at a cost on every
        push)."""
        from rclpy.parameter import Parameter

        if self.node.get_parameter(self.name).value == value:
            return
        self._own = True  # the executors here are single-threaded: no other set runs in between
        try:
            result = self.node.set_parameters([Parameter(self.name, value=value)])[0]
        finally:
            self._own = False
        if not result.successful:
            raise ValueError(f"parameter '{self.name}': {result.reason}")
