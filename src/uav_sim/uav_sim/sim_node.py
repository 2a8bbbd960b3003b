"""sim_node: the pybullet quadrotor simulator on ROS 2.

Publishes depth/image_raw (32FC1), depth/camera_info, odom, step_outcome (uav_interfaces/StepOutcome), world/markers
(the room and obstacles, latched), trajectory (this episode's path), /clock (unless publish_clock:=false:
several simulators in one graph would each say their own time), /diagnostics and, with a teacher
(teacher:=stack|all|map), teacher_label (uav_interfaces/TeacherLabel): the planner's action, scores and reason per
frame; consumes cmd_vel. Services: ~/reset (std_srvs/Trigger: a new episode at the start pose) and ~/pause
(std_srvs/SetBool: true holds the vehicle where it is, no step and nothing published until false).
Frames carry the node's namespace (`/uav1`: `uav1/odom`, `uav1/base_link`). In
`lockstep` mode one cmd_vel advances one step; in `realtime` mode the simulator steps at a fixed
rate with the latest command and a watchdog.
"""

from __future__ import annotations

import math
import time

from geometry_msgs.msg import Twist
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger

from uav_common import contract
from uav_common.kinematics import HOVER, BodyTwist, twist_error
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError
from uav_common.settings import declare_settings

from .messages import camera_info_msg, odometry_msg, teacher_label_msg
from .planner import PlannerConfig, SimPlanner
from .reward import window_fov_rad
from .sim_outputs import SimOutputs
from .sim_settings import REMOVED, SimNodeSettings, describe
from .simulator import Simulator, StepResult, reward_floor_problem
from .world import WorldError


