"""World descriptions: small YAML scene files, validated into plain dataclasses.

Format (`format: uav_sim_world/1`), all lengths in metres, angles in degrees:

    format: uav_sim_world/1
    name: basic
    base: basic            # optional: start from another world (built-in name or path)
    room: {length_m: 16, width_m: 12, wall_height_m: 3}   # walls enclose |x|<=L/2, |y|<=W/2
    start: {x_m: -6, y_m: 0, z_m: 1, yaw_deg: 0}
    obstacles:             # replaces the base's list when given
      - {shape: box, x_m: 0, y_m: 2, size_x_m: 1, size_y_m: 1, height_m: 3, yaw_deg: 0}
      - {shape: cylinder, x_m: 3, y_m: -2, radius_m: 0.3, height_m: 3}
    weather: {rain: 0, snow: 0, leaves: 0}   # particle counts around the vehicle

Built-in worlds live in the package's `worlds/` folder (installed to share/uav_sim/worlds);
`random` (or `random:SEED`) makes a seeded procedural layout for held-out testing;
`random_partitions[:SEED]` the same with long partitions among the boxes (held-out evaluation);
`validation:K` (K = 0..99) is a validation world, seeded layouts with partitions, doorways or weather
that nothing trains or tests on (VALIDATION_WORLDS, the set every choice is made on);
`random_each_episode` (sim_node) flies a new one every episode, for training.
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from uav_common.settings import setting

FORMAT = "uav_sim_world/1"
BUILTIN_WORLDS = ("basic", "complex", "turbulent")
EACH_EPISODE = "random_each_episode"  # sim_node: a new training layout every episode
PARTITIONS = "random_partitions"  # procedural layouts where half of the boxes are 2-3 m partitions
TRAINING_LAYOUTS_FROM = 1000  # random:0..999 are never trained on (test and validation layouts)
# The validation worlds: validation:K is built from the layout seed VALIDATION_SEEDS_FROM + K, so its layouts are
# neither the training stream's (random:1000 onward) nor the held-out tests' (random:0..899, random_partitions:0..899,
# of which docs/RESULTS.md reports 0..2), and the test worlds (basic, complex, turbulent) are files.
VALIDATION = "validation"
VALIDATION_SEEDS_FROM = 900
VALIDATION_MAX = 100  # validation:0..99
# Families by K % 4: a plain layout, partitions among the boxes, cross walls with doorways, a plain layout in weather.
VALIDATION_FAMILIES = ("layout", "partitions", "doorways", "weather")
VALIDATION_WORLDS = tuple(f"{VALIDATION}:{k}" for k in range(8))  # the set `evaluate --worlds validation` and train fly
VALIDATION_STEPS = 500  # a choice flies each weights file this many steps per validation world: 4000 in all


# The room's walls, at x = +L/2, -L/2, y = +W/2, -W/2. Where a body must be named by one number (what a pixel shows,
# what a decision is about), an obstacle is its index in World.obstacles and wall i is wall_code(i).
WALLS = ("wall_x+", "wall_x-", "wall_y+", "wall_y-")


def wall_code(i: int) -> int:
    """The number that names wall i of WALLS (-2 .. -5; obstacles are >= 0, -1 is nothing)."""
    return -2 - i


class WorldError(ValueError):
    """A world name, file or field that cannot be used; the message says which and why."""


@dataclasses.dataclass(frozen=True)
class Obstacle:
    shape: str  # "box" or "cylinder"
    x_m: float
    y_m: float
    height_m: float
    size_x_m: float = 0.0
    size_y_m: float = 0.0
    radius_m: float = 0.0
    yaw_deg: float = 0.0


@dataclasses.dataclass(frozen=True)
class Weather:
    rain: int = 0
    snow: int = 0
    leaves: int = 0

    @property
    def any(self) -> bool:
        return self.rain + self.snow + self.leaves > 0


@dataclasses.dataclass(frozen=True)
class World:
    name: str
    length_m: float
    width_m: float
    wall_height_m: float
    start_xyz_m: tuple[float, float, float]
    start_yaw_deg: float
    obstacles: tuple[Obstacle, ...]
    weather: Weather


def worlds_dir() -> Path:
    """Folder of the built-in world files (installed share/ first, source tree second)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory("uav_sim")) / "worlds"
        if share.is_dir():
            return share
    except Exception:  # not installed with colcon: fall back to the source tree
        pass
    return Path(__file__).resolve().parent.parent / "worlds"


