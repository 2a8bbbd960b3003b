import itertools

import pytest

from uav_sim.world import WorldError, load_world, training_layouts


def write(tmp_path, text, name="w.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def test_user_world_file_loads(tmp_path):
    path = write(
        tmp_path,
        """
format: uav_sim_world/1
name: mine
room: {length_m: 10, width_m: 8, wall_height_m: 3}
start: {x_m: -3, y_m: 0}
obstacles:
  - {shape: cylinder, x_m: 1, y_m: 1, radius_m: 0.3, height_m: 3}
weather: {snow: 5}
""",
    )
    w = load_world(path)
    assert w.name == "mine" and w.obstacles[0].shape == "cylinder" and w.weather.snow == 5
    assert w.start_xyz_m == (-3.0, 0.0, 1.0)


def test_base_inheritance(tmp_path):
    w = load_world(write(tmp_path, "format: uav_sim_world/1\nbase: complex\nweather: {rain: 3}\n"))
    assert w.obstacles == load_world("complex").obstacles and w.weather.rain == 3


@pytest.mark.parametrize(
    "text, message",
    [
        ("format: uav_sim_world/1\nroom: [1, 2]\n", "'room' must be a mapping"),
        ("format: other\n", "'format' must be"),
        (
            "format: uav_sim_world/1\nroom: {length_m: 10, width_m: 8, wall_height_m: 3}\n",
            "missing required field 'x_m'",
        ),
        ("format: uav_sim_world/1\nbase: basic\nobstacles: [{shape: sphere}]\n", "'box' or 'cylinder'"),
        ("format: uav_sim_world/1\nbase: basic\nobstacles: [{shape: box, x_m: .nan, y_m: 0}]\n", "finite number"),
        ("format: uav_sim_world/1\nbase: basic\nstart: {x_m: 100}\n", "not inside the room"),
        ("format: [unclosed\n", "not valid YAML"),
    ],
)
def test_malformed_world_files_fail_with_a_clear_message(tmp_path, text, message):
    with pytest.raises(WorldError, match=message):
        load_world(write(tmp_path, text))


def test_unknown_name_and_missing_file():
    with pytest.raises(WorldError, match="unknown world 'mars'"):
        load_world("mars")
    with pytest.raises(WorldError, match="cannot read world file"):
        load_world("/nonexistent/world.yaml")


def test_training_layouts_can_mix_a_world_in_every_kth_episode():
    basic = load_world("basic")
    plain = [w.name for w in itertools.islice(training_layouts(2), 6)]
    mixed = [w.name for w in itertools.islice(training_layouts(2, basic, 3), 9)]
    # Every third episode is Basic; the layouts in between keep their order and skip none.
    assert mixed[2::3] == ["basic"] * 3
    assert [n for i, n in enumerate(mixed) if i % 3 != 2] == plain
    assert [w.name for w in itertools.islice(training_layouts(2, basic, 0), 6)] == plain
    for bad in (1, -2):
        with pytest.raises(ValueError, match="world_every"):
            training_layouts(2, basic, bad)
    with pytest.raises(ValueError, match="world_every"):
        training_layouts(2, None, 3)