class SimNode(Node):
    def __init__(self, **node_options):  # e.g. context=: built in a test's own context
        super().__init__("sim_node", **node_options)
        st = declare_settings(self, SimNodeSettings, REMOVED)
        cfg = st.sim
        self.mode = st.mode
        self.watchdog_s = st.watchdog_timeout_s
        self.republish_s = st.lockstep_republish_s
        self.wait_for_subscribers = st.wait_for_subscribers
        self.step_budget = st.step_budget
        ns = self.get_namespace()
        self.frame_id, self.odom_frame, self.base_frame = (
            contract.vehicle_frame(ns, f) for f in (st.camera_frame_id, st.odom_frame_id, st.base_frame_id)
        )
        try:
            world, layouts = st.worlds.load(cfg.seed)
        except WorldError as e:
            raise ParameterError(f"parameter {e}") from None
        try:
            self.sim = Simulator(world, cfg, next_worlds=layouts)
        except ValueError as e:
            raise ParameterError(str(e)) from None
        self.cfg = cfg = self.sim.config  # with the sensor preset's camera
        self.teacher = (
            None
            if st.teacher == "none"
            else SimPlanner(self.sim, PlannerConfig(knowledge=st.teacher, memory_frames=st.teacher_frames))
        )
        self.depth_encoding = st.depth_encoding
        floor = reward_floor_problem(cfg, world.start_xyz_m[2])
        if floor:  # crash counts stay meaningful (evaluation); training on this reward does not
            self.get_logger().warning(floor)

        self.out = SimOutputs(self, self.teacher is not None, st.publish_clock, self.odom_frame)
        q = contract.STREAM_QOS
        # Commands lost on the way (a publisher's history overwritten under a flood, a gap) are counted from the
        # publisher's sequence numbers, not silent.
        self.create_subscription(Twist, contract.CMD_VEL_TOPIC, self.on_cmd_vel_with_info, q)
        self.cmd_topic = self.resolve_topic_name(contract.CMD_VEL_TOPIC)
        self.cmd_publishers, self.last_cmd_seq = 0, None
        self.create_service(Trigger, "~/reset", self.on_reset)
        self.create_service(SetBool, "~/pause", self.on_pause)
        self.paused = False

        self.rejected = 0
        self.commands_lost = 0  # gaps in the publisher's sequence numbers (one publisher on cmd_vel)
        self.commands_ignored = 0  # came while the first frame was held (wait_for_subscribers) or after step_budget
        self.brushes = 0
        self.cmd = HOVER
        self.executed = HOVER
        self.last_cmd_wall = -math.inf
        self.watchdog_active = False
        self.last_publish_wall = time.monotonic()
        self.steps_at_diag = 0
        self.diag_wall = time.monotonic()
        self.current: StepResult = self.sim.observe()
        self.from_reset = False  # the current frame began an episode at ~/reset (its outcome says so)
        # Closed until wait_for_subscribers peers listen (lockstep): no frame, and commands are ignored.
        self.gate_open, self.gate_ticks = self.mode != "lockstep" or self.wait_for_subscribers == 0, 0
        if self.gate_open:
            self.publish(self.current)
        else:
            self.get_logger().info(
                f"holding the first frame until depth and outcome have {self.wait_for_subscribers} subscribers each"
            )
        if self.mode == "realtime":
            self.create_timer(cfg.step_duration_s, self.on_realtime_tick)
        else:
            self.create_timer(min(self.republish_s, 0.25), self.on_lockstep_idle)
        self.create_timer(1.0, self.publish_diagnostics)
        self.get_logger().info(describe(world, layouts, st.worlds, self.mode, cfg, self.depth_encoding))
        if self.teacher is not None:
            self.get_logger().info(f"teacher_label: the planner ({st.teacher}) labels every frame, for a trainer to learn")

    # -- commands ----------------------------------------------------------------------
    def on_cmd_vel(self, msg: Twist) -> None:
        cmd = BodyTwist(msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z)
        err = twist_error(cmd, self.cfg.limits)
        if err:
            self.rejected += 1
            self.get_logger().warning(f"rejected cmd_vel ({err}); holding position", throttle_duration_sec=2.0)
            self.cmd = HOVER
            return
        if not self.gate_open:
            self.commands_ignored += 1
            self.get_logger().warning(
                "ignoring cmd_vel: the first frame is held (wait_for_subscribers)", throttle_duration_sec=5.0
            )
            return
        self.last_cmd_wall = time.monotonic()
        if self.mode == "lockstep":
            if self.paused:
                self.commands_ignored += 1
                return
            if self.budget_flown():
                self.commands_ignored += 1
                self.get_logger().info(f"step budget of {self.step_budget} steps flown: holding position", once=True)
                return
            self.advance(cmd)
        else:
            self.cmd = cmd
            if self.watchdog_active:
                self.get_logger().info("cmd_vel is back: watchdog released")
                self.watchdog_active = False

    def budget_flown(self) -> bool:
        return self.mode == "lockstep" and 0 < self.step_budget <= self.sim.total_steps

    def on_cmd_vel_with_info(self, msg: Twist, info: dict) -> None:
        """Count the commands lost before this one (a gap in its publisher's sequence numbers; several publishers
        interleave theirs, so only with one), then take it."""
        seq = info.get("publication_sequence_number")
        if seq is not None and self.last_cmd_seq is not None and seq > self.last_cmd_seq + 1 and self.cmd_publishers == 1:
            self.commands_lost += seq - self.last_cmd_seq - 1
            self.get_logger().warning(
                f"{self.commands_lost} cmd_vel message(s) lost before they reached the simulator", throttle_duration_sec=5.0
            )
        self.last_cmd_seq = seq
        self.on_cmd_vel(msg)

    def on_realtime_tick(self) -> None:
        if self.paused:
            return
        if time.monotonic() - self.last_cmd_wall > self.watchdog_s:
            if not self.watchdog_active:
                self.get_logger().warning(f"no cmd_vel for {self.watchdog_s} s: watchdog stops the vehicle (hover)")
                self.watchdog_active = True
            self.cmd = HOVER
        self.advance(self.cmd)

    def on_lockstep_idle(self) -> None:
        if self.paused:
            return
        if not self.gate_open:
            listening = min(self.out.depth.get_subscription_count(), self.out.outcome.get_subscription_count())
            # Open one tick after the count is reached: a subscriber's other topics (the trainer's
            # action subscription) are matched a moment after its first.
            self.gate_ticks = self.gate_ticks + 1 if listening >= self.wait_for_subscribers else 0
            if self.gate_ticks >= 2:
                self.gate_open = True
                self.get_logger().info(f"{listening} subscribers on depth and outcome: publishing the first frame")
                self.publish(self.current)
            return
        # A frame can be lost while peers are still being discovered: say it again.
        if time.monotonic() - self.last_publish_wall > self.republish_s:
            self.publish(self.current)

    def on_reset(self, _req, resp):
        self.current, self.from_reset = self.sim.reset(), True
        if self.gate_open and not self.paused:  # else the frame goes out when the gate opens or the pause ends
            self.publish(self.current)
        resp.success = True
        resp.message = f"episode {self.sim.episode} started at the start pose of '{self.sim.world.name}'"
        return resp

    def on_pause(self, req, resp):
        """Pause (data true): no step and nothing published from now on, and /diagnostics says so with the final
        `published TOPIC` counts at once (a recorder's launcher waits for the bag to hold them all); resume (false):
        a lockstep simulator says its frame again, to be answered."""
        was, self.paused = self.paused, bool(req.data)
        if self.paused and not was:
            self.get_logger().info(f"paused after {self.sim.total_steps} steps")
        elif was and not self.paused:
            self.get_logger().info("resumed")
            if self.mode == "lockstep" and self.gate_open:
                self.publish(self.current)
        self.publish_diagnostics()
        resp.success = True
        resp.message = f"{'paused' if self.paused else 'running'} after {self.sim.total_steps} steps"
        return resp

    def advance(self, cmd: BodyTwist) -> None:
        result = self.sim.step(cmd)
        self.executed = cmd
        self.brushes += result.brushes
        if result.collided:
            self.get_logger().info(
                f"collision: episode {result.episode - 1} ended; vehicle back at the start of '{self.sim.world.name}' "
                f"({self.sim.collisions} collisions in {self.sim.total_steps} steps)"
            )
        elif result.truncated:
            self.get_logger().info(
                f"time limit: episode {result.episode - 1} ended after {self.cfg.max_episode_steps} steps; vehicle back "
                f"at the start of '{self.sim.world.name}'"
            )
        self.current, self.from_reset = result, False
        self.publish(result)

    # -- output ------------------------------------------------------------------------
    def publish(self, r: StepResult) -> None:
        stamp, out, cfg = contract.stamp_from_seconds(r.sim_time_s), self.out, self.cfg
        if out.clock is not None:
            out.send(out.clock, Clock(clock=stamp))
        if self.teacher is not None and not self.budget_flown():  # the teacher's answer and reason before the frame
            out.send(out.teacher, teacher_label_msg(self.teacher.label(), self.teacher.reason_mask(), stamp, self.frame_id))
        window_rad = window_fov_rad(cfg.image_width, cfg.hfov_deg, cfg.reward_window_fraction)
        out.send(
            out.outcome,
            contract.make_outcome(
                r.beta_m,
                r.collided,
                stamp,
                self.frame_id,
                cfg.min_range_m,
                cfg.max_range_m,
                window_rad,
                truncated=r.truncated,
                reset=self.from_reset,
            ),
        )
        # The outcome, the camera and the frame first (a frame is mapped through the CameraInfo before it): a
        # lockstep step waits for them; the rest goes out meanwhile. Once the step budget is flown no frame goes
        # out: there is nothing more to answer (and so nothing decided or measured beyond the budget).
        if not self.budget_flown():
            k = self.sim.camera.intrinsics.k_matrix()
            out.send(out.info, camera_info_msg(stamp, self.frame_id, cfg.image_width, cfg.image_height, k))
            out.send(out.depth, contract.depth_to_image(r.depth_m, stamp, self.frame_id, self.depth_encoding))
        self.last_publish_wall = time.monotonic()
        out.send(out.odom, odometry_msg(r.pose, self.executed, stamp, self.odom_frame, self.base_frame))
        out.world(self.sim.world, stamp)
        out.path_step(r.pose, r.collided or r.truncated, stamp)

    def publish_diagnostics(self) -> None:
        self.cmd_publishers = self.count_publishers(self.cmd_topic)
        now = time.monotonic()
        rate = (self.sim.total_steps - self.steps_at_diag) / max(now - self.diag_wall, 1e-6)
        self.steps_at_diag, self.diag_wall = self.sim.total_steps, now
        vals = {
            "world": self.sim.world.name,
            "episodes": self.sim.episode,
            "steps": self.sim.total_steps,
            "collisions": self.sim.collisions,
            "brushes": self.brushes,
            "rejected_commands": self.rejected,
            "commands_lost": self.commands_lost,
            "commands_ignored": self.commands_ignored,
            "cmd_vel_publishers": self.cmd_publishers,
            "steps_per_s": f"{rate:.1f}",
            "paused": str(self.paused).lower(),
        } | self.out.published()
        level, message = ("WARN", "watchdog: hovering") if self.watchdog_active else ("OK", "running")
        message = "paused" if self.paused else message
        self.out.diag.publish(contract.diagnostics(self, "uav_sim", level, message, vals))

    def close(self) -> None:
        self.sim.close()


def main(args=None) -> int:
    return run(SimNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
