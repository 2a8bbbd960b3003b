"""Measuring flights: a policy flown exploit-only through the ROS nodes (`evaluate_once`) or in process
(`evaluate_inprocess`, through the one act -> step -> stack loop), counted into an EvalResult: crashes, reward,
distance, crash sites, turning steps and floor area covered."""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

from uav_common import contract
from uav_common.launching import Processes, params_args
from uav_policy.insight import Insight, InsightSummary, explanation
from uav_sim.reward import CENTER_WINDOW_FRACTION, step_reward


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


def quaternion_yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class StepMonitor:
    """Counts steps, crashes, reward and distance from step_outcome and odom (joined by stamp)."""

    def __init__(self, steps: int):
        self.target = steps
        self.joiner = contract.StampJoiner(("outcome", "odom"), max_pending=1000)
        self.first = True
        self.outcomes = 0  # step_outcome messages heard (a frame said again included)
        self.steps = self.crashes = 0
        self.sites: set[tuple[float, float]] = set()
        self.reward = 0.0
        self.distance = 0.0
        self.last_xy = None
        self.last_stamp = self.step_ns = None
        self.gaps = 0  # steps whose stamp is not one step after the previous one: messages were lost
        self.behaviour: Behaviour | None = None

    def add(self, stream: str, msg) -> None:
        self.outcomes += stream == "outcome"
        stamp = contract.stamp_ns(msg.header.stamp)
        j = self.joiner.add(stream, stamp, msg)
        if j is None or self.done:
            return
        p = j["odom"].pose.pose.position
        xy = (p.x, p.y)
        yaw = quaternion_yaw(j["odom"].pose.pose.orientation)
        if self.first:  # the frame before any command: not a step
            self.first, self.last_xy, self.last_stamp = False, xy, stamp
            self.behaviour = Behaviour(p.x, p.y, yaw)
            return
        delta = stamp - self.last_stamp
        self.step_ns = delta if self.step_ns is None else self.step_ns
        self.gaps += delta != self.step_ns
        self.last_stamp = stamp
        out = j["outcome"]
        collided, truncated = contract.outcome_collided(out), contract.outcome_truncated(out)
        if not truncated:  # a time limit's step has no outcome (evaluation sets none)
            beta = 0.0 if collided else min(max(float(out.range), 0.0), float(out.max_range))
            self.reward += step_reward(beta, collided)
        self.steps += 1
        if collided:
            self.crashes += 1  # the vehicle is back at the start: no distance for this jump
            self.sites.add(crash_site(self.last_xy))
        elif not truncated:
            self.distance += math.hypot(xy[0] - self.last_xy[0], xy[1] - self.last_xy[1])
        self.behaviour.step(p.x, p.y, yaw, collided or truncated)
        self.last_xy = xy

    @property
    def done(self) -> bool:
        return self.steps >= self.target


ENSEMBLE_SEP = "+"  # joins an ensemble's weights files in the weights column


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


def weights_label(files: list[str]) -> str:
    """How progress lines name a policy: its file, "packaged", or an ensemble's size, first and last file
    (the weights column of results.csv keeps every file)."""
    if len(files) > 1:
        return f"ensemble of {len(files)} ({files[0]} ... {files[-1]})"
    return files[0] if files else "packaged"


# The sim_node parameters --inprocess honours.
INPROCESS_SIM_ARGS = ("hfov_deg", "reward_window_fraction", "sensor", "sensor_scale")


