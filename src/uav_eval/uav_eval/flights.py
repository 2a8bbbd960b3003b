"""Measuring flights: a policy flown exploit-only in process (`evaluate_inprocess`, through the one act -> step ->
stack loop), counted into an EvalResult: crashes, reward, distance, crash sites, turning steps and floor area
covered; and the weights and simulator arguments both this and the flight through the ROS nodes
(uav_eval.ros_flights) use."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from uav_policy.insight import Insight, InsightSummary, explanation
from uav_sim.reward import CENTER_WINDOW_FRACTION

from . import ENSEMBLE_SEP, PLANNER_WEIGHTS, PLANNERS
from .autopsy import FIELDS as AUTOPSY_FIELDS
from .autopsy import Autopsy


@dataclasses.dataclass
class EvalResult:
    model: str
    world: str
    weights: str
    steps: int
    crashes: int
    mean_reward: float
    distance_m: float
    crash_sites: int = -1  # distinct places (0.1 m grid) where a crashing step began, per run, summed; -1 unknown
    turn_steps: int = -1  # steps that changed the heading by more than TURN_DEG (-1 unknown)
    cells: int = -1  # distinct 1 m x 1 m floor cells flown through, per run, summed (-1 unknown)
    interventions: int = -1  # commands policy_node's safety layer changed (-1: flown without it)
    insight: InsightSummary | None = None  # what the decisions looked at, measured on every step (None: not measured)
    shield_overrides: int = -1  # decisions the shield changed (-1: flown without one)
    teacher_agreement: float = -1.0  # with a crash log: the share of steps flown the map teacher's way, ties counted

    @property
    def distance_between_crashes_m(self) -> float:
        return self.distance_m / self.crashes if self.crashes else math.inf


# One row per crash in crashes.csv (--crash-log): where the crashing step began (pose before it), how
# many steps the episode had flown, the heading the episode started at, and the action taken.
CRASH_FIELDS = (
    "model",
    "world",
    "weights",
    "sim_seed",
    "step",
    "episode_step",
    "x_m",
    "y_m",
    "yaw_deg",
    "start_yaw_deg",
    "action",
    *AUTOPSY_FIELDS,
)


def crash_site(xy) -> tuple[float, float]:
    """Where a crashing step began, on a 0.1 m grid: a deterministic policy restarted at the same
    pose crashes at the same site again, so crashes / sites tells repeats from new failures."""
    return (round(xy[0], 1), round(xy[1], 1))


TURN_DEG = 15.0  # the paper's turning actions yaw 30 degrees per step, the straight ones 0


class Behaviour:
    """How a policy flies, beside how often it crashes: the share of steps spent turning, and how
    much of the room it covers (distinct 1 m cells). A policy that circles on the spot can crash
    rarely while covering almost nothing; these numbers make that visible."""

    def __init__(self, x: float, y: float, yaw_rad: float):
        self.turn_steps = 0
        self.cells = {(math.floor(x), math.floor(y))}
        self.yaw = yaw_rad

    def step(self, x: float, y: float, yaw_rad: float, collided: bool) -> None:
        """After every step; after a collision the pose is the next episode's start."""
        if not collided:
            turn = (yaw_rad - self.yaw + math.pi) % (2 * math.pi) - math.pi
            self.turn_steps += abs(math.degrees(turn)) > TURN_DEG
        self.cells.add((math.floor(x), math.floor(y)))
        self.yaw = yaw_rad


def architecture_args(model: str, weights: str) -> list[str]:
    """policy_node parameters for a weights file whose input size or frame stack is not the default."""
    from uav_policy import weights as wio
    from uav_policy.networks import NetConfig

    cfg = wio.config_for(model, weights)
    args = []
    if (cfg.height, cfg.width) != (NetConfig.height, NetConfig.width):
        args += [f"input_height:={cfg.height}", f"input_width:={cfg.width}"]
    if cfg.frames != NetConfig.frames:
        args.append(f"frame_stack:={cfg.frames}")
    return args


def image_size_args(model: str, weights: str, sim_args) -> list[str]:
    """sim_node parameters that render at the input size of `weights`, unless `sim_args` set a size."""
    from uav_policy import weights as wio

    if not weights or any(a.partition(":=")[0] in ("image_width", "image_height") for a in sim_args):
        return []
    cfg = wio.config_for(model, weights)
    return [f"image_width:={cfg.width}", f"image_height:={cfg.height}"]


