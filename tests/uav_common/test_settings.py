"""One declaration per setting: ROS parameters, flags, params/*.yaml and the reference come from it."""

import argparse
import dataclasses
import subprocess
import sys

import pytest
import yaml

from conftest import ROOT, executable
from uav_common.settings import SettingError, add_flags, build, given_flags, setting, specs


@dataclasses.dataclass(frozen=True)
class Inner:
    rate: float = setting(0.5, "a rate", 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class Outer:
    name: str = setting("a", "a choice", choices=("a", "b"))
    sizes: tuple[int, ...] = setting((1, 2), "sizes")
    on: bool = setting(True, "a switch")
    frames: int = setting(5, "frames", 1, 16, name="frame_stack")
    inner: Inner = Inner()
    derived: int = 3  # not a setting


def test_specs_are_flat_and_renamed_and_skip_derived_fields():
    assert [s.name for s in specs(Outer)] == ["name", "sizes", "on", "frame_stack", "rate"]


def test_build_checks_ranges_types_and_choices_and_rebuilds_nested_configs():
    o = build(Outer, {"rate": 1, "frame_stack": 7, "sizes": [3]})
    assert o.inner.rate == 1.0 and isinstance(o.inner.rate, float) and o.frames == 7 and o.sizes == (3,)
    with pytest.raises(SettingError, match=r"'rate'=2.0 is outside \[0.0, 1.0\]"):
        build(Outer, {"rate": 2.0})
    with pytest.raises(SettingError, match="expected one of a, b"):
        build(Outer, {"name": "c"})
    with pytest.raises(SettingError, match="must be of type int"):
        build(Outer, {"frame_stack": "5"})
    with pytest.raises(SettingError, match="did you mean 'frame_stack'"):
        build(Outer, {"frame_stak": 5})


def test_flags_come_from_the_same_declarations_and_default_to_not_given():
    ap = argparse.ArgumentParser()
    add_flags(ap, Outer)
    assert given_flags(ap.parse_args([])) == {}
    got = given_flags(ap.parse_args(["--rate", "0.25", "--no-on", "--sizes", "4", "5", "--frame-stack", "2"]))
    assert got == {"rate": 0.25, "on": False, "sizes": [4, 5], "frame_stack": 2}
    assert build(Outer, got).sizes == (4, 5)


@pytest.mark.parametrize("name", ["sim", "policy", "trainer"])
def test_each_params_file_holds_exactly_the_declared_defaults(name):
    sys.path.insert(0, str(ROOT / "scripts"))
    import param_reference

    declared = {s.name: s.default for s in specs(param_reference.NODES[name][2])}
    given = yaml.safe_load((ROOT / "params" / f"{name}.yaml").read_text())["/**"]["ros__parameters"]
    assert set(given) == set(declared), f"undeclared: {set(given) - set(declared)}, missing: {set(declared) - set(given)}"
    for key, value in given.items():
        want = declared[key]
        assert (tuple(value) if isinstance(value, list) else value) == want, key


def test_the_parameter_reference_and_params_files_are_up_to_date():
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "param_reference.py"), "--check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize(
    "pkg,exe,param,says",
    [
        ("uav_trainer", "trainer_node", "n_step:=3", "'n_step' was removed"),
        ("uav_trainer", "trainer_node", "lerning_rate:=0.1", "did you mean 'learning_rate'"),
        ("uav_sim", "sim_node", "max_rate_hz:=30.0", "'max_rate_hz' was removed"),
        ("uav_policy", "policy_node", "ensemble_rule:=min", "'ensemble_rule' was removed"),
    ],
)
def test_nodes_refuse_retired_and_misspelt_parameters_naming_them(pkg, exe, param, says, tmp_path, ros_domain):
    env = {**__import__("os").environ, "ROS_DOMAIN_ID": ros_domain, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    args = [str(executable(pkg, exe)), "--ros-args", "-p", param, "-p", f"run_dir:={tmp_path}"]
    if exe != "trainer_node":
        args = args[:-2]
    r = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2 and says in r.stdout + r.stderr, r.stdout + r.stderr
