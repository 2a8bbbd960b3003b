"""Watch a policy fly, for users with a full ROS 2 install: sim_node in real time and policy_node with
params/*.yaml, optionally the recorder and the Foxglove live view. `fly` does the same on the pip
set-up (and is what this repository tests; `launch` is not on PyPI).

    ros2 launch uav_bringup fly.launch.py params_dir:=$PWD/params model:=sam world:=turbulent live_view:=true
    ros2 launch uav_bringup fly.launch.py namespace:=uav1 record:=runs/bags/uav1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition, LaunchConfigurationNotEquals
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackagePrefix


def generate_launch_description():
    params = LaunchConfiguration("params_dir")
    ns = LaunchConfiguration("namespace")
    tool = lambda exe: PathJoinSubstitution([FindPackagePrefix("uav_bringup"), "lib", "uav_bringup", exe])  # noqa: E731
    ros_ns = ["--ros-args", "-r", ["__ns:=/", ns]]
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_dir", default_value="params"),
            DeclareLaunchArgument("model", default_value="sam"),
            DeclareLaunchArgument("world", default_value="basic"),
            DeclareLaunchArgument("namespace", default_value="", description="e.g. uav1: topics and frames uav1/..."),
            DeclareLaunchArgument("record", default_value="", description="a bag folder to record the flight to"),
            DeclareLaunchArgument("live_view", default_value="false", description="serve Foxglove on ws://localhost:8765"),
            ExecuteProcess(
                cmd=[tool("record"), "-o", LaunchConfiguration("record"), *ros_ns],
                condition=LaunchConfigurationNotEquals("record", ""),
                output="screen",
            ),
            ExecuteProcess(
                cmd=[tool("live_view"), *ros_ns], condition=IfCondition(LaunchConfiguration("live_view")), output="screen"
            ),
            Node(
                package="uav_sim",
                executable="sim_node",
                namespace=ns,
                parameters=[
                    PathJoinSubstitution([params, "sim.yaml"]),
                    {"world": LaunchConfiguration("world"), "mode": "realtime"},
                ],
                output="screen",
            ),
            Node(
                package="uav_policy",
                executable="policy_node",
                namespace=ns,
                parameters=[
                    PathJoinSubstitution([params, "policy.yaml"]),
                    {"model": LaunchConfiguration("model"), "source": "simulator"},
                ],
                output="screen",
            ),
        ]
    )
