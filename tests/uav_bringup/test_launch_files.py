"""The launch files for a full ROS 2 install (`launch` is not on PyPI, so they cannot run here): what they name must
exist. Each node parameter they set is one the node declares, each parameter file and recipe they read is in params/,
and each executable they start is installed."""

import ast

import pytest

from conftest import ROOT, executable
from uav_common.settings import specs
from uav_policy.config import PolicySettings
from uav_sim.sim_settings import SimNodeSettings
from uav_trainer.trainer_settings import TrainerNodeSettings

DECLARED = {
    "sim_node": {s.name for s in specs(SimNodeSettings)},
    "policy_node": {s.name for s in specs(PolicySettings)},
    "trainer_node": {s.name for s in specs(TrainerNodeSettings)},
}
LAUNCH_FILES = [ROOT / "src/uav_bringup/launch/fly.launch.py", ROOT / "src/uav_trainer/launch/train.launch.py"]


def calls(tree, name):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == name]


def keyword(call, name):
    return next((k.value for k in call.keywords if k.arg == name), None)


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_a_launch_file_sets_only_declared_parameters_from_files_that_exist(path):
    tree = ast.parse(path.read_text())
    nodes = calls(tree, "Node")
    assert nodes, "no Node in the launch file"
    defaults = {
        ast.literal_eval(c.args[0]): ast.literal_eval(keyword(c, "default_value")) for c in calls(tree, "DeclareLaunchArgument")
    }
    for node in nodes:
        exe, pkg = ast.literal_eval(keyword(node, "executable")), ast.literal_eval(keyword(node, "package"))
        assert executable(pkg, exe).exists(), f"{pkg} {exe} is not installed"
        given = [k for d in ast.walk(keyword(node, "parameters")) if isinstance(d, ast.Dict) for k in d.keys]
        names = {ast.literal_eval(k) for k in given}
        assert names and names <= DECLARED[exe], f"{exe}: {sorted(names - DECLARED[exe])} are not declared parameters"
        assert (ROOT / "params" / f"{exe.removesuffix('_node')}.yaml").exists()  # the node's parameter file
    parts = {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}  # f"{node}.yaml": above
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value.endswith(".yaml") and id(n) not in parts:
            assert (ROOT / "params" / n.value).exists(), f"params/{n.value} is missing"
    if "recipe" in defaults:
        assert (ROOT / "params/recipes" / f"{defaults['recipe']}.yaml").exists()
    for call in calls(tree, "tool"):
        assert executable("uav_bringup", ast.literal_eval(call.args[0])).exists()