def weights_or_packaged(model: str, weights: str) -> list[str]:
    """The files a policy flies: `weights` (one file, or an ensemble's joined by ENSEMBLE_SEP), or
    without them the packaged files policy_node loads by default ([] when there are none)."""
    from uav_policy import weights as wio

    return weights.split(ENSEMBLE_SEP) if weights else [str(p) for p in wio.packaged_weights(model)]


def flown_hfov_deg(model: str, weights: str) -> float:
    """The camera field of view weights fly with when no hfov_deg is given: the one the weights file (or,
    without one, the packaged files policy_node loads) was trained with, else SimConfig's default."""
    from uav_policy import weights as wio

    return wio.camera_for(next(iter(weights_or_packaged(model, weights)), None), wio.UNRECORDED_HFOV_DEG)


def flown_window(model: str, weights: str) -> float:
    """The reward window weights are measured with when none is given: the one the weights file (or the
    packaged files) records, else the paper's (SimConfig's default, which sim_node's need not be)."""
    from uav_policy import weights as wio

    return wio.window_for(next(iter(weights_or_packaged(model, weights)), None), CENTER_WINDOW_FRACTION)


def sim_arg_number(sim_args, wanted: str) -> float | None:
    """The value of `wanted` among sim_node arguments NAME:=VALUE, if one is given (ValueError if not a number)."""
    for arg in sim_args:
        name, _, value = arg.partition(":=")
        if name == wanted:
            try:
                return float(value)
            except ValueError:
                raise ValueError(f"sim_node argument {arg!r}: {wanted} must be a number") from None
    return None


def sim_arg_hfov_deg(sim_args) -> float | None:
    """The hfov_deg among sim_node arguments NAME:=VALUE, if one is given (ValueError if not a number)."""
    return sim_arg_number(sim_args, "hfov_deg")


def weights_label(files: list[str], model: str = "sam") -> str:
    """How progress lines name a policy: its file, "packaged", or an ensemble's size, first and last file
    (the weights column of results.csv keeps every file); a planner flies none."""
    if model in PLANNERS:
        return "no weights"
    if len(files) > 1:
        return f"ensemble of {len(files)} ({files[0]} ... {files[-1]})"
    return files[0] if files else "packaged"


# The sim_node parameters --inprocess honours.
INPROCESS_SIM_ARGS = ("hfov_deg", "reward_window_fraction", "sensor", "sensor_scale")


@dataclasses.dataclass(frozen=True)
class FlightSpec:
    """One measured flight, resolved once: what flies, where, how long and how; `evaluate_inprocess` and
    `uav_eval.ros_flights.evaluate_once` both take it.

    `weights`: a file, or an ensemble's files joined by ENSEMBLE_SEP, or "" for the packaged files (a model of PLANNERS
    flies uav_sim.planner and no weights). In process: `hfov_deg` None flies the camera the weights were trained with,
    `reward_window_fraction` None the window the weights record (else the paper's); a `sensor` preset renders its own
    camera (at `sensor_scale`), mapped onto the weights' field of view as policy_node maps a camera through CameraInfo
    (None: the preset of the weights' camera at the recipes' scale, else the ideal camera); over ROS `sim_args` carry
    sim_node's parameters and `epsilon` the policy's exploration. What the decisions look at is measured on every
    `insight_every`-th step (0: never). `safety`: the commands pass policy_node's safety layer (its interventions
    counted); `shield`: the network chooses among the actions the local map says are safe (its overrides counted).
    `max_crashes` N > 0 ends an in-process flight at its N-th crash (the result's steps are those flown)."""

    model: str
    weights: str = ""
    world: str = "basic"
    steps: int = 1000
    seed: int = 0
    start_yaw_jitter_deg: float = 0.0
    insight_every: int = 1
    safety: bool = False
    shield: bool = False
    hfov_deg: float | None = None
    reward_window_fraction: float | None = None
    sensor: str | None = None
    sensor_scale: float | None = None
    max_crashes: int = 0
    sim_args: tuple[str, ...] = ()
    epsilon: float = 0.0


