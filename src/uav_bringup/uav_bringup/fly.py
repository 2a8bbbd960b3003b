"""fly: watch a policy fly. Starts sim_node and policy_node with params/*.yaml (and, if asked, the
recorder and the Foxglove live view) and stops them cleanly on Ctrl-C, as `train` does for training.

    ros2 run uav_bringup fly --model sam --world turbulent --live-view       # Foxglove: ws://localhost:8765
    ros2 run uav_bringup fly --model cnn --world complex --record runs/bags/cnn_complex --duration 120

The simulator runs in real time (one step per step_duration_s, 0.5 s) unless --lockstep, which steps
as fast as the policy answers. --namespace puts the pair in a namespace (frames follow: uav1/odom).
The full-ROS equivalent is `ros2 launch uav_bringup fly.launch.py`.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from uav_common.launching import Processes, params_args, stop_signals

# The simulator first (nothing new is said), the recorder last: the bag holds the final messages. With a recorder the
# simulator is paused before (RecorderWatch.pause_sim), so that its last messages reach the bag too.
STOP_ORDER = ["sim", "policy", "mavlink", "record", "live_view"]


class RecorderWatch:
    """fly's own node (its own context: Ctrl-C stays fly's), listening to the recorder's reports: the simulator starts
    once the recorder hears policy_node, so that the first step is on record too, and at the end the simulator is
    paused and the nodes stop only once the recorder has written everything they said."""

    def __init__(self, namespace: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        from .record import RecorderReports

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("fly", namespace=namespace or "/", context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.reports = RecorderReports(self.node)

    def policy_heard(self, procs: Processes, stopped, timeout_s: float = 60.0) -> bool:
        """False (and says why) if the recorder does not hear the policy within `timeout_s`, a process exits or
        Ctrl-C comes."""
        try:
            return self.reports.wait_for_policy(self.executor, procs.procs, timeout_s, stopped)
        except (RuntimeError, TimeoutError) as e:
            print(f"{e}; stopping the others", file=sys.stderr)
            return False

    def pause_sim(self, timeout_s: float = 10.0) -> bool:
        """Pause sim_node (its ~/pause); False (and says why) if it does not answer within `timeout_s`."""
        from std_srvs.srv import SetBool

        from uav_common.node_runner import call_until_answered

        client = self.node.create_client(SetBool, "sim_node/pause")
        try:
            answer = call_until_answered(self.executor, client, SetBool.Request(data=True), timeout_s)
        finally:
            self.node.destroy_client(client)
        if answer is not None and answer.success:
            return True
        print(
            f"sim_node did not answer its pause within {timeout_s:g} s: stopping it; its last messages may be "
            "missing from the bag",
            file=sys.stderr,
        )
        return False

    def drained(self, timeout_s: float = 20.0) -> None:
        if not self.reports.wait_until_idle(self.executor, timeout_s):
            missing = self.reports.missing()
            lacks = ", ".join(f"{t} its last {n}" for t, n in missing.items()) or "perhaps the last steps"
            print(f"the recorder was still writing after {timeout_s:g} s: the bag lacks {lacks}", file=sys.stderr)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()


def node_args(params: Path | None, name: str, values: list[str], namespace: str) -> list[str]:
    ns = ["-r", f"__ns:={namespace}"] if namespace else []
    return params_args(params, name) + ns + [x for kv in values for x in ("-p", kv)]


def camera_of(model: str, weights: str) -> list[str]:
    """sim_node arguments for the sensor `weights` (default: the packaged ones) were trained behind."""
    from uav_policy import weights as wio
    from uav_sim.sensor import sim_args_for_camera

    try:
        files = wio.parse_files(weights) if weights else wio.packaged_weights(model)
        return sim_args_for_camera(wio.read_file_camera(files[0]) if files else None)
    except ValueError:  # unreadable weights: policy_node says why at start-up
        return []


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="fly", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", choices=("sam", "cnn"), default="sam")
    ap.add_argument("--weights", default="", help="weights files a,b,c (default: the packaged policy)")
    ap.add_argument("--world", default="basic", help="basic, complex, turbulent, random:SEED or a world file")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed")
    ap.add_argument("--namespace", default="", help="namespace of the pair, e.g. /uav1 (default: none)")
    ap.add_argument("--lockstep", action="store_true", help="step as fast as the policy answers, not in real time")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: until Ctrl-C)")
    ap.add_argument("--record", default="", metavar="BAG", help="record the flight to this bag folder (must not exist)")
    ap.add_argument("--live-view", action="store_true", help="serve the flight to Foxglove (ws://localhost:PORT)")
    ap.add_argument("--port", type=int, default=8765, help="live view port (default: 8765)")
    ap.add_argument("--params-dir", default="params", help="folder with sim.yaml and policy.yaml (default: params)")
    ap.add_argument("--log-dir", default="", help="write node logs here instead of the terminal")
    ap.add_argument("--sim-arg", action="append", default=[], metavar="NAME:=VALUE", help="extra sim_node parameter")
    ap.add_argument("--policy-arg", action="append", default=[], metavar="NAME:=VALUE", help="extra policy_node parameter")
    ap.add_argument(
        "--shield",
        action="store_true",
        help="fly the network behind the shield (policy_node's shield:=always: its best action of those the local map of "
        "the simulator's frames and odometry says are safe); a camera's frames are shielded by default",
    )
    ap.add_argument(
        "--mavlink",
        default="",
        metavar="URL",
        help="also hand cmd_vel to an autopilot through mavlink_bridge (e.g. udpin:0.0.0.0:14540); it never arms or "
        "switches modes (docs/REAL_CAMERA.md)",
    )
    a = ap.parse_args(argv)
    if a.duration < 0:
        ap.error("--duration must be >= 0")
    if a.namespace and not a.namespace.startswith("/"):
        a.namespace = "/" + a.namespace
    for arg in a.sim_arg + a.policy_arg:
        if ":=" not in arg:
            ap.error(f"{arg!r}: node arguments are NAME:=VALUE")
    if a.record and Path(a.record).exists():
        ap.error(f"--record {a.record}: already exists (a bag is never overwritten)")
    params = Path(a.params_dir) if Path(a.params_dir).is_dir() else None
    stopped = stop_signals()
    procs = Processes(log_dir=Path(a.log_dir) if a.log_dir else None)
    ns = ["-r", f"__ns:={a.namespace}"] if a.namespace else []
    # Recorder and viewer first: the simulator's first frames find them listening.
    if a.record:
        procs.start("record", "uav_bringup", "record", ns, args=["-o", a.record])
    if a.live_view:
        procs.start("live_view", "uav_bringup", "live_view", ns, args=["--port", str(a.port)])
    # The policy before the simulator: loading its networks takes longer than the real-time watchdog.
    policy_values = [f"model:={a.model}", "source:=simulator"] + ([f"weights:={a.weights}"] if a.weights else [])
    policy_values += ["shield:=always"] if a.shield else []
    procs.start("policy", "uav_policy", "policy_node", node_args(params, "policy", policy_values + a.policy_arg, a.namespace))
    if a.mavlink:
        procs.start(
            "mavlink", "uav_bringup", "mavlink_bridge", node_args(params, "mavlink_bridge", [f"url:={a.mavlink}"], a.namespace)
        )
    watch = RecorderWatch(a.namespace) if a.record else None
    try:
        return flight(a, procs, params, stopped, watch)
    finally:
        if watch is not None:
            watch.close()


def flight(a, procs: Processes, params: Path | None, stopped, watch: RecorderWatch | None) -> int:
    if watch is not None and not watch.policy_heard(procs, stopped):
        procs.stop_all(STOP_ORDER)
        return 0 if stopped() else 1
    sim_values = [f"world:={a.world}", f"seed:={a.seed}", f"mode:={'lockstep' if a.lockstep else 'realtime'}"]
    if not any(arg.startswith("sensor:=") for arg in a.sim_arg):
        sim_values += camera_of(a.model, a.weights)  # the sensor the weights were trained behind
    if a.lockstep and a.record:
        sim_values.append("wait_for_subscribers:=2")  # the policy and the recorder
    procs.start("sim", "uav_sim", "sim_node", node_args(params, "sim", sim_values + a.sim_arg, a.namespace))
    extras = (
        (f", recording to {a.record}" if a.record else "")
        + (f", live view on ws://localhost:{a.port}" if a.live_view else "")
        + (f", commands to the autopilot on {a.mavlink}" if a.mavlink else "")
    )
    print(f"flying D3QN-{a.model.upper()} in '{a.world}'{extras}; Ctrl-C stops", flush=True)

    end = time.monotonic() + a.duration if a.duration else float("inf")
    code = 0
    while not stopped() and time.monotonic() < end:
        dead = [(n, p.returncode) for n, p in procs.procs.items() if p.poll() is not None]
        if dead:
            print(f"{dead[0][0]} exited early (code {dead[0][1]}); stopping the others", file=sys.stderr)
            code = 1
            break
        time.sleep(0.2)
    sim = procs.procs.get("sim")
    paused = watch is not None and sim is not None and sim.poll() is None and watch.pause_sim()
    codes = {"sim": procs.stop("sim")} if sim is not None and not paused else {}
    if watch is not None:
        watch.drained()
    codes.update({name: procs.stop(name) for name in STOP_ORDER if name in procs.procs and name not in codes})
    failed = {n: c for n, c in codes.items() if c not in (0, -signal.SIGINT)}
    if failed and not code:
        print(f"stopped with errors: {failed}", file=sys.stderr)
        code = 1
    if a.record and Path(a.record).is_dir():
        print(f"bag: {a.record}", flush=True)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
