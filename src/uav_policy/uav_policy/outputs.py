"""What policy_node publishes for each decision: the network's action (stamped with the frame: the record), the
command flown (cmd_vel, and cmd_vel_stamped for flight stacks), q_values, and what the decision looks at (SAM's
attention, the CNN's Grad-CAM saliency: maps on an absolute scale, overlays for a subscriber)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from geometry_msgs.msg import Twist, TwistStamped
from rclpy.node import Node
from sensor_msgs.msg import Image

from uav_common import contract
from uav_common.actions import Action
from uav_interfaces.msg import ActionValues, AttentionWeights

from .attention import attention_map, map_overlay, overlay
from .pilot import Decision


class Outputs:
    def __init__(self, node: Node, actions: tuple[Action, ...], stamped: bool, overlays: bool, max_range_m: float):
        self.actions, self.overlays, self.max_range_m = actions, overlays, max_range_m
        # A decision's record is kept deep for a recorder that falls behind (DECISION_QOS); the overlays (pictures of
        # 0.2 MB and more) STREAM_QOS's 100 deep.
        q, pub, big = contract.DECISION_QOS, node.create_publisher, contract.STREAM_QOS
        self.cmd = pub(Twist, contract.CMD_VEL_TOPIC, q)
        self.stamped = pub(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, q) if stamped else None
        self.base_frame = contract.vehicle_frame(node.get_namespace(), "base_link")  # what action commands move
        self.action = pub(TwistStamped, contract.ACTION_TOPIC, q)
        self.q_values = pub(ActionValues, contract.Q_VALUES_TOPIC, q)
        self.attention = (pub(Image, contract.ATTENTION_TOPIC, q), pub(Image, contract.ATTENTION_OVERLAY_TOPIC, big))
        self.weights = pub(AttentionWeights, contract.ATTENTION_WEIGHTS_TOPIC, q)
        self.saliency = (pub(Image, contract.SALIENCY_TOPIC, q), pub(Image, contract.SALIENCY_OVERLAY_TOPIC, big))
        self.local_map = pub(Image, contract.ATTENTION_LOCAL_MAP_TOPIC, big)  # a network with the local map, top-down
        self.action_names = tuple(a.name for a in actions)
        self.last_cmd, self.last_cmd_unheard = None, False
        self.sent: dict[str, int] = {}  # messages published per topic of the decision's record

    def listeners(self) -> dict[str, int]:
        """Of the decision's record (the action, the command, q_values and the attention map): {`subscribers TOPIC`:
        subscriptions matched}, as this node's publishers see them (discovery matches a subscription on each side at
        its own time: fly waits for both before the first frame), and {`published TOPIC`: messages sent} (at the end
        fly waits until a recorder has them all: a reliable message still on its way is lost when we exit)."""
        pubs = (self.action, self.cmd, self.q_values, self.attention[0])
        heard = {f"subscribers {p.topic_name}": p.get_subscription_count() for p in pubs}
        return heard | {f"published {p.topic_name}": self.sent.get(p.topic_name, 0) for p in pubs}

    def _send(self, pub, msg) -> None:
        pub.publish(msg)
        self.sent[pub.topic_name] = self.sent.get(pub.topic_name, 0) + 1

    def decision(self, img: Image, d: Decision, command_of) -> None:
        """The network's choice (the record: it goes out before the command, so whatever is flown is on record)
        and the command flown: the action's (`command_of(action)`), or what the safety layer made of it."""
        chosen = Twist()
        chosen.linear.x, chosen.angular.z = command_of(d.action)
        stamped = TwistStamped(twist=chosen)
        stamped.header.stamp, stamped.header.frame_id = img.header.stamp, self.base_frame
        self._send(self.action, stamped)
        cmd = chosen
        if d.safety:
            cmd = Twist()
            cmd.linear.x, cmd.angular.z = d.linear_x_mps, d.yaw_rate_radps
        self.command(cmd, img.header.stamp)

    def command(self, cmd: Twist, stamp) -> None:
        self.last_cmd_unheard = self.cmd.get_subscription_count() == 0
        self._send(self.cmd, cmd)
        if self.stamped is not None:
            out = TwistStamped(twist=cmd)
            out.header.stamp, out.header.frame_id = stamp, self.base_frame
            self.stamped.publish(out)
        self.last_cmd = cmd

    def forget(self) -> None:
        """The source restarted: nothing from before is said again."""
        self.last_cmd, self.last_cmd_unheard = None, False

    def say_again(self) -> None:
        """The simulator said an answered frame again, and our command went out before anyone listened (discovery):
        say it again. A command that had a reliable listener is only late (a busy machine); answering it twice would
        advance a lockstep sim two steps."""
        if self.last_cmd_unheard:
            self.last_cmd_unheard = self.cmd.get_subscription_count() == 0
            self._send(self.cmd, self.last_cmd)

    def explained(self, img: Image, depth: np.ndarray, d: Decision, grid_hw, view, grid=None) -> Callable | None:
        """q_values and SAM's attention maps (with the local map's `grid`, the picture of what it weighs there); for the
        CNN, the saliency publisher `publish(rows)` when someone subscribes (its Grad-CAM costs a backward pass), else
        None."""
        self._send(self.q_values, contract.action_values_msg(img.header, d.q, self.action_names, d.action))
        maps = lambda rows, kind, pubs: self._map(img, depth, d, rows, grid_hw, view, kind, pubs)  # noqa: E731
        if d.attention is not None:  # SAM: the attention is at hand
            maps(d.attention, "attention", self.attention)
            if self.weights.get_subscription_count() > 0:
                self.weights.publish(contract.attention_weights_msg(img.header, d.attention, grid_hw))
            if grid is not None and self.local_map.get_subscription_count() > 0:
                label = self.actions[d.action].name.split("_", 1)[0]
                self.local_map.publish(contract.rgb_image(img.header, map_overlay(grid, d.attention, grid_hw, label)))
            return None
        if any(p.get_subscription_count() > 0 for p in self.saliency):
            return lambda rows: maps(rows, "saliency", self.saliency)
        return None

    def _map(self, img: Image, depth: np.ndarray, d: Decision, rows, grid_hw, view, kind: str, pubs) -> None:
        """The map (32FC1, relative to a uniform share) and, when subscribed, its overlay with the network's action and Q
        lead over the next best (and, where the shield overrode it, the action flown)."""
        pub_map, pub_overlay = pubs
        to_overlay = self.overlays and pub_overlay.get_subscription_count() > 0
        if pub_map.get_subscription_count() == 0 and not to_overlay:
            return  # drawn for no one (a training run's policy): not on the per-step path
        amap = attention_map(rows, grid_hw, depth.shape, view)
        self._send(pub_map, contract.depth_to_image(amap, img.header.stamp, img.header.frame_id))
        if to_overlay:
            q, action = d.q, d.unshielded if d.unshielded >= 0 else d.action
            second = np.partition(q, -2)[-2] if len(q) > 1 else q[action]
            name = lambda a: self.actions[a].name.split("_", 1)[0]  # noqa: E731
            label = f"{name(action)} Q {q[action]:.2f}, lead {q[action] - second:+.2f}"
            label += f"; shield: {name(d.action)}" if d.shield else ""
            pub_overlay.publish(contract.rgb_image(img.header, overlay(depth, amap, self.max_range_m, label, kind)))