def evaluate_once(
    model: str,
    weights: str,
    world: str,
    steps: int,
    epsilon: float = 0.0,
    seed: int = 0,
    params_dir: Path | None = None,
    timeout_s: float = 600.0,
    start_yaw_jitter_deg: float = 0.0,
    sim_args: tuple[str, ...] = (),
    log_dir: Path | None = None,
    progress=None,
    record_to: Path | None = None,
    safety: bool = False,
    insight_every: int = 1,
) -> EvalResult:
    """Run sim_node + policy_node (installed executables) and measure `steps` lockstep steps; with
    `record_to`, uav_bringup's `record` keeps the flight there as a bag, from its first frame. The policy
    flies without its safety layer (its own crashes), or with `safety` through it (interventions counted).

    Without hfov_deg in `sim_args` the simulator gets the camera the weights were trained with, without
    reward_window_fraction the reward window they record (else the paper's), and without image_width/image_height
    it renders at their input size. `weights` may be an ensemble's files joined by ENSEMBLE_SEP (which
    must share architecture, camera and reward window: load_policy checks): policy_node gets the list."""
    files = weights.split(ENSEMBLE_SEP) if weights else []
    first = files[0] if files else ""
    if sim_arg_hfov_deg(sim_args) is None:
        sim_args = (*sim_args, f"hfov_deg:={flown_hfov_deg(model, first)}")
    if sim_arg_number(sim_args, "reward_window_fraction") is None:
        sim_args = (*sim_args, f"reward_window_fraction:={flown_window(model, first)}")
    if not any(arg.startswith("sensor:=") for arg in sim_args):
        from uav_sim.sensor import sim_args_for_camera

        sim_args = (*sim_args, *sim_args_for_camera(flown_hfov_deg(model, first)))
    sim_args = (*sim_args, *image_size_args(model, first, sim_args))
    import rclpy
    import rclpy.executors
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, Range

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("evaluate_monitor", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    mon = StepMonitor(steps)
    deep = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10000)
    node.create_subscription(Range, contract.OUTCOME_TOPIC, lambda m: mon.add("outcome", m), deep)
    node.create_subscription(Odometry, contract.ODOM_TOPIC, lambda m: mon.add("odom", m), deep)
    said = {}  # the policy's latest /diagnostics values, and when they came
    node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: policy_said(said, m), 10)
    procs = Processes(log_dir=log_dir, quiet=log_dir is None)
    pargs = lambda kv: [x for item in kv for x in ("-p", item)]  # noqa: E731
    try:
        wargs = [f"weights:={','.join(files)}", *architecture_args(model, first)] if files else []
        policy_args = params_args(params_dir, "policy") + pargs(
            [
                f"model:={model}",
                f"epsilon:={epsilon}",
                f"seed:={seed}",
                "publish_overlay:=false",
                f"safety:={str(safety).lower()}",
                f"insight_every:={insight_every}",  # every k-th decision measured, over the whole flight
                f"insight_window:={2 * steps + 100}",
                *wargs,
            ]
        )
        ready_by = time.monotonic() + 60.0
        sim_extra = []
        written = {}  # the recorder's messages written, by topic
        if record_to is not None:
            # Recorder and policy first. The simulator starts once the recorder hears the policy's
            # publishers, and holds its first frame until the policy, the recorder and this monitor
            # all listen: the bag holds every step from the first frame on.
            from uav_bringup.record import recorder_publishers, wait_for_policy

            heard = recorder_publishers(node, written)
            node.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: None, deep)  # the third listener
            procs.start("record", "uav_bringup", "record", [], args=["-o", str(record_to), "--quiet"])
            procs.start("policy", "uav_policy", "policy_node", policy_args)
            wait_for_policy(heard, node, executor, procs.procs, ready_by - time.monotonic())
            sim_extra = ["wait_for_subscribers:=3"]
        # The lockstep sim only advances once the policy answers, and it says its first frame again
        # every lockstep_republish_s: without a recorder the policy starts once the monitor has that
        # frame, so no step can go by before the monitor hears the simulator.
        sim = procs.start(
            "sim",
            "uav_sim",
            "sim_node",
            params_args(params_dir, "sim")
            + pargs(
                [
                    f"world:={world}",
                    f"seed:={seed}",
                    f"start_yaw_jitter_deg:={float(start_yaw_jitter_deg)}",
                    f"step_budget:={steps}",  # exactly the steps measured: no frame after the last to answer
                    *sim_args,
                ]
                + sim_extra
            ),
        )
        while mon.first:
            executor.spin_once(timeout_sec=0.05)
            if sim.poll() is not None:
                raise RuntimeError(f"sim_node exited with code {sim.returncode} before its first frame")
            if time.monotonic() > ready_by:
                raise TimeoutError("no first frame from sim_node within 60 s")
        if record_to is None:
            procs.start("policy", "uav_policy", "policy_node", policy_args)
        end = time.monotonic() + timeout_s
        last = 0
        while not mon.done:
            executor.spin_once(timeout_sec=0.05)
            if progress and mon.steps != last:
                progress(mon.steps - last)
                last = mon.steps
            for name, p in procs.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name}_node exited with code {p.returncode} during evaluation")
            if time.monotonic() > end:
                raise TimeoutError(f"evaluation reached only {mon.steps}/{steps} steps in {timeout_s} s")
        if mon.gaps:
            raise RuntimeError(f"the monitor missed messages ({mon.gaps} steps out of sequence): the measurement is void")
        if record_to is not None:
            # A busy recorder may lag, or miss a message and get it again: the simulator lives on (holding
            # position and saying the last step's outcome again each lockstep_republish_s) until the bag holds every step.
            outcome, heard = node.resolve_topic_name(contract.OUTCOME_TOPIC), mon.outcomes
            asked = time.monotonic()
            while written.get(outcome, 0) < heard and time.monotonic() < asked + 60.0:
                executor.spin_once(timeout_sec=0.05)
            if written.get(outcome, 0) < heard:
                raise RuntimeError(
                    f"the recorder wrote {written.get(outcome, 0)} of the {heard} step outcomes within 60 s: "
                    f"the bag {record_to} is incomplete"
                )
        # The interventions and insight measured over the flight: the simulator stops first (no step more is
        # flown), then policy_node's next report (every second) is read.
        procs.stop("sim")
        asked = time.monotonic()
        while said.get("at", 0.0) <= asked and time.monotonic() < asked + 5.0:
            executor.spin_once(timeout_sec=0.05)
        if "safety_interventions" not in said:
            raise RuntimeError("policy_node did not report its safety interventions on /diagnostics")
    finally:
        procs.stop_all(["policy", "sim", "record"])
        executor.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    b = mon.behaviour
    return EvalResult(
        model,
        world,
        weights,
        mon.steps,
        mon.crashes,
        mon.reward / max(mon.steps, 1),
        mon.distance,
        len(mon.sites),
        b.turn_steps if b else -1,
        len(b.cells) if b else -1,
        int(said["safety_interventions"]) if safety else -1,
        InsightSummary.from_values(said),
    )