def _num(d: dict, key: str, where: str, default=None, minimum=None) -> float:
    if key not in d:
        if default is None:
            raise WorldError(f"{where}: missing required field '{key}'")
        return float(default)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise WorldError(f"{where}: field '{key}' must be a finite number, got {v!r}")
    if minimum is not None and v < minimum:
        raise WorldError(f"{where}: field '{key}' must be >= {minimum}, got {v}")
    return float(v)


def _int(d: dict, key: str, where: str) -> int:
    v = d.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0 or v > 2000:
        raise WorldError(f"{where}: field '{key}' must be an integer in [0, 2000], got {v!r}")
    return v


def _dict(d, key: str, where: str) -> dict:
    v = d.get(key, {})
    if not isinstance(v, dict):
        raise WorldError(f"{where}: field '{key}' must be a mapping, got {type(v).__name__}")
    return v


def _obstacle(o, where: str) -> Obstacle:
    if not isinstance(o, dict):
        raise WorldError(f"{where}: each obstacle must be a mapping, got {o!r}")
    shape = o.get("shape")
    if shape == "box":
        return Obstacle(
            "box",
            _num(o, "x_m", where),
            _num(o, "y_m", where),
            _num(o, "height_m", where, minimum=0.01),
            size_x_m=_num(o, "size_x_m", where, minimum=0.01),
            size_y_m=_num(o, "size_y_m", where, minimum=0.01),
            yaw_deg=_num(o, "yaw_deg", where, default=0.0),
        )
    if shape == "cylinder":
        return Obstacle(
            "cylinder",
            _num(o, "x_m", where),
            _num(o, "y_m", where),
            _num(o, "height_m", where, minimum=0.01),
            radius_m=_num(o, "radius_m", where, minimum=0.01),
        )
    raise WorldError(f"{where}: obstacle shape must be 'box' or 'cylinder', got {shape!r}")


# The keys a world file may hold, per level; anything else (a typo, a key of another format) is refused.
TOP_KEYS = ("format", "name", "base", "room", "start", "obstacles", "weather")
SECTION_KEYS = {
    "room": ("length_m", "width_m", "wall_height_m"),
    "start": ("x_m", "y_m", "z_m", "yaw_deg"),
    "weather": ("rain", "snow", "leaves"),
}
OBSTACLE_KEYS = {
    "box": ("shape", "x_m", "y_m", "height_m", "size_x_m", "size_y_m", "yaw_deg"),
    "cylinder": ("shape", "x_m", "y_m", "height_m", "radius_m"),
}


def _check_keys(node: yaml.Node, source: str) -> None:
    """WorldError for the first key the format does not know, at any level, with its line, a did-you-mean
    and the valid keys: a typo such as 'obstacle:' must not silently fly the base world's obstacles."""

    def check(mapping: yaml.Node, valid, where: str) -> dict:
        if not isinstance(mapping, yaml.MappingNode):
            return {}
        keys = {}
        for k, v in mapping.value:
            key = k.value if isinstance(k, yaml.ScalarNode) else str(k.value)
            if key not in valid:
                close = difflib.get_close_matches(key, valid, n=1)
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                raise WorldError(
                    f"{source}:{k.start_mark.line + 1}: unknown key '{key}'{where}{hint}; valid keys: {', '.join(valid)}"
                )
            keys[key] = v
        return keys

    top = check(node, TOP_KEYS, "")
    for section, valid in SECTION_KEYS.items():
        if section in top:
            check(top[section], valid, f" in '{section}'")
    if isinstance(top.get("obstacles"), yaml.SequenceNode):
        for i, o in enumerate(top["obstacles"].value):
            shape = next((v.value for k, v in getattr(o, "value", []) if getattr(k, "value", None) == "shape"), None)
            valid = OBSTACLE_KEYS.get(shape, tuple(dict.fromkeys(OBSTACLE_KEYS["box"] + OBSTACLE_KEYS["cylinder"])))
            check(o, valid, f" in obstacle {i}" + (f" ({shape})" if shape in OBSTACLE_KEYS else ""))


