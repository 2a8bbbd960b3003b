import dataclasses
import hashlib
import itertools

import pytest

from conftest import SMALL_WORLD
from uav_sim.simulator import obstacle_distance_m
from uav_sim.world import WorldError, load_world, procedural_world, training_layouts


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


def layout_digest(seeds) -> str:
    h = hashlib.sha256()
    for s in seeds:
        w = procedural_world(s)
        fields = [v for o in w.obstacles for v in dataclasses.astuple(o)] + [w.length_m, w.width_m, *w.start_xyz_m]
        h.update(repr([round(v, 6) if isinstance(v, float) else v for v in fields]).encode())
    return h.hexdigest()


def test_the_held_out_layouts_do_not_change():
    # random:0..999 are the held-out test layouts of every experiment in docs/RESULTS.md: changes to the
    # training layouts must leave them as they were (digest taken before the training-layout options were added).
    assert layout_digest(range(0, 1000, 37)) == "6fbbeb79a60eb2048385fbab6029a3c1dd2fa210d9ab4455880fc4e105280235"


def test_partition_layouts_add_long_boxes_and_keep_the_start_clear():
    w = load_world("random_partitions:7")
    assert w.name == "random_partitions:7" and w.length_m == load_world("random:7").length_m  # the same room
    layouts = [load_world(f"random_partitions:{101000 + i}") for i in range(100)]
    long_boxes = [sum(o.shape == "box" and max(o.size_x_m, o.size_y_m) >= 2.0 for o in w.obstacles) for w in layouts]
    plain = [
        sum(o.shape == "box" and max(o.size_x_m, o.size_y_m) >= 2.0 for o in w.obstacles)
        for w in itertools.islice(training_layouts(1), 100)
    ]
    assert sum(plain) == 0 and sum(n > 0 for n in long_boxes) >= 80  # 92 % of layouts have one or more
    for w in layouts:
        x, y, _ = w.start_xyz_m
        assert min(obstacle_distance_m(o, x, y) for o in w.obstacles) > 1.4, w.name
    with pytest.raises(WorldError, match="after 'random_partitions:' must be an integer"):
        load_world("random_partitions:x")


@pytest.mark.parametrize(
    "text, said",
    [
        (  # a typo that would fly the base world's obstacles
            "format: uav_sim_world/1\nbase: basic\nobstacle:\n  - {shape: box, x_m: 0, y_m: 2, size_x_m: 1}\n",
            ":3: unknown key 'obstacle' (did you mean 'obstacles'?); valid keys: format, name, base, room, start, obstacles,",
        ),
        (
            "format: uav_sim_world/1\nbase: basic\nroom: {length_m: 16, widht_m: 12}\n",
            ":3: unknown key 'widht_m' in 'room' (did you mean 'width_m'?); valid keys: length_m, width_m, wall_height_m",
        ),
        ("format: uav_sim_world/1\nbase: basic\nstart:\n  x_m: 0\n  yaw: 90\n", ":5: unknown key 'yaw' in 'start'"),
        (
            "format: uav_sim_world/1\nbase: basic\nweather: {rian: 3}\n",
            ":3: unknown key 'rian' in 'weather' (did you mean 'rain'?)",
        ),
        (
            "format: uav_sim_world/1\nbase: basic\nobstacles:\n  - {shape: cylinder, x_m: 3, y_m: -2, radius_m: 0.3, height_m: 3,"
            " colour: red}\n",
            ":4: unknown key 'colour' in obstacle 0 (cylinder); valid keys: shape, x_m, y_m, height_m, radius_m",
        ),
        ("format: uav_sim_world/1\nbase: basic\ncolour: red\n", ":3: unknown key 'colour'; valid keys"),
    ],
)
def test_unknown_or_misspelt_keys_stop_the_load_naming_key_line_and_valid_keys(tmp_path, text, said):
    path = write(tmp_path, text)
    with pytest.raises(WorldError) as e:
        load_world(path)
    assert str(e.value).startswith(path) and said in str(e.value), str(e.value)


def test_the_built_in_worlds_use_only_known_keys():
    for name in ("basic", "complex", "turbulent", SMALL_WORLD):
        assert load_world(name).obstacles
