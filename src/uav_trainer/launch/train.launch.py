"""The main job for users with a full ROS 2 install: the three nodes with params/*.yaml and a recipe file
(params/recipes/<recipe>.yaml, the same file `ros2 run uav_trainer train --recipe` reads), learning in
lockstep. `train` is what this repository tests (`launch` is not on PyPI).

    ros2 launch uav_trainer train.launch.py params_dir:=$PWD/params recipe:=shipped total_steps:=30000

sim_node's planner answers every frame as a teacher (`teacher`, default stack: what the shipped recipe's trainer learns
from; a trainer without a teacher, `recipe:=rl`, does not listen, and `teacher:=none` spares the planner's time).

Pushes are signed with the key in push_key_file (default runs/train/push.key): trainer_node creates it
(mode 0600) when it is missing, policy_node reads it at the first push.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    params = LaunchConfiguration("params_dir")
    recipe = PathJoinSubstitution([params, "recipes", PythonExpression(["'", LaunchConfiguration("recipe"), "' + '.yaml'"])])
    files = lambda node: [PathJoinSubstitution([params, f"{node}.yaml"]), recipe]  # noqa: E731
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_dir", default_value="params"),
            DeclareLaunchArgument("recipe", default_value="shipped"),
            DeclareLaunchArgument("total_steps", default_value="30000"),
            DeclareLaunchArgument("push_key_file", default_value="runs/train/push.key"),
            DeclareLaunchArgument("teacher", default_value="stack"),
            Node(
                package="uav_sim",
                executable="sim_node",
                parameters=[*files("sim"), {"wait_for_subscribers": 2, "teacher": LaunchConfiguration("teacher")}],
            ),
            Node(
                package="uav_policy",
                executable="policy_node",
                parameters=[
                    *files("policy"),
                    {
                        "epsilon": 1.0,
                        "wait_for_trainer": True,
                        "accept_pushes": True,
                        "safety": False,
                        "shield": "never",
                        "push_key_file": LaunchConfiguration("push_key_file"),
                    },
                ],
            ),
            Node(
                package="uav_trainer",
                executable="trainer_node",
                parameters=[
                    *files("trainer"),
                    {
                        "total_steps": ParameterValue(LaunchConfiguration("total_steps"), value_type=int),
                        "push_key_file": LaunchConfiguration("push_key_file"),
                    },
                ],
            ),
        ]
    )