def _parse(doc, source: str, depth: int = 0) -> World:
    if not isinstance(doc, dict):
        raise WorldError(f"{source}: a world file must be a YAML mapping")
    if doc.get("format") != FORMAT:
        raise WorldError(f"{source}: 'format' must be '{FORMAT}', got {doc.get('format')!r}")
    base = None
    if "base" in doc:
        if depth > 4:
            raise WorldError(f"{source}: 'base' chain is too deep (a cycle?)")
        base = load_world(str(doc["base"]), _depth=depth + 1)
    room = _dict(doc, "room", source)
    start = _dict(doc, "start", source)
    weather = _dict(doc, "weather", source)
    b = base
    length = _num(room, "length_m", f"{source} room", b and b.length_m, minimum=2.0)
    width = _num(room, "width_m", f"{source} room", b and b.width_m, minimum=2.0)
    wall_h = _num(room, "wall_height_m", f"{source} room", b and b.wall_height_m, minimum=0.5)
    sx = _num(start, "x_m", f"{source} start", b.start_xyz_m[0] if b else None)
    sy = _num(start, "y_m", f"{source} start", b.start_xyz_m[1] if b else None)
    sz = _num(start, "z_m", f"{source} start", b.start_xyz_m[2] if b else 1.0, minimum=0.2)
    syaw = _num(start, "yaw_deg", f"{source} start", b.start_yaw_deg if b else 0.0)
    if abs(sx) > length / 2 - 0.3 or abs(sy) > width / 2 - 0.3 or sz > wall_h:
        raise WorldError(f"{source}: start ({sx}, {sy}, {sz}) is not inside the room")
    if "obstacles" in doc:
        raw = doc["obstacles"] or []
        if not isinstance(raw, list):
            raise WorldError(f"{source}: 'obstacles' must be a list")
        obstacles = tuple(_obstacle(o, f"{source} obstacle {i}") for i, o in enumerate(raw))
    else:
        obstacles = b.obstacles if b else ()
    if weather or not b:
        w = Weather(
            rain=_int(weather, "rain", f"{source} weather"),
            snow=_int(weather, "snow", f"{source} weather"),
            leaves=_int(weather, "leaves", f"{source} weather"),
        )
    else:
        w = b.weather
    name = str(doc.get("name", Path(source).stem))
    return World(name, length, width, wall_h, (sx, sy, sz), syaw, obstacles, w)


def load_world(name_or_path: str, seed: int = 0, _depth: int = 0) -> World:
    """A world by built-in name (basic, complex, turbulent), `random[:SEED]`, `random_partitions[:SEED]`,
    or file path."""
    if not isinstance(name_or_path, str) or not name_or_path:
        raise WorldError("world must be a non-empty string: a built-in name or a file path")
    kind, colon, seed_text = name_or_path.partition(":")
    if kind == VALIDATION:
        try:
            k = int(seed_text)
        except ValueError:
            k = -1
        if not 0 <= k < VALIDATION_MAX:
            raise WorldError(f"world '{name_or_path}': a validation world is '{VALIDATION}:K' with K in 0..{VALIDATION_MAX - 1}")
        return validation_world(k)
    if kind in ("random", PARTITIONS):
        if colon:
            try:
                seed = int(seed_text)
            except ValueError:
                raise WorldError(f"world '{name_or_path}': the seed after '{kind}:' must be an integer") from None
        return procedural_world(seed, partitions=kind == PARTITIONS)
    if name_or_path in BUILTIN_WORLDS:
        path = worlds_dir() / f"{name_or_path}.yaml"
    else:
        path = Path(os.path.expanduser(name_or_path))
        if not path.suffix and os.sep not in name_or_path:
            raise WorldError(
                f"unknown world '{name_or_path}': expected one of {', '.join(BUILTIN_WORLDS)}, "
                "'random[:SEED]', 'random_partitions[:SEED]', 'validation:K', or a path to a .yaml world file"
            )
    try:
        text = path.read_text()
    except OSError as e:
        raise WorldError(f"cannot read world file '{path}': {e.strerror}") from None
    try:
        doc = yaml.safe_load(text)
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        raise WorldError(f"world file '{path}' is not valid YAML: {e}") from None
    if node is not None:
        _check_keys(node, str(path))
    return _parse(doc, str(path), _depth)


