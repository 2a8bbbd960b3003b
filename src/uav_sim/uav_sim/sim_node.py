"""sim_node: the pybullet quadrotor simulator on ROS 2.

Publishes depth/image_raw (32FC1), depth/camera_info, odom, step_outcome, /clock and
/diagnostics; consumes cmd_vel. In `lockstep` mode one cmd_vel advances one step; in
`realtime` mode the simulator steps at a fixed rate with the latest command and a watchdog.
"""

from __future__ import annotations

import math
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, Range
from std_srvs.srv import Trigger

from uav_common import contract
from uav_common.node_runner import run
from uav_common.ros_params import ParameterError, declare

from .reward import window_fov_rad
from .simulator import SimConfig, Simulator, StepResult, reward_floor_problem
from .vehicle import HOVER, BodyTwist, TwistLimits, twist_error
from .world import EACH_EPISODE, PARTITIONS, WorldError, load_world, training_layouts

# sim_node's camera and reward window by default: those of the packaged weights (docs/RESULTS.md,
# round 35), so that sim_node and policy_node fly them out of the box as they were measured.
# SimConfig keeps the 120 deg camera and the paper's window that the in-process tools default to.
NODE_HFOV_DEG = 150.0
NODE_REWARD_WINDOW_FRACTION = 0.078  # 5 x 5 px at 64 px: at 150 deg the paper's 0.2 would see the floor


