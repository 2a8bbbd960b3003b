"""Measuring flights through the ROS nodes: sim_node and policy_node started for one policy and world, flown
exploit-only in lockstep (`evaluate_once`), their step outcomes and odometry counted into an EvalResult (the
in-process flight and the result types: uav_eval.flights)."""

from __future__ import annotations

import math
import time
from pathlib import Path

from uav_common import contract
from uav_common.launching import Processes, params_args
from uav_policy.insight import InsightSummary
from uav_sim.reward import step_reward

from . import ENSEMBLE_SEP
from .flights import (
    Behaviour,
    EvalResult,
    FlightSpec,
    architecture_args,
    crash_site,
    flown_hfov_deg,
    flown_window,
    image_size_args,
    sim_arg_hfov_deg,
    sim_arg_number,
)


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
            beta = contract.outcome_beta(out)
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


def evaluate_once(
    spec: FlightSpec,
    params_dir: Path | None = None,
    timeout_s: float = 600.0,
    log_dir: Path | None = None,
    progress=None,
    record_to: Path | None = None,
) -> EvalResult:
    """Run sim_node + policy_node (installed executables) and measure the spec's steps in lockstep; with
    `record_to`, uav_bringup's `record` keeps the flight there as a bag, from its first frame. The policy
    flies without its safety layer (its own crashes), or with the spec's `safety` through it (interventions counted);
    with `shield` it chooses among the actions its local map says are safe (overrides counted). sim_node gets the spec's
    `sim_args` (nodes_args: what they leave out, the weights decide); `weights` may be an ensemble's files joined by
    ENSEMBLE_SEP (which must share architecture, camera and reward window: load_policy checks)."""
    steps = spec.steps
    sim_args, policy_args = nodes_args(spec, params_dir)
    import rclpy
    import rclpy.executors
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from uav_interfaces.msg import StepOutcome

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("evaluate_monitor", context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    mon = StepMonitor(steps)
    deep = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10000)
    node.create_subscription(StepOutcome, contract.OUTCOME_TOPIC, lambda m: mon.add("outcome", m), deep)
    node.create_subscription(Odometry, contract.ODOM_TOPIC, lambda m: mon.add("odom", m), deep)
    said = {}  # the policy's latest /diagnostics values, and when they came
    node.create_subscription(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: policy_said(said, m), 10)
    procs = Processes(log_dir=log_dir, quiet=log_dir is None)
    try:
        ready_by = time.monotonic() + 60.0
        sim_extra = []
        recorder = None
        if record_to is not None:
            # Recorder and policy first. The simulator starts once the recorder and the policy hear each
            # other, and holds its first frame until the policy, the recorder and this monitor
            # all listen: the bag holds every step from the first frame on.
            from uav_bringup.record import RecorderReports

            recorder = RecorderReports(node)
            node.create_subscription(Image, contract.DEPTH_TOPIC, lambda m: None, deep)  # the third listener
            procs.start("record", "uav_bringup", "record", [], args=["-o", str(record_to), "--quiet"])
            procs.start("policy", "uav_policy", "policy_node", policy_args)
            recorder.wait_for_policy(executor, procs.procs, ready_by - time.monotonic())
            sim_extra = ["-p", "wait_for_subscribers:=3"]
        # The lockstep sim only advances once the policy answers, and it says its first frame again
        # every lockstep_republish_s: without a recorder the policy starts once the monitor has that
        # frame, so no step can go by before the monitor hears the simulator.
        sim = procs.start("sim", "uav_sim", "sim_node", sim_args + sim_extra)
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
        if recorder is not None:
            wait_for_the_bag(executor, recorder, node.resolve_topic_name(contract.OUTCOME_TOPIC), mon.outcomes, record_to)
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
        spec.model,
        spec.world,
        spec.weights,
        mon.steps,
        mon.crashes,
        mon.reward / max(mon.steps, 1),
        mon.distance,
        len(mon.sites),
        b.turn_steps if b else -1,
        len(b.cells) if b else -1,
        int(said["safety_interventions"]) if spec.safety else -1,
        InsightSummary.from_values(said),
        int(said["shield_overridden"]) if spec.shield else -1,
    )


def nodes_args(spec: FlightSpec, params_dir: Path | None) -> tuple[list[str], list[str]]:
    """(sim_node's, policy_node's) arguments for a flight: without hfov_deg in the spec's `sim_args` the simulator gets
    the camera the weights were trained with, without reward_window_fraction the reward window they record (else the
    paper's), without a sensor the preset of that camera, and without image_width/image_height their input size."""
    model, sim_args = spec.model, tuple(spec.sim_args)
    files = spec.weights.split(ENSEMBLE_SEP) if spec.weights else []
    first = files[0] if files else ""
    if sim_arg_hfov_deg(sim_args) is None:
        sim_args = (*sim_args, f"hfov_deg:={flown_hfov_deg(model, first)}")
    if sim_arg_number(sim_args, "reward_window_fraction") is None:
        sim_args = (*sim_args, f"reward_window_fraction:={flown_window(model, first)}")
    if not any(arg.startswith("sensor:=") for arg in sim_args):
        from uav_sim.sensor import sim_args_for_camera

        sim_args = (*sim_args, *sim_args_for_camera(flown_hfov_deg(model, first)))
    sim_args = (*sim_args, *image_size_args(model, first, sim_args))
    pargs = lambda kv: [x for item in kv for x in ("-p", item)]  # noqa: E731
    sim = [
        f"world:={spec.world}",
        f"seed:={spec.seed}",
        f"start_yaw_jitter_deg:={float(spec.start_yaw_jitter_deg)}",
        f"step_budget:={spec.steps}",  # exactly the steps measured: no frame after the last to answer
        *sim_args,
    ]
    wargs = [f"weights:={','.join(files)}", *architecture_args(model, first)] if files else []
    policy = [
        f"model:={model}",
        f"epsilon:={spec.epsilon}",
        f"seed:={spec.seed}",
        "source:=simulator",  # the first frames wait for their outcome, whenever the policy discovers sim_node
        "publish_overlay:=false",
        f"safety:={str(spec.safety).lower()}",
        f"shield:={'always' if spec.shield else 'never'}",
        f"insight_every:={spec.insight_every}",  # every k-th decision measured, over the whole flight
        f"insight_window:={2 * spec.steps + 100}",
        *wargs,
    ]
    return params_args(params_dir, "sim") + pargs(sim), params_args(params_dir, "policy") + pargs(policy)


def wait_for_the_bag(executor, recorder, outcome_topic: str, heard: int, bag: Path) -> None:
    """A busy recorder may lag, or miss a message and get it again: the simulator lives on (holding position and
    saying the last step's outcome again each lockstep_republish_s) until the bag holds every step (RuntimeError
    when it does not within 60 s)."""
    written = recorder.written
    asked = time.monotonic()
    while written.get(outcome_topic, 0) < heard and time.monotonic() < asked + 60.0:
        executor.spin_once(timeout_sec=0.05)
    if written.get(outcome_topic, 0) < heard:
        raise RuntimeError(
            f"the recorder wrote {written.get(outcome_topic, 0)} of the {heard} step outcomes within 60 s: the bag {bag} "
            "is incomplete"
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
