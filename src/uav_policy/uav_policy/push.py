"""Building a weights push: rcl_interfaces/srv/SetParameters with one BYTE_ARRAY parameter."""

from __future__ import annotations

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from uav_sim import contract


def push_request(blob: bytes) -> SetParameters.Request:
    value = ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=bytes(blob))
    return SetParameters.Request(parameters=[Parameter(name=contract.WEIGHTS_PARAMETER, value=value)])
