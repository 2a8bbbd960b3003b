"""The simulator core: world, vehicle, camera, weather, collisions and the reward. No ROS.

One `step(cmd)` applies a body-frame velocity command for `step_duration_s`, integrated at
`physics_rate_hz`, checks collisions after every sub-step, renders the new depth frame and
returns everything a trainer needs. A collision ends the episode: the vehicle returns to
its start pose and the returned frame is the first of the next episode.

Collisions: after each sub-step pybullet's contact points between the vehicle's box and the
world are read; a contact whose penetration depth exceeds `collision_penetration_m` is a
collision. Shallower contacts are *brushes* (the paper ignores minor brushes): they are
counted in `StepResult.brushes` and do not end the episode.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import pybullet as p

from uav_common.kinematics import HOVER, BodyTwist, Pose, TwistLimits, integrate, twist_error
from uav_common.local_map import CAMERA_FORWARD_M
from uav_common.settings import setting

from .camera import CameraIntrinsics, DepthCamera
from .reward import DELTA_M, center_window_min_depth, floor_beta_m, step_reward
from .sensor import SENSORS, SensorModel, preset, scaled_size
from .weather import Particles
from .world import Obstacle, World, wall_code


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """The simulator's settings (sim_node's parameters; the in-process tools take them from a recipe)."""

    sensor: str = setting(
        "ideal",
        "Depth sensor: ideal (exact depth; the paper's protocol) or a preset camera with its own resolution, field of "
        "view, range, noise, dropout and edge holes (docs/REAL_CAMERA.md); a preset replaces image_width, image_height "
        "and hfov_deg. sim_node's default is the camera the packaged policy was trained behind",
        choices=SENSORS,
    )
    sensor_scale: float = setting(
        1.0, "A preset sensor renders at this share of its resolution (e.g. 0.25 for training speed)", 0.05, 1.0
    )
    image_width: int = setting(64, "Depth image width (px); sensor ideal only", 8, 1024)
    image_height: int = setting(64, "Depth image height (px); sensor ideal only", 8, 1024)
    hfov_deg: float = setting(
        150.0,
        "Horizontal field of view (deg; sensor ideal only); the wide150 recipe's is 150, the paper's camera 90",
        10.0,
        170.0,
    )
    min_range_m: float = setting(0.1, "Closest measurable depth (m); also the near clip plane", 0.01, 10.0)
    max_range_m: float = setting(10.0, "Farthest measurable depth (m); beyond it pixels are +Inf", 0.5, 100.0)
    step_duration_s: float = setting(0.5, "Sim time one step (one command) lasts (s)", 0.01, 5.0)
    physics_rate_hz: float = setting(40.0, "Sub-step rate for motion and collision checks (Hz)", 1.0, 1000.0)
    collision_penetration_m: float = setting(
        0.03, "Contacts deeper than this are collisions; shallower ones are brushes (m)", 0.0, 0.2
    )
    start_yaw_jitter_deg: float = setting(0.0, "Uniform random yaw added to the start pose (deg)", 0.0, 180.0)
    max_episode_steps: int = setting(
        0,
        "Training: an episode that survives this many steps ends (a time limit, not a crash; step_outcome NaN) and the "
        "next starts; 0 = episodes end only in collisions",
        0,
        10**9,
    )
    reward_window_fraction: float = setting(
        0.078,
        "The reward's central window (beta: its nearest depth), as a share of each image side: the paper's 0.2 (sim_node's "
        "default); 0.078 (5 x 5 px) for the wide150 recipe: wider than 120 deg the floor enters it unless smaller (a "
        "warning says so)",
        0.01,
        1.0,
    )
    seed: int = setting(0, "Seed for weather, start jitter and 'random' worlds", 0, 2**31 - 1)
    limits: TwistLimits = TwistLimits()
    body_half_extents_m: tuple[float, float, float] = (0.2, 0.2, 0.06)
    camera_forward_offset_m: float = CAMERA_FORWARD_M

    def validate(self) -> None:
        """Raise ValueError naming the first field that cannot be used."""
        preset(self.sensor)  # ValueError naming the presets
        checks = [
            ("sensor_scale", 0.05 <= self.sensor_scale <= 1.0, "in [0.05, 1]"),
            ("image_width", 8 <= self.image_width <= 1024, "an integer in [8, 1024]"),
            ("image_height", 8 <= self.image_height <= 1024, "an integer in [8, 1024]"),
            ("hfov_deg", 10.0 <= self.hfov_deg <= 170.0, "in [10, 170] degrees"),
            ("min_range_m", 0.01 <= self.min_range_m < self.max_range_m, "in [0.01, max_range_m)"),
            ("max_range_m", 0.5 <= self.max_range_m <= 100.0, "in [0.5, 100] m"),
            ("step_duration_s", 0.01 <= self.step_duration_s <= 5.0, "in [0.01, 5] s"),
            ("physics_rate_hz", 1.0 <= self.physics_rate_hz <= 1000.0, "in [1, 1000] Hz"),
            ("collision_penetration_m", 0.0 <= self.collision_penetration_m <= 0.2, "in [0, 0.2] m"),
            ("start_yaw_jitter_deg", 0.0 <= self.start_yaw_jitter_deg <= 180.0, "in [0, 180] degrees"),
            ("max_episode_steps", self.max_episode_steps >= 0, "an integer >= 0 (0 = no time limit)"),
            ("reward_window_fraction", 0.0 < self.reward_window_fraction <= 1.0, "in (0, 1]"),
        ]
        for name, ok, valid in checks:
            if not ok:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid: expected {valid}")


def with_sensor(config: SimConfig) -> SimConfig:
    """`config` with the camera geometry of its sensor preset (at sensor_scale); ideal: unchanged."""
    p_ = preset(config.sensor)
    if p_ is None:
        return config
    width, height = scaled_size(p_, config.sensor_scale)
    return dataclasses.replace(config, image_width=width, image_height=height, hfov_deg=p_.hfov_deg)


@dataclasses.dataclass
class StepResult:
    depth_m: np.ndarray  # (H, W) float32, REP 117 (+Inf beyond range), as the sensor measures it
    beta_m: float  # centre-window minimum depth of depth_m (capped at max range)
    collided: bool  # the step ended in a collision; depth_m is then the new episode's first frame
    reward: float
    brushes: int  # sub-steps with a contact shallower than the collision threshold
    episode: int
    step_in_episode: int
    sim_time_s: float
    pose: Pose
    # The episode ended without a collision (time limit or reset): depth_m is the new episode's
    # first frame and the step's own outcome is not reported (no transition should be learnt from it).
    truncated: bool = False


def obstacle_distance_m(o: Obstacle, x: float, y: float) -> float:
    """Horizontal distance from (x, y) to the obstacle's footprint (0 inside it)."""
    dx, dy = x - o.x_m, y - o.y_m
    if o.shape != "box":
        return max(0.0, math.hypot(dx, dy) - o.radius_m)
    yaw = math.radians(o.yaw_deg)
    u = abs(dx * math.cos(yaw) + dy * math.sin(yaw)) - o.size_x_m / 2  # in the box's own frame
    v = abs(-dx * math.sin(yaw) + dy * math.cos(yaw)) - o.size_y_m / 2
    return math.hypot(max(u, 0.0), max(v, 0.0))


