"""Building and reading a weights push: rcl_interfaces/srv/SetParameters on policy_node/push_weights.

A push holds any of these parameters: `weights` (BYTE_ARRAY, a safetensors blob) or
`weights_base64` (STRING, the same blob in base64), `epsilon` (DOUBLE, the exploration rate to act
with from now on) and `release_stamp_ns` (INTEGER: with policy_node's wait_for_trainer, answer the
frames stamped up to this sim time, ns); and, to be accepted, `push_seq` (INTEGER, larger than any
sequence number accepted before: a recorded push cannot be played again) and `signature` (STRING:
HMAC-SHA256, in hex, of all of the above under the run's key, `push_key_file`). The Fast DDS in the
PyPI wheels has no security plugins, so anyone on the domain can call the service: the key, which
`train` writes for each run (mode 0600) and hands to both nodes, is what keeps them out.

trainer_node's lockstep learning sends weights, epsilon and
release after each step's updates, so the policy acts on the network that learnt from the step that
produced the frame, as the in-process loop does. It sends the weights in base64: rclpy converts a
BYTE_ARRAY byte by byte (measured: serialising, deserialising and joining CNN's 1.2 MB blob takes
101 ms, as base64 text 8 ms), and lockstep learning waits for every push.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import hashlib
import hmac
import math
import os
import secrets
import stat
from pathlib import Path

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from uav_common import contract

WEIGHTS_BASE64_PARAMETER = "weights_base64"
EPSILON_PARAMETER = "epsilon"
RELEASE_PARAMETER = "release_stamp_ns"
SEQUENCE_PARAMETER = "push_seq"
SIGNATURE_PARAMETER = "signature"
KEY_BYTES = 32
_TYPES = {
    contract.WEIGHTS_PARAMETER: (ParameterType.PARAMETER_BYTE_ARRAY, "BYTE_ARRAY"),
    WEIGHTS_BASE64_PARAMETER: (ParameterType.PARAMETER_STRING, "STRING"),
    EPSILON_PARAMETER: (ParameterType.PARAMETER_DOUBLE, "DOUBLE"),
    RELEASE_PARAMETER: (ParameterType.PARAMETER_INTEGER, "INTEGER"),
    SEQUENCE_PARAMETER: (ParameterType.PARAMETER_INTEGER, "INTEGER"),
    SIGNATURE_PARAMETER: (ParameterType.PARAMETER_STRING, "STRING"),
}


@dataclasses.dataclass(frozen=True)
class Push:
    weights: bytes | None = None
    epsilon: float | None = None
    release_stamp_ns: int | None = None
    seq: int | None = None
    signature: str | None = None


def signed_text(blob: bytes | None, epsilon: float | None, release_stamp_ns: int | None, seq: int) -> bytes:
    """What a signature covers: every field of the push (the blob by its SHA-256)."""
    digest = hashlib.sha256(blob).hexdigest() if blob is not None else "-"
    return f"uav_push/1|{seq}|{digest}|{epsilon!r}|{release_stamp_ns!r}".encode()


def sign(key: bytes, blob: bytes | None, epsilon: float | None, release_stamp_ns: int | None, seq: int) -> str:
    return hmac.new(key, signed_text(blob, epsilon, release_stamp_ns, seq), hashlib.sha256).hexdigest()


def verify(key: bytes, push: Push, last_seq: int) -> None:
    """ValueError unless `push` is signed with `key` and newer than `last_seq`."""
    if push.signature is None or push.seq is None:
        raise ValueError(f"unsigned push refused: a push must carry '{SEQUENCE_PARAMETER}' and '{SIGNATURE_PARAMETER}'")
    good = sign(key, push.weights, push.epsilon, push.release_stamp_ns, push.seq)
    if not hmac.compare_digest(good, push.signature):
        raise ValueError("push refused: its signature does not match this run's key (push_key_file)")
    if push.seq <= last_seq:
        raise ValueError(f"push refused: sequence number {push.seq} is not newer than {last_seq} (a push played again)")


def write_key(path: str | os.PathLike) -> Path:
    """A new random key in `path`, readable by its owner only (replacing any there)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, (secrets.token_hex(KEY_BYTES) + "\n").encode())
    finally:
        os.close(fd)
    os.replace(tmp, path)
    return path