def evaluate_inprocess(spec: FlightSpec, net=None, net_cfg=None, crash_log: list | None = None) -> EvalResult:
    """The same measurement without ROS (same simulator, stack and network): for benchmarks and checks. `net`: a
    network to fly in place of the spec's weights (`net_cfg` its architecture; default: the weights file's, else the
    model's default; the camera renders at its input size). `crash_log`, when a list, gets one dict per crash
    (CRASH_FIELDS; for a network with uav_eval.autopsy's: the map teacher's last disagreement, what was hit and whether
    it had been seen)."""
    from uav_policy.rollout import Flight

    if spec.model in PLANNERS:
        spec = dataclasses.replace(spec, weights=spec.weights or PLANNER_WEIGHTS)
        sim, env, agent, layer = planner_flight(spec)
    else:
        sim, env, agent, layer, net = network_flight(spec, net, net_cfg)
    guard = None
    if spec.shield:
        from uav_policy.shield import Shield

        guard = Shield(env.actions, sim.config.step_duration_s)
    flight = Flight(env, agent, safety=layer, shield=guard)
    r = flight.last
    crashes, reward, dist, sites, steps = 0, 0.0, 0.0, set(), spec.steps
    behaviour = Behaviour(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad)
    start_yaw = r.pose.yaw_rad  # the episode's start heading
    # What the decisions look at, for the stack's networks (a stand-in network without a grid is not measured).
    every = spec.insight_every
    insight = Insight(net.grid_hw, seed=spec.seed) if net is not None and hasattr(net, "grid_hw") and every > 0 else None
    if insight is not None:
        from uav_sim.planner import SimPlanner

        reasons = SimPlanner(sim)  # what each measured decision is about
    autopsy = Autopsy(sim) if crash_log is not None and spec.model not in PLANNERS else None
    try:
        for step in range(1, steps + 1):
            episode_step = sim.step_in_episode + 1  # the simulator's count, before it restarts on a crash
            state = flight.env.state  # a new array every step: the step below leaves it as it is
            measured = insight is not None and step % every == 0
            reason = reason_pixels(reasons, env) if measured else None
            if autopsy is not None:
                autopsy.before()
            s = flight.step(0.0)
            if autopsy is not None:
                autopsy.after(step, s.action)
            if measured:
                insight.observe(net, state, s.action, explanation(net, state, s.action, s.attention), reason)
            before, r = s.before.pose, s.after
            reward += r.reward
            if r.collided:
                crashes += 1
                sites.add(crash_site((before.x_m, before.y_m)))
                if crash_log is not None:
                    action = flight.actions[s.action]
                    row = crash_row(spec, step, episode_step, before, start_yaw, action.name)
                    crash_log.append(row | (autopsy.crash(step, before, action) if autopsy else {}))
                start_yaw = r.pose.yaw_rad
            else:
                dist += math.hypot(r.pose.x_m - before.x_m, r.pose.y_m - before.y_m)
            behaviour.step(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad, r.collided)
            if spec.max_crashes and crashes >= spec.max_crashes:
                steps = step
                break
    finally:
        sim.close()
    return EvalResult(
        spec.model,
        spec.world,
        spec.weights,
        steps,
        crashes,
        reward / steps,
        dist,
        len(sites),
        behaviour.turn_steps,
        len(behaviour.cells),
        layer.counts.total if layer is not None else -1,
        insight=insight.summary() if insight is not None else None,
        shield_overrides=guard.counts.overridden if guard is not None else -1,
        teacher_agreement=autopsy.agreement if autopsy is not None else -1.0,
    )


def crash_row(spec: FlightSpec, step: int, episode_step: int, before, start_yaw: float, action: str) -> dict:
    """A crash's row of crashes.csv (CRASH_FIELDS, the autopsy's aside): where the crashing step began."""
    return dict(
        model=spec.model,
        world=spec.world,
        weights=spec.weights,
        sim_seed=spec.seed,
        step=step,
        episode_step=episode_step,
        x_m=round(before.x_m, 3),
        y_m=round(before.y_m, 3),
        yaw_deg=round(math.degrees(before.yaw_rad), 1),
        start_yaw_deg=round(math.degrees(start_yaw), 1),
        action=action,
    )