class RewardWindowError(ValueError):
    """The camera cannot train with the paper's reward (see reward_floor_problem)."""


def reward_floor_problem(config: SimConfig, camera_height_m: float) -> str | None:
    """Why the paper's reward cannot work with this camera, or None: a wide square image puts the
    floor inside the reward's central window nearer than delta, so every step is punished even in
    an empty room and training learns to end episodes by crashing (docs/WORLDS.md)."""
    b = floor_beta_m(camera_height_m, config.image_height, config.image_width, config.hfov_deg, config.reward_window_fraction)
    if b > DELTA_M:
        return None
    return (
        f"hfov_deg={config.hfov_deg:g} with {config.image_width}x{config.image_height} images shows the floor "
        f"{b:.2f} m ahead inside the reward's central window, under delta = {DELTA_M:g} m: every step's reward "
        f"is negative even in an empty room, so training learns to crash early; use a narrower camera or a "
        f"smaller reward_window_fraction (now {config.reward_window_fraction:g})"
    )


class Simulator:
    """A quadrotor with a depth camera in a world; several can share one process."""

    def __init__(
        self,
        world: World,
        config: SimConfig = SimConfig(),
        next_worlds: Iterator[World] | None = None,
    ):
        """With `next_worlds`, every new episode (after a collision or reset) flies the next world
        from it, starting at the run's first heading draw (see change_world)."""
        config.validate()
        config = with_sensor(config)
        self.world = world
        self.config = config
        p_ = preset(config.sensor)
        self.sensor = SensorModel(p_, config.seed + 2) if p_ is not None else None
        self.next_worlds = next_worlds
        self.see_bodies = False  # render the segmentation mask too (the planner and the decision's reason need it)
        self.body_ids: np.ndarray | None = None
        self.measured: np.ndarray | None = None
        self.visible: frozenset[int] = frozenset()
        self.rng = np.random.default_rng(config.seed)
        self.client = p.connect(p.DIRECT)
        self.camera = DepthCamera(
            self.client,
            CameraIntrinsics(config.image_width, config.image_height, config.hfov_deg),
            config.min_range_m,
            config.max_range_m,
        )
        self._populate()
        self.sim_time_s = 0.0
        self.episode = 0
        self.step_in_episode = 0
        self.total_steps = 0
        self.collisions = 0
        self.pose = self._start_pose()
        self._place()
        self.particles.update(0.0, self.camera_xyz(), self.pose.yaw_rad)

    # -- world ------------------------------------------------------------------------
    def _populate(self) -> None:
        """Build self.world, the vehicle body and the weather particles in the (empty) client."""
        p.setGravity(0, 0, 0, physicsClientId=self.client)
        self._build_world()
        hx, hy, hz = self.config.body_half_extents_m
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=(hx, hy, hz), physicsClientId=self.client)
        # Mass > 0 so that contacts with the static world are generated; it is moved kinematically.
        self.body = p.createMultiBody(1.0, shape, -1, (0, 0, 1), physicsClientId=self.client)
        self.particles = Particles(self.client, self.world.weather, self.config.seed + 1)

    def _static_box(self, center, half, yaw_rad=0.0) -> int:
        c = self.client
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c)
        orn = p.getQuaternionFromEuler((0, 0, yaw_rad))
        return p.createMultiBody(0, col, vis, center, orn, physicsClientId=c)

    def _build_world(self) -> None:
        w, c, t = self.world, self.client, 0.1
        L, W, H = w.length_m, w.width_m, w.wall_height_m
        self._static_box((0, 0, -t), (L / 2 + t, W / 2 + t, t))  # floor
        # What each body is, for the pixels that show it (body_ids): the walls in world.WALLS's order, the obstacles.
        codes = {
            self._static_box((L / 2 + t, 0, H / 2), (t, W / 2 + 2 * t, H / 2)): wall_code(0),
            self._static_box((-L / 2 - t, 0, H / 2), (t, W / 2 + 2 * t, H / 2)): wall_code(1),
            self._static_box((0, W / 2 + t, H / 2), (L / 2 + 2 * t, t, H / 2)): wall_code(2),
            self._static_box((0, -W / 2 - t, H / 2), (L / 2 + 2 * t, t, H / 2)): wall_code(3),
        }
        for i, o in enumerate(w.obstacles):
            if o.shape == "box":
                half = (o.size_x_m / 2, o.size_y_m / 2, o.height_m / 2)
                body = self._static_box((o.x_m, o.y_m, o.height_m / 2), half, math.radians(o.yaw_deg))
            else:
                col = p.createCollisionShape(p.GEOM_CYLINDER, radius=o.radius_m, height=o.height_m, physicsClientId=c)
                vis = p.createVisualShape(p.GEOM_CYLINDER, radius=o.radius_m, length=o.height_m, physicsClientId=c)
                body = p.createMultiBody(0, col, vis, (o.x_m, o.y_m, o.height_m / 2), physicsClientId=c)
            codes[body] = i
        self._code_of_body = np.full(max(codes) + 1, -1, dtype=np.int64)  # body id -> code (-1: no obstacle or wall)
        self._code_of_body[list(codes)] = list(codes.values())

    def _start_pose(self) -> Pose:
        x, y, z = self.world.start_xyz_m
        yaw = math.radians(self.world.start_yaw_deg)
        if self.config.start_yaw_jitter_deg > 0:
            yaw += math.radians(self.rng.uniform(-1, 1) * self.config.start_yaw_jitter_deg)
        return Pose(x, y, z, yaw)

    def _place(self) -> None:
        orn = p.getQuaternionFromEuler((0, 0, self.pose.yaw_rad))
        pos = (self.pose.x_m, self.pose.y_m, self.pose.z_m)
        p.resetBasePositionAndOrientation(self.body, pos, orn, physicsClientId=self.client)

    def _max_penetration_m(self) -> float:
        p.performCollisionDetection(physicsClientId=self.client)
        contacts = p.getContactPoints(bodyA=self.body, physicsClientId=self.client)
        return max((-cp[8] for cp in contacts), default=0.0)

    def camera_xyz(self) -> tuple[float, float, float]:
        off = self.config.camera_forward_offset_m
        return (
            self.pose.x_m + off * math.cos(self.pose.yaw_rad),
            self.pose.y_m + off * math.sin(self.pose.yaw_rad),
            self.pose.z_m,
        )

    # -- public API -----------------------------------------------------------------------
    def render(self) -> np.ndarray:
        """The current depth frame (m), exact. With `see_bodies` set, `body_ids` is its mask of what each pixel shows
        (an obstacle's index, a wall's wall_code, -1 for the floor, particles or nothing in range) and `visible` the
        set of those codes."""
        if not self.see_bodies:
            return self.camera.render(self.camera_xyz(), self.pose.yaw_rad)
        depth, ids = self.camera.render_with_ids(self.camera_xyz(), self.pose.yaw_rad)
        known = (ids >= 0) & (ids < len(self._code_of_body))  # particles were made after the world: not in the table
        self.body_ids = np.where(known, self._code_of_body[np.where(known, ids, 0)], -1)
        self.visible = frozenset(int(c) for c in np.unique(self.body_ids) if c != -1)
        return depth

    def measure(self, depth_m: np.ndarray) -> np.ndarray:
        """What the sensor reports for the exact depth (the reward's beta comes from the exact one); kept as
        `measured`, the newest frame a camera would have given (the local map's input)."""
        self.measured = depth_m if self.sensor is None else self.sensor.measure(depth_m)
        return self.measured

    def observe(self) -> StepResult:
        """The current frame as a StepResult without moving (the first frame of a run)."""
        depth = self.render()
        beta = center_window_min_depth(depth, self.config.max_range_m, self.config.reward_window_fraction)
        return StepResult(
            self.measure(depth),
            beta,
            False,
            step_reward(beta, False),
            0,
            self.episode,
            self.step_in_episode,
            self.sim_time_s,
            dataclasses.replace(self.pose),
        )

    def reset(self) -> StepResult:
        """End the episode without a collision and return to the start pose (of the next world, with
        next_worlds); the result is marked `truncated`."""
        self._new_episode()
        return dataclasses.replace(self.observe(), truncated=True)

    def _new_episode(self) -> None:
        self.episode += 1
        self.step_in_episode = 0
        # With next_worlds, _enter draws the pose for the new world (this draw only keeps the
        # heading sequence as it always was).
        self.pose = self._start_pose()
        self._place()
        self._next_world()

    def change_world(self, world: World, redraw_heading: bool = True) -> StepResult:
        """Move to another world: the current episode restarts at its start pose; counters and clock
        carry on. With `redraw_heading` the start-heading jitter is the seeded sequence's next draw;
        without it the sequence restarts, so every world starts at the run's first draw (as if a new
        Simulator had been made: how the shipped weights were trained)."""
        self._enter(world, redraw_heading)
        return self.observe()

    def _next_world(self) -> None:
        if self.next_worlds is not None:
            self._enter(next(self.next_worlds), redraw_heading=False)

    def _enter(self, world: World, redraw_heading: bool) -> None:
        if not redraw_heading:
            self.rng = np.random.default_rng(self.config.seed)
        p.resetSimulation(physicsClientId=self.client)
        self.world = world
        self._populate()
        self.step_in_episode = 0
        self.pose = self._start_pose()
        self._place()
        self.particles.update(0.0, self.camera_xyz(), self.pose.yaw_rad)

    def step(self, cmd: BodyTwist = HOVER) -> StepResult:
        """Fly `cmd` for one step; raises ValueError for a command outside the limits."""
        err = twist_error(cmd, self.config.limits)
        if err:
            raise ValueError(err)
        cfg = self.config
        n_sub = max(1, int(math.ceil(cfg.step_duration_s * cfg.physics_rate_hz)))
        dt = cfg.step_duration_s / n_sub
        collided, brushes = False, 0
        z_max = self.world.wall_height_m - 0.3
        for _ in range(n_sub):
            self.pose = integrate(self.pose, cmd, dt)
            self.pose.z_m = min(self.pose.z_m, z_max)  # geofence: no escaping over the walls
            self._place()
            pen = self._max_penetration_m()
            if pen > cfg.collision_penetration_m:
                collided = True
                break
            if pen > 0.0:
                brushes += 1
        self.sim_time_s += cfg.step_duration_s
        self.total_steps += 1
        truncated = False
        if collided:
            self.collisions += 1
            self._new_episode()  # the crash's outcome is reported from the next episode's first frame
        else:
            self.step_in_episode += 1
            if 0 < cfg.max_episode_steps <= self.step_in_episode:
                truncated = True
                self._new_episode()
        self.particles.update(cfg.step_duration_s, self.camera_xyz(), self.pose.yaw_rad)
        depth = self.render()
        beta = center_window_min_depth(depth, cfg.max_range_m, cfg.reward_window_fraction)
        return StepResult(
            self.measure(depth),
            beta,
            collided,
            step_reward(beta, collided),
            brushes,
            self.episode,
            self.step_in_episode,
            self.sim_time_s,
            dataclasses.replace(self.pose),
            truncated,
        )

    def close(self) -> None:
        if self.client is not None and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = None