def load_key(path: str | os.PathLike) -> bytes:
    """The key in `path`; ValueError names the file and what is wrong (missing, readable by others, too short)."""
    path = Path(path)
    try:
        st = path.stat()
        text = path.read_text().strip()
    except OSError as e:
        raise ValueError(f"push key file '{path}': {e.strerror or e}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ValueError(f"push key file '{path}' can be read by others (mode {stat.S_IMODE(st.st_mode):o}): chmod 600 it")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        raise ValueError(f"push key file '{path}' does not hold a hex key") from None
    if len(key) < KEY_BYTES:
        raise ValueError(f"push key file '{path}' holds {len(key)} bytes; at least {KEY_BYTES} are needed")
    return key


def push_request(
    blob: bytes | None,
    epsilon: float | None = None,
    release_stamp_ns: int | None = None,
    as_base64: bool = False,
    key: bytes | None = None,
    seq: int | None = None,
) -> SetParameters.Request:
    """A push of weights (None: none; `as_base64`: as weights_base64 text), and optionally an exploration
    rate and a release stamp; with `key`, signed as push `seq`."""
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
    if key is not None:
        if seq is None:
            raise ValueError("a signed push needs its sequence number")
        eps = None if epsilon is None else float(epsilon)
        stamp = None if release_stamp_ns is None else int(release_stamp_ns)
        signature = sign(key, None if blob is None else bytes(blob), eps, stamp, int(seq))
        params.append(
            Parameter(name=SEQUENCE_PARAMETER, value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=int(seq)))
        )
        params.append(
            Parameter(name=SIGNATURE_PARAMETER, value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=signature))
        )
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
    seq = seen[SEQUENCE_PARAMETER].integer_value if SEQUENCE_PARAMETER in seen else None
    signature = seen[SIGNATURE_PARAMETER].string_value if SIGNATURE_PARAMETER in seen else None
    return Push(blob, eps, stamp, seq, signature)


# How far a release may lead the newest frame the policy has seen: trainer_node releases frames it has
# received, which reach the policy by another path, a few steps later at most.
MAX_RELEASE_LEAD_NS = 10_000_000_000


class ReleaseGate:
    """wait_for_trainer: frames held until trainer_node releases them (a push's release_stamp_ns), or until
    one has waited `timeout_s` (no trainer, or one that stopped: the vehicle must not stall)."""

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.held: list[tuple[int, float, object]] = []  # (stamp, held since, item), oldest first
        self.released_ns = -1  # frames stamped up to this may be answered
        self.newest_ns = -1  # the newest frame stamp seen
        self.timed_out = 0  # frames answered without a release

    def beyond(self, stamp: int) -> str | None:
        """Why a release up to `stamp` is refused (it leads every frame seen by more than MAX_RELEASE_LEAD_NS: it
        would answer frames not yet taken without their updates), or None."""
        if self.newest_ns >= 0 and stamp > self.newest_ns + MAX_RELEASE_LEAD_NS:
            return (
                f"release_stamp_ns {stamp} is {(stamp - self.newest_ns) / 1e9:.1f} s beyond the newest frame seen "
                f"({self.newest_ns}): refused"
            )
        return None

    def hold(self, stamp: int, item, now: float) -> bool:
        """Hold `item` unless its frame is already released; whether it was held."""
        self.newest_ns = max(self.newest_ns, stamp)
        if stamp <= self.released_ns:
            return False
        self.held.append((stamp, now, item))
        return True

    def restart(self) -> int:
        """The stamps started again (a restarted simulator): the held frames are dropped; how many."""
        dropped, self.held, self.released_ns, self.newest_ns = len(self.held), [], -1, -1
        return dropped

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
