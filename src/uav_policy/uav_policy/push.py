"""Building and reading a weights push: uav_interfaces/srv/PushWeights on policy_node/push_weights.

A request carries, each in its own field: `weights` (a safetensors blob; empty: none), `epsilon` (the exploration rate
to act with from now on; KEEP_EPSILON: unchanged), `release_stamp_ns` (with policy_node's wait_for_trainer, answer
the frames stamped up to this sim time, ns; NO_RELEASE: none), `fly_action` (with a release: answer the released frame
with this action of the table, not the network's choice: a teacher flies the step) and, to be accepted, `push_seq`
(larger than any sequence number accepted before: a recorded push cannot be played again) and `signature`
(HMAC-SHA256, in hex, of the weights and every field under the run's key, `push_key_file`). The answer's `success`
and `message` say whether it was taken, and why not. An oversize push is refused by its length before anything of
the weights is read (rclpy hands a `uint8[]` over as one array: 200 MB in well under a second, benchmarks/
bench_policy.py; a SetParameters BYTE_ARRAY is converted byte by byte: 61 s with the executor stalled).

The Fast DDS in the PyPI wheels has no security plugins, so anyone on the domain can call the service:
the key, which `train` writes for each run (mode 0600) and hands to both nodes, is what keeps them out.
trainer_node's lockstep learning releases each stored frame with the exact epsilon and the weights the learner had
at the release before, then makes that step's updates while the policy acts, as the in-process loop orders them.
"""

from __future__ import annotations

import array
import dataclasses
import hashlib
import hmac
import math
import os
import secrets
import stat
from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from uav_interfaces.srv import PushWeights as PushService  # noqa: N814 (the push service's type)

KEY_BYTES = 32
# The push service's request queue. rclpy's services keep the last 10 requests: under load, a burst of
# forged pushes overwrote queued ones (10 of 50 never answered), the trainer's among them.
PUSH_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST, depth=100
)


@dataclasses.dataclass(frozen=True)
class Push:
    weights: bytes | None = None
    epsilon: float | None = None
    release_stamp_ns: int | None = None
    seq: int | None = None
    signature: str | None = None
    fly_action: int | None = None


def signed_text(
    blob: bytes | None, epsilon: float | None, release_stamp_ns: int | None, seq: int, fly_action: int | None = None
) -> bytes:
    """What a signature covers: every field of the push (the blob by its SHA-256)."""
    digest = hashlib.sha256(blob).hexdigest() if blob is not None else "-"
    fly = "" if fly_action is None else f"|{fly_action!r}"
    return f"uav_push/1|{seq}|{digest}|{epsilon!r}|{release_stamp_ns!r}{fly}".encode()


def sign(
    key: bytes, blob: bytes | None, epsilon: float | None, release_stamp_ns: int | None, seq: int, fly_action: int | None = None
) -> str:
    return hmac.new(key, signed_text(blob, epsilon, release_stamp_ns, seq, fly_action), hashlib.sha256).hexdigest()


def verify(key: bytes, push: Push, last_seq: int) -> None:
    """ValueError unless `push` is signed with `key` and newer than `last_seq`."""
    if push.signature is None or push.seq is None:
        raise ValueError("unsigned push refused: a push must carry 'push_seq' and 'signature'")
    good = sign(key, push.weights, push.epsilon, push.release_stamp_ns, push.seq, push.fly_action)
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
    key: bytes | None = None,
    seq: int | None = None,
    fly_action: int | None = None,
) -> PushService.Request:
    """A push of weights (None: none), and optionally an exploration rate, a release stamp and the action the released
    frame is answered with; with `key`, signed as push `seq`."""
    epsilon = None if epsilon is None else float(epsilon)  # signed as the receiver reads them
    release_stamp_ns = None if release_stamp_ns is None else int(release_stamp_ns)
    fly_action = None if fly_action is None else int(fly_action)
    req = PushService.Request()
    if blob is not None:
        req.weights = array.array("B", blob)
    if epsilon is not None:
        req.epsilon = epsilon
    if release_stamp_ns is not None:
        req.release_stamp_ns = release_stamp_ns
    if fly_action is not None:
        req.fly_action = fly_action
    if key is not None:
        if seq is None:
            raise ValueError("a signed push needs its sequence number")
        req.push_seq = int(seq)
        req.signature = sign(key, None if blob is None else bytes(blob), epsilon, release_stamp_ns, int(seq), fly_action)
    return req


def read_push(request, max_bytes: int) -> Push:
    """The push in a request; ValueError names what is wrong (weights over `max_bytes`, an epsilon outside [0, 1], a
    negative stamp or action that is not the field's 'none', an action without a release, or nothing at all). The
    length is checked before anything of the weights is read."""
    n = len(request.weights)
    if n > max_bytes:
        raise ValueError(f"the push's weights ({n} bytes) are more than the {max_bytes} bytes allowed")
    blob = bytes(request.weights) if n else None
    keep, none = PushService.Request.KEEP_EPSILON, PushService.Request.NO_RELEASE
    eps = None if request.epsilon == keep else float(request.epsilon)
    if eps is not None and not (math.isfinite(eps) and 0.0 <= eps <= 1.0):
        raise ValueError(f"push field 'epsilon' must lie in [0, 1] (or be KEEP_EPSILON), got {eps}")
    stamp = None if request.release_stamp_ns == none else int(request.release_stamp_ns)
    if stamp is not None and stamp < 0:
        raise ValueError(f"push field 'release_stamp_ns' must be >= 0 (or NO_RELEASE), got {stamp}")
    fly = None if request.fly_action == PushService.Request.NETWORK_ANSWERS else int(request.fly_action)
    if fly is not None and (stamp is None or fly < 0):
        raise ValueError(f"push field 'fly_action' must be an action index >= 0 and come with 'release_stamp_ns', got {fly}")
    if blob is None and eps is None and stamp is None:
        raise ValueError("an empty push: expected weights, epsilon or release_stamp_ns")
    signed = bool(request.signature)
    return Push(blob, eps, stamp, int(request.push_seq) if signed else None, request.signature or None, fly)


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
        self.fly: tuple[int, int] | None = None  # (stamp, action): the released frame a teacher answers

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
        dropped, self.held, self.released_ns, self.newest_ns, self.fly = len(self.held), [], -1, -1, None
        return dropped

    def fly_action_for(self, stamp: int) -> int | None:
        """The action a release said the frame at `stamp` is answered with (a teacher's), or None: the network's."""
        return self.fly[1] if self.fly is not None and self.fly[0] == stamp else None

    def release(self, stamp: int, fly_action: int | None = None) -> list:
        """The held items released by a release up to `stamp`, oldest first; with `fly_action`, the frame at `stamp` is
        to be answered with that action (fly_action_for)."""
        if fly_action is not None:
            self.fly = (stamp, fly_action)
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