class SimNode(Node):
    def __init__(self):
        super().__init__("sim_node")
        d = lambda *a, **k: declare(self, *a, **k)  # noqa: E731
        world_name = d(
            "world",
            "basic",
            f"World: basic, complex, turbulent, random[:SEED], a path to a world .yaml file, or {EACH_EPISODE} "
            "(training: a new seeded procedural layout every episode, random:1000+100000*seed onward)",
        )
        self.mode = d(
            "mode",
            "lockstep",
            "lockstep: one step per cmd_vel; realtime: fixed rate with watchdog",
            choices=("lockstep", "realtime"),
        )
        seed = d("seed", 0, "Seed for weather, start jitter and 'random' worlds", 0, 2**31 - 1)
        cfg = SimConfig(
            image_width=d("image_width", 64, "Depth image width (px)", 8, 1024),
            image_height=d("image_height", 64, "Depth image height (px)", 8, 1024),
            hfov_deg=d(
                "hfov_deg",
                NODE_HFOV_DEG,
                "Horizontal field of view (deg); the packaged weights were trained at 150, the paper's camera is 90",
                10.0,
                170.0,
            ),
            min_range_m=d("min_range_m", 0.1, "Closest measurable depth (m); also the near clip plane", 0.01, 10.0),
            max_range_m=d("max_range_m", 10.0, "Farthest measurable depth (m); beyond it pixels are +Inf", 0.5, 100.0),
            step_duration_s=d("step_duration_s", 0.5, "Sim time one step (one command) lasts (s)", 0.01, 5.0),
            physics_rate_hz=d("physics_rate_hz", 40.0, "Sub-step rate for motion and collision checks (Hz)", 1.0, 1000.0),
            collision_penetration_m=d(
                "collision_penetration_m",
                0.03,
                "Contacts deeper than this are collisions; shallower ones are brushes (m)",
                0.0,
                0.2,
            ),
            start_yaw_jitter_deg=d("start_yaw_jitter_deg", 0.0, "Uniform random yaw added to the start pose (deg)", 0.0, 180.0),
            max_episode_steps=d(
                "max_episode_steps",
                0,
                "Training: an episode that survives this many steps ends (a time limit, not a crash; step_outcome "
                "NaN) and the next starts; 0 = episodes end only in collisions",
                0,
                10**9,
            ),
            random_start_fraction=d(
                "random_start_fraction",
                0.0,
                "Training: the share of episodes that start at a random free place and heading instead of the "
                "world's start pose; 0 = always the start pose (as the paper and evaluation)",
                0.0,
                1.0,
            ),
            random_start_clearance_m=d(
                "random_start_clearance_m",
                SimConfig.random_start_clearance_m,
                "Training: a random start keeps at least this distance from walls and obstacles (m)",
                0.25,
                5.0,
            ),
            reward_window_fraction=d(
                "reward_window_fraction",
                NODE_REWARD_WINDOW_FRACTION,
                "The reward's central window (beta: its nearest depth), as a share of each image side: 0.078 (5 x 5 "
                "px, the packaged weights'); the paper's is 0.2; wider than 120 deg the floor enters it unless "
                "smaller (a warning says so)",
                0.01,
                1.0,
            ),
            limits=TwistLimits(
                max_speed_mps=d("max_speed_mps", 3.0, "Largest |linear.x| and |linear.y| accepted (m/s)", 0.1, 20.0),
                max_climb_mps=d("max_climb_mps", 1.0, "Largest |linear.z| accepted (m/s)", 0.0, 5.0),
                max_yaw_rate_radps=d("max_yaw_rate_radps", 2.0, "Largest |angular.z| accepted (rad/s)", 0.1, 10.0),
            ),
            seed=seed,
        )
        self.watchdog_s = d("watchdog_timeout_s", 1.0, "realtime: hover when no cmd_vel came for this long (s)", 0.05, 60.0)
        self.republish_s = d(
            "lockstep_republish_s",
            1.0,
            "lockstep: publish the current frame again when no command came for this long (s)",
            0.05,
            60.0,
        )
        self.max_rate_hz = d(
            "max_rate_hz",
            0.0,
            "lockstep: at most this many steps per wall-clock second (0 = as fast as commands come)",
            0.0,
            100000.0,
        )
        self.wait_for_subscribers = d(
            "wait_for_subscribers",
            0,
            "lockstep: hold the first frame until depth and outcome each have this many subscribers (the train "
            "launcher sets 2, policy and trainer, so that the trainer learns from the first step); 0 = at once",
            0,
            100,
        )
        self.frame_id = d("camera_frame_id", "camera_depth_optical_frame", "frame_id of depth and camera_info (REP 118)")
        self.odom_frame = d("odom_frame_id", "odom", "Odometry header frame (REP 105)")
        self.base_frame = d("base_frame_id", "base_link", "Odometry child frame (REP 105)")
        redraw_heading = d(
            "redraw_start_heading",
            False,
            f"world:={EACH_EPISODE} only: draw a new start_yaw_jitter_deg heading for every layout (default: every "
            "layout starts at the run's first draw, as the shipped weights were trained; redrawing trained worse)",
        )
        mix_name = d("mix_world", "basic", f"world:={EACH_EPISODE} with mix_world_every: the world flown between the layouts")
        mix_every = d(
            "mix_world_every",
            0,
            f"world:={EACH_EPISODE} only: every K-th episode (K >= 2) flies mix_world instead of a new layout "
            "(an extension; 0 = layouts only)",
            0,
            10**6,
        )
        partitions = d(
            "layout_partitions",
            False,
            f"world:={EACH_EPISODE} only: layouts with 2-3 m partitions among the boxes ({PARTITIONS}:SEED, an "
            "extension; default: plain layouts, as the shipped weights were trained)",
        )
        if partitions and world_name != EACH_EPISODE:
            raise ParameterError(f"parameter 'layout_partitions' (true): needs world:={EACH_EPISODE}")
        if mix_every and (mix_every < 2 or world_name != EACH_EPISODE):
            raise ParameterError(f"parameter 'mix_world_every' ({mix_every}): must be 0, or >= 2 with world:={EACH_EPISODE}")
        try:
            mix = load_world(mix_name, seed=seed) if mix_every else None
        except WorldError as e:
            raise ParameterError(f"parameter 'mix_world': {e}") from None
        layouts = training_layouts(seed, mix, mix_every, partitions) if world_name == EACH_EPISODE else None
        try:
            world = next(layouts) if layouts else load_world(world_name, seed=seed)
        except WorldError as e:
            raise ParameterError(f"parameter 'world': {e}") from None
        try:
            self.sim = Simulator(world, cfg, next_worlds=layouts, redraw_heading=redraw_heading)
        except ValueError as e:
            raise ParameterError(str(e)) from None
        self.cfg = cfg
        floor = reward_floor_problem(cfg, world.start_xyz_m[2])
        if floor:  # crash counts stay meaningful (evaluation); training on this reward does not
            self.get_logger().warning(floor)

        q = contract.STREAM_QOS
        self.pub_depth = self.create_publisher(Image, contract.DEPTH_TOPIC, q)
        self.pub_info = self.create_publisher(CameraInfo, contract.CAMERA_INFO_TOPIC, q)
        self.pub_odom = self.create_publisher(Odometry, contract.ODOM_TOPIC, q)
        self.pub_outcome = self.create_publisher(Range, contract.OUTCOME_TOPIC, q)
        self.pub_clock = self.create_publisher(Clock, "/clock", q)
        self.pub_diag = self.create_publisher(DiagnosticArray, contract.DIAGNOSTICS_TOPIC, 10)
        self.create_subscription(Twist, contract.CMD_VEL_TOPIC, self.on_cmd_vel, q)
        self.create_service(Trigger, "~/reset", self.on_reset)

        self.rejected = 0
        self.brushes = 0
        self.cmd = HOVER
        self.executed = HOVER
        self.last_cmd_wall = -math.inf
        self.watchdog_active = False
        self.last_publish_wall = time.monotonic()
        self.next_step_wall = time.monotonic()
        self.steps_at_diag = 0
        self.diag_wall = time.monotonic()
        self.current: StepResult = self.sim.observe()
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
        mixed = f" ('{mix.name}' every {mix_every} episodes)" if mix else ""
        self.get_logger().info(
            (f"a new layout every episode{mixed}, first " if layouts else "")
            + f"world '{world.name}' ({len(world.obstacles)} obstacles, weather rain={world.weather.rain} "
            f"snow={world.weather.snow} leaves={world.weather.leaves}), mode {self.mode}, "
            f"{cfg.image_width}x{cfg.image_height} depth, step {cfg.step_duration_s} s"
        )

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
            self.get_logger().warning(
                "ignoring cmd_vel: the first frame is held (wait_for_subscribers)", throttle_duration_sec=5.0
            )
            return
        self.last_cmd_wall = time.monotonic()
        if self.mode == "lockstep":
            if self.max_rate_hz > 0:
                # Rate cap: lets a learner on a small machine keep its replay ratio.
                wait = self.next_step_wall - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                self.next_step_wall = max(self.next_step_wall, time.monotonic() - 1.0) + 1.0 / self.max_rate_hz
            self.advance(cmd)
        else:
            self.cmd = cmd
            if self.watchdog_active:
                self.get_logger().info("cmd_vel is back: watchdog released")
                self.watchdog_active = False

    def on_realtime_tick(self) -> None:
        if time.monotonic() - self.last_cmd_wall > self.watchdog_s:
            if not self.watchdog_active:
                self.get_logger().warning(f"no cmd_vel for {self.watchdog_s} s: watchdog stops the vehicle (hover)")
                self.watchdog_active = True
            self.cmd = HOVER
        self.advance(self.cmd)

    def on_lockstep_idle(self) -> None:
        if not self.gate_open:
            listening = min(self.pub_depth.get_subscription_count(), self.pub_outcome.get_subscription_count())
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
        self.current = self.sim.reset()
        if self.gate_open:  # else the frame goes out when the gate opens (an answer now would be ignored)
            self.publish(self.current)
        resp.success = True
        resp.message = f"episode {self.sim.episode} started at the start pose of '{self.sim.world.name}'"
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
        self.current = result
        self.publish(result)

    # -- output ------------------------------------------------------------------------
    def publish(self, r: StepResult) -> None:
        stamp = contract.stamp_from_seconds(r.sim_time_s)
        self.pub_clock.publish(Clock(clock=stamp))
        cfg = self.cfg
        self.pub_outcome.publish(
            contract.make_outcome(
                r.beta_m,
                r.collided,
                stamp,
                self.frame_id,
                cfg.min_range_m,
                cfg.max_range_m,
                window_fov_rad(cfg.image_width, cfg.hfov_deg, cfg.reward_window_fraction),
                truncated=r.truncated,
            )
        )
        self.pub_odom.publish(self.odometry(r, stamp))
        info = CameraInfo()
        info.header.stamp = stamp
        info.header.frame_id = self.frame_id
        info.width, info.height = cfg.image_width, cfg.image_height
        info.distortion_model = "plumb_bob"
        info.d = [0.0] * 5
        info.k = self.sim.camera.intrinsics.k_matrix()
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        k = info.k
        info.p = [k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
        self.pub_info.publish(info)
        self.pub_depth.publish(contract.depth_to_image(r.depth_m, stamp, self.frame_id))
        self.last_publish_wall = time.monotonic()

    def odometry(self, r: StepResult, stamp) -> Odometry:
        msg = Odometry()
        msg.header.stamp = stamp
        msg.header.frame_id = self.odom_frame
        msg.child_frame_id = self.base_frame
        pose = r.pose
        msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = pose.x_m, pose.y_m, pose.z_m
        msg.pose.pose.orientation.z = math.sin(pose.yaw_rad / 2)
        msg.pose.pose.orientation.w = math.cos(pose.yaw_rad / 2)
        cmd = self.executed  # the body velocity flown during the step that ended here
        msg.twist.twist.linear.x, msg.twist.twist.linear.y = cmd.vx_mps, cmd.vy_mps
        msg.twist.twist.linear.z, msg.twist.twist.angular.z = cmd.vz_mps, cmd.yaw_rate_radps
        return msg

    def publish_diagnostics(self) -> None:
        now = time.monotonic()
        rate = (self.sim.total_steps - self.steps_at_diag) / max(now - self.diag_wall, 1e-6)
        self.steps_at_diag, self.diag_wall = self.sim.total_steps, now
        st = DiagnosticStatus(level=DiagnosticStatus.OK, name="uav_sim", hardware_id=self.get_fully_qualified_name())
        st.message = "watchdog: hovering" if self.watchdog_active else "running"
        if self.watchdog_active:
            st.level = DiagnosticStatus.WARN
        vals = {
            "world": self.sim.world.name,
            "episodes": self.sim.episode,
            "steps": self.sim.total_steps,
            "collisions": self.sim.collisions,
            "brushes": self.brushes,
            "rejected_commands": self.rejected,
            "steps_per_s": f"{rate:.1f}",
        }
        st.values = [KeyValue(key=k, value=str(v)) for k, v in vals.items()]
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def close(self) -> None:
        self.sim.close()


def main(args=None) -> int:
    return run(SimNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
