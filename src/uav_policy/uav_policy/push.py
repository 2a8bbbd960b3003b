"""Building and reading a weights push: rcl_interfaces/srv/SetParameters on policy_node/push_weights.

A push holds any of these parameters: `weights` (BYTE_ARRAY, a safetensors blob) or
`weights_base64` (STRING, the same blob in base64), `epsilon` (DOUBLE, the exploration rate to act
with from now on) and `release_stamp_ns` (INTEGER: with policy_node's wait_for_trainer, answer the
frames stamped up to this sim time, ns). trainer_node's lockstep learning sends weights, epsilon and
release after each step's updates, so the policy acts on the network that learnt from the step that
produced the frame, as the in-process loop does. It sends the weights in base64: rclpy converts a
BYTE_ARRAY byte by byte (measured: serialising, deserialising and joining CNN's 1.2 MB blob takes
101 ms, as base64 text 8 ms), and lockstep learning waits for every push.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import math

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from uav_common import contract

WEIGHTS_BASE64_PARAMETER = "weights_base64"
EPSILON_PARAMETER = "epsilon"
RELEASE_PARAMETER = "release_stamp_ns"
_TYPES = {
    contract.WEIGHTS_PARAMETER: (ParameterType.PARAMETER_BYTE_ARRAY, "BYTE_ARRAY"),
    WEIGHTS_BASE64_PARAMETER: (ParameterType.PARAMETER_STRING, "STRING"),
    EPSILON_PARAMETER: (ParameterType.PARAMETER_DOUBLE, "DOUBLE"),
    RELEASE_PARAMETER: (ParameterType.PARAMETER_INTEGER, "INTEGER"),
}


@dataclasses.dataclass(frozen=True)
class Push:
    weights: bytes | None = None
    epsilon: float | None = None
    release_stamp_ns: int | None = None


def push_request(
    blob: bytes | None, epsilon: float | None = None, release_stamp_ns: int | None = None, as_base64: bool = False
) -> SetParameters.Request:
    """A push of weights (None: none; `as_base64`: as weights_base64 text), and optionally an exploration
    rate and a release stamp."""
    params = []
    if blob is not None and as_base64:
        value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=base64.b64encode(blob).decode("ascii"))
        params.append(Parameter(name=WEIGHTS_BASE64_PARAMETER, value=value))
    elif blob is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=bytes(blob))
        params.append(Parameter(name=contract.WEIGHTS_PARAMETER, value=value))
    if epsilon is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(epsilon))
        params.append(Parameter(name=EPSILON_PARAMETER, value=value))
    if release_stamp_ns is not None:
        value = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=int(release_stamp_ns))
        params.append(Parameter(name=RELEASE_PARAMETER, value=value))
    return SetParameters.Request(parameters=params)


def read_push(params, max_bytes: int) -> Push:
    """The push in a request's parameters; ValueError names what is wrong (unknown or repeated names,
    wrong types, weights given both ways, base64 that is malformed or would decode to over `max_bytes`,
    an epsilon outside [0, 1], a negative stamp, or nothing at all)."""
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
        raise ValueError(
            f"expected a BYTE_ARRAY parameter named '{contract.WEIGHTS_PARAMETER}' (or weights_base64, epsilon, release_stamp_ns)"
        )
    blob = None
    if contract.WEIGHTS_PARAMETER in seen and WEIGHTS_BASE64_PARAMETER in seen:
        raise ValueError(f"give '{contract.WEIGHTS_PARAMETER}' or '{WEIGHTS_BASE64_PARAMETER}', not both")
    if contract.WEIGHTS_PARAMETER in seen:
        raw = seen[contract.WEIGHTS_PARAMETER].byte_array_value
        blob = raw if isinstance(raw, (bytes, bytearray)) else b"".join(raw)
    if WEIGHTS_BASE64_PARAMETER in seen:
        text = seen[WEIGHTS_BASE64_PARAMETER].string_value
        if len(text) > 4 * (max_bytes // 3 + 1):  # refused before anything is decoded
            raise ValueError(f"push parameter '{WEIGHTS_BASE64_PARAMETER}' would hold more than the {max_bytes} bytes allowed")
        try:
            blob = base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError) as e:
            raise ValueError(f"push parameter '{WEIGHTS_BASE64_PARAMETER}' is not base64: {e}") from None
    eps = seen[EPSILON_PARAMETER].double_value if EPSILON_PARAMETER in seen else None
    if eps is not None and not (math.isfinite(eps) and 0.0 <= eps <= 1.0):
        raise ValueError(f"push parameter 'epsilon' must lie in [0, 1], got {eps}")
    stamp = seen[RELEASE_PARAMETER].integer_value if RELEASE_PARAMETER in seen else None
    if stamp is not None and stamp < 0:
        raise ValueError(f"push parameter 'release_stamp_ns' must be >= 0, got {stamp}")
    return Push(blob, eps, stamp)


class ReleaseGate:
    """wait_for_trainer: frames held until trainer_node releases them (a push's release_stamp_ns), or until
    one has waited `timeout_s` (no trainer, or one that stopped: the vehicle must not stall)."""

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.held: list[tuple[int, float, object]] = []  # (stamp, held since, item), oldest first
        self.released_ns = -1  # frames stamped up to this may be answered
        self.timed_out = 0  # frames answered without a release

    def hold(self, stamp: int, item, now: float) -> bool:
        """Hold `item` unless its frame is already released; whether it was held."""
        if stamp <= self.released_ns:
            return False
        self.held.append((stamp, now, item))
        return True

    def release(self, stamp: int) -> list:
        """The held items released by a release up to `stamp`, oldest first."""
        self.released_ns = max(self.released_ns, stamp)
        out = []
        while self.held and self.held[0][0] <= self.released_ns:
            out.append(self.held.pop(0)[2])
        return out

    def expired(self, now: float) -> tuple[int | None, list]:
        """(the stamp of the oldest frame held past the timeout, or None; the items that releases)."""
        if not self.held or now - self.held[0][1] <= self.timeout_s:
            return None, []
        self.timed_out += 1
        stamp = self.held[0][0]
        return stamp, self.release(stamp)