def policy_said(said: dict, msg) -> None:
    """Keep the values of policy_node's /diagnostics status, and when they came."""
    for st in msg.status:
        if st.name == "uav_policy":
            said.update({kv.key: kv.value for kv in st.values}, at=time.monotonic())


def bag_name(model: str, world: str, group: int, seed: int) -> str:
    """A flight's bag folder under evaluate --record: model, world (a file's stem), weights group, sim seed."""
    w = Path(world).stem if world.endswith((".yaml", ".yml")) else world.replace(":", "-")
    return f"{model}_{w}_w{group}_seed{seed}"


def evaluate_inprocess(
    model: str,
    weights: str,
    world: str,
    steps: int,
    seed: int = 0,
    net=None,
    start_yaw_jitter_deg: float = 0.0,
    hfov_deg: float | None = None,
    net_cfg=None,
    crash_log: list | None = None,
    reward_window_fraction: float | None = None,
    sensor: str | None = None,
    sensor_scale: float | None = None,
    insight_every: int = 1,
    safety: bool = False,
    max_crashes: int = 0,
) -> EvalResult:
    """The same measurement without ROS (same simulator, stack and network): for benchmarks and checks.

    `weights`: a file, or an ensemble's files joined by ENSEMBLE_SEP, or "" for the packaged files.
    hfov_deg None: the camera the weights were trained with (with `net` and no file: the sim default).
    `net_cfg`: `net`'s architecture (default: the weights file's, else the model's default); the
    camera renders at its input size. `crash_log`, when a list, gets one dict per crash (CRASH_FIELDS).
    `reward_window_fraction` None: the window the weights file records, else the paper's (SimConfig's default).
    A `sensor` preset renders its own camera (at `sensor_scale`), mapped onto the weights' field of view as
    policy_node maps a camera through CameraInfo; None: the preset of the weights' camera (uav_sim.sensor.
    preset_for_camera) at the recipes' scale, else the ideal camera. What the decisions look at is measured on every
    `insight_every`-th step (policy_node's parameter; 0 = never). With `safety` the commands pass policy_node's
    safety layer (its default settings), as `evaluate --safety` flies them through the node; its interventions
    are counted. `max_crashes` N > 0 ends the flight at its N-th crash (the result's steps are those flown)."""
    from uav_policy import weights as wio
    from uav_policy.agent import Agent
    from uav_policy.safety import SafetyLayer, SafetySettings
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.world import load_world

    from .rollout import Flight

    if net is None:
        files = weights_or_packaged(model, weights)
        if not files:
            raise FileNotFoundError(f"no weights given and no packaged {model} weights")
        net, net_cfg, hfov_deg, reward_window_fraction = load_policy(model, files, hfov_deg, reward_window_fraction)
    cfg = net_cfg if net_cfg is not None else wio.config_for(model, weights)
    if hfov_deg is None:  # `net` given without its camera: the weights file's, else the sim default
        hfov_deg = wio.camera_for(weights, wio.UNRECORDED_HFOV_DEG)
    if reward_window_fraction is None:
        reward_window_fraction = wio.window_for(weights, CENTER_WINDOW_FRACTION)
    if sensor is None:
        from uav_sim.sensor import TRAINING_SCALE, preset_for_camera

        sensor = preset_for_camera(hfov_deg)
        sensor_scale = TRAINING_SCALE if sensor != "ideal" and sensor_scale is None else sensor_scale
    sensor_scale = 1.0 if sensor_scale is None else sensor_scale
    agent = Agent(net, cfg, seed=seed)
    sim_cfg = SimConfig(
        seed=seed,
        start_yaw_jitter_deg=start_yaw_jitter_deg,
        hfov_deg=hfov_deg,
        image_width=cfg.width,
        image_height=cfg.height,
        reward_window_fraction=reward_window_fraction,
        sensor=sensor,
        sensor_scale=sensor_scale,
    )
    sim = Simulator(load_world(world), sim_cfg)
    layer = SafetyLayer(SafetySettings(), cfg.height, cfg.width, hfov_deg) if safety else None
    flight = Flight(sim, agent, cfg.frames, trained_hfov_deg=hfov_deg, safety=layer)
    r = flight.last
    crashes, reward, dist, sites = 0, 0.0, 0.0, set()
    behaviour = Behaviour(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad)
    start_yaw = r.pose.yaw_rad  # the episode's start heading
    # What the decisions look at, for the stack's networks (a stand-in network without a grid is not measured).
    insight = Insight(net.grid_hw, seed=seed) if hasattr(net, "grid_hw") and insight_every > 0 else None
    try:
        for step in range(1, steps + 1):
            episode_step = sim.step_in_episode + 1  # the simulator's count, before it restarts on a crash
            state = flight.env.state  # a new array every step: the step below leaves it as it is
            s = flight.step(0.0)
            if insight is not None and step % insight_every == 0:
                insight.observe(net, state, s.action, explanation(net, state, s.action, s.attention))
            before, r = s.before.pose, s.after
            reward += r.reward
            if r.collided:
                crashes += 1
                sites.add(crash_site((before.x_m, before.y_m)))
                if crash_log is not None:
                    crash_log.append(
                        dict(
                            model=model,
                            world=world,
                            weights=weights,
                            sim_seed=seed,
                            step=step,
                            episode_step=episode_step,
                            x_m=round(before.x_m, 3),
                            y_m=round(before.y_m, 3),
                            yaw_deg=round(math.degrees(before.yaw_rad), 1),
                            start_yaw_deg=round(math.degrees(start_yaw), 1),
                            action=flight.actions[s.action].name,
                        )
                    )
                start_yaw = r.pose.yaw_rad
            else:
                dist += math.hypot(r.pose.x_m - before.x_m, r.pose.y_m - before.y_m)
            behaviour.step(r.pose.x_m, r.pose.y_m, r.pose.yaw_rad, r.collided)
            if max_crashes and crashes >= max_crashes:
                steps = step
                break
    finally:
        sim.close()
    return EvalResult(
        model,
        world,
        weights,
        steps,
        crashes,
        reward / steps,
        dist,
        len(sites),
        behaviour.turn_steps,
        len(behaviour.cells),
        layer.counts.total if layer is not None else -1,
        insight=insight.summary() if insight is not None else None,
    )


def load_policy(model: str, files: list[str], hfov_deg: float | None, window: float | None = None):
    """(the network, or for several files a QEnsemble on their mean Q-values; its NetConfig; the
    camera to fly with; the reward window) for weights files of one architecture. Without hfov_deg
    the members' trained camera and without `window` their reward window, each of which must then
    be the same for all (ValueError if not)."""
    from uav_policy import weights as wio

    net = wio.load_files(files, model)
    if hfov_deg is None:
        cameras = {wio.camera_for(f, wio.UNRECORDED_HFOV_DEG) for f in files}
        if len(cameras) != 1:
            raise ValueError(f"members were trained with different cameras {sorted(cameras)}: give --sim-arg hfov_deg:=X")
        hfov_deg = cameras.pop()
    if window is None:
        windows = {wio.window_for(f, CENTER_WINDOW_FRACTION) for f in files}
        if len(windows) != 1:
            raise ValueError(
                f"members were trained with different reward windows {sorted(windows)}: give --sim-arg reward_window_fraction:=F"
            )
        window = windows.pop()
    return net, net.cfg, hfov_deg, window