def network_flight(spec: FlightSpec, net=None, net_cfg=None):
    """evaluate_inprocess's simulator, stacked frames, agent, safety layer (or None) and network for a network: the
    spec's weights (or `net`), behind the camera and with the reward window they were trained with unless the spec
    says otherwise."""
    from uav_policy import weights as wio
    from uav_policy.agent import Agent
    from uav_policy.safety import SafetyLayer, SafetySettings
    from uav_sim.stacked_sim import StackedSim

    model, weights, hfov_deg, window = spec.model, spec.weights, spec.hfov_deg, spec.reward_window_fraction
    if net is None:
        files = weights_or_packaged(model, weights)
        if not files:
            raise FileNotFoundError(f"no weights given and no packaged {model} weights")
        net, net_cfg, hfov_deg, window = wio.load_policy(model, files, hfov_deg, window, CENTER_WINDOW_FRACTION)
    cfg = net_cfg if net_cfg is not None else wio.config_for(model, weights)
    if hfov_deg is None:  # `net` given without its camera: the weights file's, else the sim default
        hfov_deg = wio.camera_for(weights, wio.UNRECORDED_HFOV_DEG)
    if window is None:
        window = wio.window_for(weights, CENTER_WINDOW_FRACTION)
    sim = flight_simulator(spec, hfov_deg, window, hfov_deg=hfov_deg, image_width=cfg.width, image_height=cfg.height)
    layer = SafetyLayer(SafetySettings(), cfg.height, cfg.width, hfov_deg) if spec.safety else None
    env = StackedSim(sim, cfg.frames, input_hw=(cfg.height, cfg.width), trained_hfov_deg=hfov_deg, map_grid=cfg.map_grid)
    return sim, env, Agent(net, cfg, seed=spec.seed), layer, net


def flight_simulator(spec: FlightSpec, camera_hfov_deg: float, window: float, **image):
    """The simulator a flight flies: the spec's world, seed and headings, the reward `window`, and the spec's sensor
    preset, else the preset of a camera of `camera_hfov_deg` at the recipes' scale (uav_sim.sensor.preset_for_camera);
    `image`: SimConfig's camera fields (hfov_deg, image size)."""
    from uav_sim.sensor import TRAINING_SCALE, preset_for_camera
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.world import load_world

    sensor, scale = spec.sensor, spec.sensor_scale
    if sensor is None:
        sensor = preset_for_camera(camera_hfov_deg)
        scale = TRAINING_SCALE if sensor != "ideal" and scale is None else scale
    cfg = SimConfig(
        seed=spec.seed,
        start_yaw_jitter_deg=spec.start_yaw_jitter_deg,
        reward_window_fraction=window,
        sensor=sensor,
        sensor_scale=1.0 if scale is None else scale,
        **image,
    )
    return Simulator(load_world(spec.world), cfg)


def reason_pixels(reasons, env) -> np.ndarray | None:
    """The pixels of the newest frame, on the network's input, of what the planner's decision on it is about (its
    reason: uav_sim.planner), or None when nothing bounds that decision."""
    if not reasons.label().reason:
        return None
    return env.input_mask(reasons.reason_mask())


def planner_flight(spec: FlightSpec):
    """evaluate_inprocess's simulator, stacked frames and agent for the privileged planner: behind the camera the
    packaged networks were trained behind (sensor None), measured with their reward window."""
    from uav_policy.net_config import NetConfig
    from uav_sim.planner import PlannerAgent, PlannerConfig, SimPlanner
    from uav_sim.stacked_sim import StackedSim

    for flag, what in (("safety", "safety layer"), ("shield", "shield")):
        if getattr(spec, flag):
            raise ValueError(f"--{flag}: the {spec.model} flies no network, so there is no {what} to measure")
    window = flown_window("sam", "") if spec.reward_window_fraction is None else spec.reward_window_fraction
    sim = flight_simulator(spec, flown_hfov_deg("sam", ""), window)
    config = PlannerConfig(knowledge=PLANNERS[spec.model], memory_frames=NetConfig.frames)
    return sim, StackedSim(sim, NetConfig.frames), PlannerAgent(SimPlanner(sim, config)), None