def procedural_world(seed: int, n_obstacles: int | None = None, partitions: bool = False) -> World:
    """A seeded random room with boxes and cylinders, keeping the start area clear.

    With `partitions` (world `random_partitions:SEED`, a held-out layout family), half of the boxes
    are partitions instead: 2-3 m long and 0.3-0.8 m thick, as the long boxes of Basic and Complex,
    which plain layouts (boxes up to 1.5 m) lack. Plain layouts are unchanged by the option."""
    rng = np.random.default_rng(seed)
    length = float(rng.uniform(12.0, 20.0))
    width = float(rng.uniform(10.0, 16.0))
    start = (-length / 2 + 2.0, float(rng.uniform(-width / 4, width / 4)), 1.0)
    count = int(rng.integers(6, 14)) if n_obstacles is None else n_obstacles
    obstacles = []
    tries = 0
    while len(obstacles) < count and tries < 500:
        tries += 1
        x = float(rng.uniform(-length / 2 + 1.0, length / 2 - 1.0))
        y = float(rng.uniform(-width / 2 + 1.0, width / 2 - 1.0))
        if math.hypot(x - start[0], y - start[1]) < 2.5:
            continue
        if any(math.hypot(x - o.x_m, y - o.y_m) < 2.0 for o in obstacles):
            continue
        if rng.random() < 0.5:
            obstacles.append(Obstacle("cylinder", x, y, 3.0, radius_m=float(rng.uniform(0.15, 0.5))))
        elif partitions and rng.random() < 0.5:
            size = (float(rng.uniform(2.0, 3.0)), float(rng.uniform(0.3, 0.8)))
            yaw = float(rng.uniform(0, 180))
            if math.hypot(x - start[0], y - start[1]) < 2.5 + size[0] / 2:  # the long side must not reach the start
                continue
            obstacles.append(Obstacle("box", x, y, 3.0, size_x_m=size[0], size_y_m=size[1], yaw_deg=yaw))
        else:
            obstacles.append(
                Obstacle(
                    "box",
                    x,
                    y,
                    3.0,
                    size_x_m=float(rng.uniform(0.3, 1.5)),
                    size_y_m=float(rng.uniform(0.3, 1.5)),
                    yaw_deg=float(rng.uniform(0, 90)),
                )
            )
    name = f"{PARTITIONS}:{seed}" if partitions else f"random:{seed}"
    return World(name, length, width, 3.0, start, 0.0, tuple(obstacles), Weather())


def validation_world(k: int) -> World:
    """Validation world K: from layout seed VALIDATION_SEEDS_FROM + K, of family VALIDATION_FAMILIES[K % 4]."""
    seed = VALIDATION_SEEDS_FROM + k
    family = VALIDATION_FAMILIES[k % len(VALIDATION_FAMILIES)]
    if family == "doorways":
        w = doorway_world(seed)
    else:
        w = procedural_world(seed, partitions=family == "partitions")
    if family == "weather":
        rng = np.random.default_rng([seed, 1])  # its own stream: the layout is random:SEED's
        w = dataclasses.replace(
            w, weather=Weather(int(rng.integers(20, 51)), int(rng.integers(20, 51)), int(rng.integers(10, 31)))
        )
    return dataclasses.replace(w, name=f"{VALIDATION}:{k}")


def doorway_world(seed: int) -> World:
    """A seeded room crossed by one or two walls, each with a doorway 1.4-2.0 m wide, and a few pillars
    between them: a structure the training layouts (free-standing boxes and cylinders) never show."""
    rng = np.random.default_rng([seed, 2])
    length = float(rng.uniform(14.0, 20.0))
    width = float(rng.uniform(8.0, 12.0))
    start = (-length / 2 + 2.0, float(rng.uniform(-width / 4, width / 4)), 1.0)
    walls = 2 if length >= 16.0 else 1
    first, last = start[0] + 3.5, length / 2 - 2.5
    xs = [first + (last - first) * (i + 0.5) / walls for i in range(walls)]
    obstacles, doors = [], []
    for x in xs:
        gap = float(rng.uniform(1.4, 2.0))
        gy = float(rng.uniform(-width / 2 + 1.0 + gap / 2, width / 2 - 1.0 - gap / 2))
        doors.append((x, gy))
        for lo, hi in ((-width / 2, gy - gap / 2), (gy + gap / 2, width / 2)):
            obstacles.append(Obstacle("box", x, (lo + hi) / 2, 3.0, size_x_m=0.2, size_y_m=hi - lo))
    pillars, tries = int(rng.integers(2, 5)), 0
    while pillars and tries < 200:
        tries += 1
        x = float(rng.uniform(start[0] + 2.5, length / 2 - 1.0))
        y = float(rng.uniform(-width / 2 + 1.0, width / 2 - 1.0))
        clear = all(abs(x - wx) > 1.0 for wx in xs) and all(math.hypot(x - dx, y - dy) > 2.0 for dx, dy in doors)
        if clear and math.hypot(x - start[0], y - start[1]) >= 2.5:
            obstacles.append(Obstacle("cylinder", x, y, 3.0, radius_m=float(rng.uniform(0.15, 0.4))))
            pillars -= 1
    return World(f"doorways:{seed}", length, width, 3.0, start, 0.0, tuple(obstacles), Weather())


