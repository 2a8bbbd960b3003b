"""Minimal launch file for users with a full ROS 2 install: the same three nodes, parameter files and
default recipe ("ensemble", for the default 30 000-step budget) and lockstep learning as
`ros2 run uav_trainer train` (which is what this repository tests; `launch` is not on PyPI).

    ros2 launch uav_trainer train.launch.py params_dir:=$PWD/params
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node


def generate_launch_description():
    params = LaunchConfiguration("params_dir")
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_dir", default_value="params"),
            Node(
                package="uav_sim",
                executable="sim_node",
                parameters=[
                    PathJoinSubstitution([params, "sim.yaml"]),
                    {
                        "start_yaw_jitter_deg": 180.0,
                        "max_rate_hz": 0.0,  # lockstep learning: acting waits for learning
                        "wait_for_subscribers": 2,
                        "world": "random_each_episode",
                        "hfov_deg": 150.0,
                        "reward_window_fraction": 0.078,
                        "mix_world": "basic",
                        "mix_world_every": 4,
                        "max_episode_steps": 300,
                    },
                ],
            ),
            Node(
                package="uav_policy",
                executable="policy_node",
                parameters=[PathJoinSubstitution([params, "policy.yaml"]), {"epsilon": 1.0, "wait_for_trainer": True}],
            ),
            Node(
                package="uav_trainer",
                executable="trainer_node",
                parameters=[
                    PathJoinSubstitution([params, "trainer.yaml"]),
                    {
                        "lockstep_learning": True,
                        "turn_penalty": 1.0,
                        "replay_ratio": 0.5,
                        "total_steps": 30000,
                        "save_weights_every_steps": 1000,
                        "save_weights_from_step": 21000,
                    },
                ],
            ),
        ]
    )
