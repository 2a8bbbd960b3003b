"""live_view: a Foxglove WebSocket server for the flying stack (what foxglove_bridge does on a full ROS
install), with foxglove-sdk.

    ros2 run uav_bringup live_view                  # then in Foxglove: Open connection, ws://localhost:8765
    ros2 run uav_bringup live_view --port 8766 --topics depth/image_raw attention/overlay --ros-args -r __ns:=/uav1

Serves the stack's topics as ROS 2 messages (CDR with their ros2msg schemas, so Foxglove decodes
them natively): the world's markers, odometry and trajectory for the 3D panel, the depth image with
the attention overlay, Q-values, the chosen action and /diagnostics. Topics are served as they
appear. The layout share/uav_bringup/foxglove/uav_stack.json (in the repository:
src/uav_bringup/foxglove/) arranges them in one click (Foxglove: Layouts, Import from file).
"""

from __future__ import annotations

import argparse
import sys

from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from uav_common.node_runner import run
from uav_common.ros_params import ParameterError

from .taps import DEFAULT_TOPICS, TopicTap, typestore


class LiveView(Node):
    def __init__(self, host: str, port: int, topics):
        super().__init__("live_view")
        import foxglove

        self.foxglove = foxglove
        try:
            self.server = foxglove.start_server(name="uav_stack", host=host, port=port)
        except Exception as e:  # the SDK raises its own error types; a taken port is the usual cause
            raise ParameterError(f"--port {port}: cannot serve on {host}:{port} ({e})") from None
        self.channels = {}
        self.messages = 0
        self.tap = TopicTap(self, topics, self.on_message, self.on_new)
        self.get_logger().info(
            f"Foxglove live view on ws://{host}:{self.server.port}: {' '.join(self.tap.wanted)} (served as they appear)"
        )

    def on_new(self, topic: str, msgtype: str) -> bool:
        ts = typestore()
        if msgtype not in ts.types:
            self.get_logger().warning(f"not serving {topic}: {msgtype} has no definition in the ROS 2 Jazzy type store")
            return False
        text, _ = ts.generate_msgdef(msgtype, ros_version=2)
        schema = self.foxglove.Schema(name=msgtype, encoding="ros2msg", data=text.encode())
        self.channels[topic] = self.foxglove.Channel(topic, schema=schema, message_encoding="cdr")
        return True

    def on_message(self, topic: str, _msgtype: str, data: bytes, receive_ns: int, _seq=None) -> None:
        self.channels[topic].log(bytes(data), log_time=receive_ns)
        self.messages += 1

    def close(self) -> None:
        self.server.stop()


def main(argv=None) -> int:
    argv = list(sys.argv if argv is None else ["live_view", *argv])
    ap = argparse.ArgumentParser(prog="live_view", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    ap.add_argument("--port", type=int, default=8765, help="WebSocket port (Foxglove's default: 8765; 0: any free port)")
    ap.add_argument("--topics", nargs="+", default=list(DEFAULT_TOPICS), metavar="TOPIC", help="topics to serve")
    a = ap.parse_args(remove_ros_args(argv)[1:])
    if not 0 <= a.port <= 65535:
        ap.error(f"--port {a.port}: must be 0..65535")
    return run(lambda: LiveView(a.host, a.port, a.topics), argv)


if __name__ == "__main__":
    raise SystemExit(main())