LAYOUT_FAMILIES = ("plain", "mixed")  # the training stream's layouts: plain, or plain, partitions and doorways in turn


def training_layout(s: int, families: str = "plain") -> World:
    """Training layout seed `s` (>= TRAINING_LAYOUTS_FROM): a plain procedural layout, or with families 'mixed' by
    s % 3 a plain one, one with partitions among the boxes, or a room crossed by walls with doorways."""
    if s < TRAINING_LAYOUTS_FROM:
        raise ValueError(f"training layout seeds start at {TRAINING_LAYOUTS_FROM} (below: validation and tests), got {s}")
    if families == "plain" or s % 3 == 0:
        return procedural_world(s)
    if families != "mixed":
        raise ValueError(f"layout families {families!r} are invalid: expected one of {', '.join(LAYOUT_FAMILIES)}")
    return procedural_world(s, partitions=True) if s % 3 == 1 else doorway_world(s)


def training_layouts(seed: int, world: World | None = None, world_every: int = 0, families: str = "plain") -> Iterator[World]:
    """The procedural layouts a run with this seed trains on, one per episode:
    random:1000+100000*seed, then +1, ... so that the held-out random:0..999 never appear (`families` 'mixed':
    partitions and doorways among them, from the same seeds).

    With `world` and `world_every` = K >= 2, every K-th episode flies `world` instead (an extension:
    e.g. the paper's training room Basic between the layouts); the layouts keep their order."""
    start = TRAINING_LAYOUTS_FROM + 100_000 * seed
    layouts = (training_layout(s, families) for s in itertools.count(start))
    if not world_every:
        return layouts
    if world is None or world_every < 2:
        raise ValueError(f"world_every must be 0 (layouts only) or >= 2 with a world, got {world_every}")
    return (world if i % world_every == 0 else next(layouts) for i in itertools.count(1))


@dataclasses.dataclass(frozen=True)
class WorldChoice:
    """Which world a run flies: sim_node's parameters, and the in-process tools' from a recipe."""

    world: str = setting(
        "basic",
        f"World: basic, complex, turbulent, random[:SEED], random_partitions[:SEED], validation:K, a path to a world "
        ".yaml file, or "
        f"{EACH_EPISODE} (training: a new seeded procedural layout every episode, random:1000+100000*seed onward)",
    )
    mix_world: str = setting("basic", f"world:={EACH_EPISODE} with mix_world_every: the world flown between the layouts")
    mix_world_every: int = setting(
        0,
        f"world:={EACH_EPISODE} only: every K-th episode (K >= 2) flies mix_world instead of a new layout; 0 = layouts only",
        0,
        10**6,
    )
    layout_families: str = setting(
        "plain",
        f"world:={EACH_EPISODE}: plain procedural layouts, or mixed (plain, partitions among the boxes, walls with "
        "doorways in turn; seeds disjoint from validation and tests)",
        choices=LAYOUT_FAMILIES,
    )

    def load(self, seed: int) -> tuple[World, Iterator[World] | None]:
        """(the first world, the worlds of the episodes after it or None for one fixed world). Raises
        WorldError naming the setting that cannot be used."""
        if self.mix_world_every and (self.mix_world_every < 2 or self.world != EACH_EPISODE):
            raise WorldError(f"'mix_world_every' ({self.mix_world_every}): must be 0, or >= 2 with world:={EACH_EPISODE}")
        if self.world != EACH_EPISODE:
            try:
                return load_world(self.world, seed=seed), None
            except WorldError as e:
                raise WorldError(f"'world': {e}") from None
        try:
            mix = load_world(self.mix_world, seed=seed) if self.mix_world_every else None
        except WorldError as e:
            raise WorldError(f"'mix_world': {e}") from None
        layouts = training_layouts(seed, mix, self.mix_world_every, self.layout_families)
        return next(layouts), layouts
