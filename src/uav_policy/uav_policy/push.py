"""Building and reading a weights push: rcl_interfaces/srv/SetParameters on policy_node/push_weights.

A push holds any of three parameters: `weights` (BYTE_ARRAY, a safetensors blob), `epsilon`
(DOUBLE, the exploration rate to act with from now on) and `release_stamp_ns` (INTEGER: with
policy_node's wait_for_trainer, answer the frames stamped up to this sim time, ns). trainer_node's
lockstep learning sends all three after each step's updates, so the policy acts on the network that
learnt from the step that produced the frame, as the in-process loop does.
"""

from __future__ import annotations

import dataclasses
import math

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from uav_sim import contract

EPSILON_PARAMETER = "epsilon"
RELEASE_PARAMETER = "release_stamp_ns"
_TYPES = {
    contract.WEIGHTS_PARAMETER: (ParameterType.PARAMETER_BYTE_ARRAY, "BYTE_ARRAY"),
    EPSILON_PARAMETER: (ParameterType.PARAMETER_DOUBLE, "DOUBLE"),
    RELEASE_PARAMETER: (ParameterType.PARAMETER_INTEGER, "INTEGER"),
}


@dataclasses.dataclass(frozen=True)
class Push:
    weights: bytes | None = None
    epsilon: float | None = None
    release_stamp_ns: int | None = None


def push_request(blob: bytes | None, epsilon: float | None = None, release_stamp_ns: int | None = None) -> SetParameters.Request:
    """A push of weights (None: none), and optionally an exploration rate and a release stamp."""
    params = []
    if blob is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=bytes(blob))
        params.append(Parameter(name=contract.WEIGHTS_PARAMETER, value=value))
    if epsilon is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(epsilon))
        params.append(Parameter(name=EPSILON_PARAMETER, value=value))
    if release_stamp_ns is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=int(release_stamp_ns))
        params.append(Parameter(name=RELEASE_PARAMETER, value=value))
    return SetParameters.Request(parameters=params)


def read_push(params) -> Push:
    """The push in a request's parameters; ValueError names what is wrong (unknown or repeated names,
    wrong types, an epsilon outside [0, 1], a negative stamp, or nothing at all)."""
    seen: dict[str, ParameterValue] = {}
    for p in params:
        if p.name not in _TYPES:
            raise ValueError(f"unknown push parameter '{p.name}'; expected any of {', '.join(_TYPES)}")
        if p.name in seen:
            raise ValueError(f"push parameter '{p.name}' given twice")
        if p.value.type != _TYPES[p.name][0]:
            raise ValueError(f"push parameter '{p.name}' must be a {_TYPES[p.name][1]}")
        seen[p.name] = p.value
    if not seen:
        raise ValueError(f"expected a BYTE_ARRAY parameter named '{contract.WEIGHTS_PARAMETER}' (or epsilon, release_stamp_ns)")
    blob = None
    if contract.WEIGHTS_PARAMETER in seen:
        raw = seen[contract.WEIGHTS_PARAMETER].byte_array_value
        blob = raw if isinstance(raw, (bytes, bytearray)) else b"".join(raw)
    eps = seen[EPSILON_PARAMETER].double_value if EPSILON_PARAMETER in seen else None
    if eps is not None and not (math.isfinite(eps) and 0.0 <= eps <= 1.0):
        raise ValueError(f"push parameter 'epsilon' must lie in [0, 1], got {eps}")
    stamp = seen[RELEASE_PARAMETER].integer_value if RELEASE_PARAMETER in seen else None
    if stamp is not None and stamp < 0:
        raise ValueError(f"push parameter 'release_stamp_ns' must be >= 0, got {stamp}")
    return Push(blob, eps, stamp)
