"""Taking a weights push (uav_policy.push) on policy_node's side, without ROS: authenticated with the run's key (read
at the first push: trainer_node may write the file after the policy starts), in sequence, releasing no frame beyond
those seen, and weights priced against the control period before anything of them is built; each outcome counted.

`log` is a logger with rclpy's signature (warning(message, throttle_duration_sec=...)).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from . import weights as wio
from .networks import NetConfig, QEnsemble, forward_flops
from .push import Push, ReleaseGate, load_key, read_push, verify


class Refused(ValueError):
    """A push of which nothing is taken and no frame released: forged, played again, or releasing too far."""


class PushReceiver:
    def __init__(self, key_file: str, gate: ReleaseGate, control_period_s: float, log, actions: int):
        self.key_file, self.gate, self.control_period_s, self.log = key_file, gate, control_period_s, log
        self.actions = actions  # the action table's size: a release's fly_action must index it
        self.key: bytes | None = None
        self.last_seq = -1
        self.seconds_per_flop = 0.0  # this machine's inference time per operation (time_inference)
        self.spare = None  # the network the last push replaced: the next push of its architecture is loaded into it
        self.accepted = self.rejected = self.unauthenticated = self.releases_refused = 0

    def time_inference(self, agent) -> None:
        """Time the network flown at start (the best of five passes): what prices a pushed architecture."""
        net = agent.net
        members = len(net.members) if isinstance(net, QEnsemble) else 1
        state = np.zeros((net.cfg.channels, net.cfg.height, net.cfg.width), np.float32)
        agent.q_values(state)  # warm-up
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            agent.q_values(state)
            best = min(best, time.perf_counter() - t0)
        self.seconds_per_flop = best / (members * forward_flops(net.cfg))

    def authenticate(self, request) -> Push:
        """The request's push: Refused (counted) when nothing of it may be taken, ValueError when malformed."""
        push = read_push(request, wio.MAX_BYTES)
        try:
            if self.key is None:
                self.key = load_key(self.key_file)
            verify(self.key, push, self.last_seq)
        except ValueError as e:  # not from our trainer: nothing of it is taken, no frame is released
            self.unauthenticated += 1
            self.log.warning(f"weights push refused: {e}", throttle_duration_sec=5.0)
            raise Refused(str(e)) from None
        self.last_seq = push.seq
        beyond = None if push.release_stamp_ns is None else self.gate.beyond(push.release_stamp_ns)
        if beyond:  # a trainer that lost track of the stream
            self.releases_refused += 1
            self.log.warning(f"weights push refused: {beyond}", throttle_duration_sec=5.0)
            raise Refused(beyond)
        if push.fly_action is not None and push.fly_action >= self.actions:
            raise ValueError(f"push field 'fly_action' {push.fly_action} is not an action of this policy's {self.actions}")
        return push

    def check_cost(self, blob: bytes, cfg: NetConfig) -> None:
        """ValueError when the blob's architecture (priced from its header, over `cfg` the interface flown)
        would not answer within the control period here."""
        flops = forward_flops(wio.with_sizes_of(cfg, wio.read_header_config(blob)))
        seconds = flops * self.seconds_per_flop
        if seconds > self.control_period_s:
            raise ValueError(
                f"the pushed architecture ({flops / 1e6:.0f} MFLOP a frame) would take about {1e3 * seconds:.0f} ms a "
                f"frame here, more than the {1e3 * self.control_period_s:.0f} ms control period (control_rate_hz)"
            )

    def load(self, blob: bytes, cfg: NetConfig, reuse: bool) -> torch.nn.Module:
        """The pushed network: priced (check_cost), checked and loaded (weights.load_bytes; the trainer owns the
        layer sizes, the interface must match `cfg`). `reuse`: the spare is written over when it has the pushed
        architecture (False while anything may still read it)."""
        self.check_cost(blob, cfg)
        if wio.read_header_config(blob).local_map != cfg.local_map:
            has = "needs" if cfg.local_map else "does not take"
            raise ValueError(f"the pushed network's local map input differs: the one flown {has} it (restart policy_node)")
        spare, self.spare = (self.spare if reuse else None), None
        return wio.load_bytes(blob, cfg, sizes_from_blob=True, into=spare)

    def retire(self, net: torch.nn.Module) -> None:
        """`net` is no longer flown: the spare of the next load."""
        self.spare = None if isinstance(net, QEnsemble) else net

    def reject(self, why: str, released: bool) -> str:
        """A push whose weights or epsilon were not taken (counted, logged); the answer's message. A well-formed
        push releases its frames all the same (answered on the weights and epsilon in use), so a refusal never
        holds a frame for wait_for_trainer_timeout_s."""
        self.rejected += 1
        message = why + ("; its frame release was applied, acting on the weights and epsilon in use" if released else "")
        self.log.warning(f"weights push rejected: {message}")
        return message

    def values(self) -> dict:
        return {
            "pushes_accepted": self.accepted,
            "pushes_rejected": self.rejected,
            "pushes_unauthenticated": self.unauthenticated,
            "releases_refused": self.releases_refused,
        }
