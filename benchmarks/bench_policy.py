"""Policy figures in one run: inference latency (p50/p99, batch 1, CPU) for SAM and CNN, alone and as
ensembles of 3 and 10 networks; the cost of measuring one decision (uav_policy.insight) against it;
lockstep steps/s of sim_node <-> policy_node over ROS on their defaults
(the packaged weights) against the same loop in-process; weight-push latency; how long a hostile 200 MB
push takes to be refused, and the loop's steps/s meanwhile against before it, measured in the same run.

Run: source .venv/bin/activate && source install/setup.bash && python benchmarks/bench_policy.py
"""

from __future__ import annotations

import argparse
import array
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import private_nodes, sim_steps_reader

from uav_policy import weights as wio
from uav_policy.agent import Agent
from uav_policy.networks import NetConfig, QEnsemble, build_network
from uav_policy.rollout import Flight
from uav_sim.simulator import SimConfig, Simulator
from uav_sim.stacked_sim import StackedSim
from uav_sim.world import load_world


def inference_latency(model: str, n: int = 2000, members: int = 1) -> tuple[float, float]:
    """(p50, p99) ms of one act() at batch 1; `members` > 1: an ensemble (policy_node weights:=A,B,...)."""
    cfg = NetConfig(model=model)
    nets = [build_network(cfg, seed=i) for i in range(members)]
    agent = Agent(nets[0] if members == 1 else QEnsemble(nets), cfg)
    state = np.random.default_rng(0).uniform(0, 10, (5, 64, 64)).astype(np.float32)
    for _ in range(50):
        agent.act(state, 0.0)
    times = []
    for _ in range(n):
        t = time.perf_counter()
        agent.act(state, 0.0)
        times.append(time.perf_counter() - t)
    return float(np.percentile(times, 50) * 1e3), float(np.percentile(times, 99) * 1e3)


def insight_cost(model: str, members: int, n: int = 200) -> float:
    """p50 ms of measuring one decision (uav_policy.insight: the explanation, Grad-CAM for the CNN, and the
    deletion test's five masked forward passes), what policy_node spends on every insight_every-th frame."""
    from uav_policy.insight import Insight, explanation

    cfg = NetConfig(model=model)
    nets = [build_network(cfg, seed=i) for i in range(members)]
    net = nets[0] if members == 1 else QEnsemble(nets)
    state = np.random.default_rng(0).uniform(0, 10, (5, 64, 64)).astype(np.float32)
    insight, times = Insight(net.grid_hw), []
    with torch.no_grad():
        q, w = net(torch.from_numpy(state)[None])
    action, w = int(q.argmax()), None if w is None else w[0].numpy()
    for _ in range(n):
        t = time.perf_counter()
        insight.observe(net, state, action, explanation(net, state, action, w))
        times.append(time.perf_counter() - t)
    return float(np.percentile(times, 50) * 1e3)


def in_process_loop(model: str, steps: int) -> float:
    """Steps/s of the loop policy_node and sim_node fly on their defaults (the packaged weights, ten
    networks as one when packaged so; sim_node's default camera), without ROS."""
    packaged = wio.packaged_weights(model)
    net = wio.load_files(packaged, model) if packaged else build_network(NetConfig(model=model), seed=0)
    agent = Agent(net, net.cfg)
    sim = Simulator(load_world("basic"), SimConfig())
    flight = Flight(StackedSim(sim, net.cfg.frames, input_hw=(net.cfg.height, net.cfg.width)), agent)
    t0 = time.perf_counter()
    for _ in range(steps):
        flight.step(0.0)
    rate = steps / (time.perf_counter() - t0)
    sim.close()
    return rate


def ros_loop_and_pushes(model: str, seconds: float, pushes: int, domain: int) -> tuple[float, list[float], int, float, float]:
    """(lockstep steps/s over ROS, push latencies in ms, the blob's size, seconds until a 200 MB push is refused,
    the steps/s while it was)."""
    import rclpy

    from uav_common import contract
    from uav_policy.push import PushService, load_key, push_request, write_key

    nodes = private_nodes(domain)
    key_dir = tempfile.TemporaryDirectory()
    key_file = write_key(Path(key_dir.name) / "push.key")
    key = load_key(key_file)
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bench_policy")
    try:
        read = sim_steps_reader(node)
        nodes.start("sim", "uav_sim", "sim_node", [])
        pushes_args = [
            "-p",
            "accept_pushes:=true",
            "-p",
            f"push_key_file:={key_file}",
            "-p",
            "safety:=false",
            "-p",
            "shield:=never",
        ]
        nodes.start("policy", "uav_policy", "policy_node", ["-p", f"model:={model}", *pushes_args])
        end = time.perf_counter() + 60
        while read()[1] is None or read()[1] < 50:
            rclpy.spin_once(node, timeout_sec=0.1)
            if time.perf_counter() > end:
                raise RuntimeError("the sim <-> policy loop did not start")
        t0, s0 = read()
        while read()[0] - t0 < seconds:
            rclpy.spin_once(node, timeout_sec=0.1)
        t1, s1 = read()
        rate = (s1 - s0) / (t1 - t0)
        cfg = NetConfig(model=model)
        blob = wio.to_bytes(build_network(cfg, seed=1), cfg)
        client = node.create_client(PushService, contract.PUSH_WEIGHTS_SERVICE)
        client.wait_for_service(timeout_sec=10)
        lat = []
        for i in range(pushes):
            t = time.perf_counter()
            fut = client.call_async(push_request(blob, key=key, seq=i + 1))
            rclpy.spin_until_future_complete(node, fut, timeout_sec=10)
            assert fut.result().success, fut.result().message
            lat.append((time.perf_counter() - t) * 1e3)
        # A hostile push of 200 MB: refused by its length once rclpy has handed the array over.
        huge = PushService.Request(weights=array.array("B", bytes(200 << 20)))
        t0, s0 = read()
        t = time.perf_counter()
        fut = client.call_async(huge)
        rclpy.spin_until_future_complete(node, fut, timeout_sec=120)
        refused = time.perf_counter() - t
        assert fut.result() is not None and not fut.result().success, "the 200 MB push was not refused"
        while read()[0] - t0 < max(refused, 1.0):
            rclpy.spin_once(node, timeout_sec=0.1)
        t1, s1 = read()
        return rate, lat, len(blob), refused, (s1 - s0) / (t1 - t0)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        nodes.stop_all()
        key_dir.cleanup()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=1500, help="in-process loop steps")
    ap.add_argument("--seconds", type=float, default=8.0, help="ROS loop measuring time")
    ap.add_argument("--pushes", type=int, default=10)
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread, {os.cpu_count()} cores")
    for model in ("sam", "cnn"):
        p50, p99 = inference_latency(model)
        print(f"[{model}] inference batch 1: p50 {p50:.3f} ms, p99 {p99:.3f} ms")
        for k in (3, 10):  # ensembles of k networks (policy_node weights:=A,B,...): cost against one
            e50, e99 = inference_latency(model, n=500, members=k)
            print(f"[{model}] ensemble of {k}: p50 {e50:.3f} ms ({e50 / p50:.1f}x one network), p99 {e99:.3f} ms")
        for k in (1, 10):
            cost = insight_cost(model, k, n=200 if k == 1 else 50)
            print(
                f"[{model}] measuring one decision (insight), {k} network(s): p50 {cost:.2f} ms ({cost / p50:.1f}x one inference)"
            )
    for i, model in enumerate(("sam", "cnn")):
        base = in_process_loop(model, a.steps)
        ros, lat, size, refused, during = ros_loop_and_pushes(model, a.seconds, a.pushes, 80 + (os.getpid() + i) % 10)
        print(f"[{model}] lockstep loop: in-process {base:.1f} steps/s, over ROS {ros:.1f} steps/s, ratio {ros / base:.3f}")
        print(
            f"[{model}] weight push ({size / 1024:.0f} KiB): p50 {float(np.percentile(lat, 50)):.1f} ms, max {max(lat):.1f} ms "
            f"({len(lat)} pushes); a 200 MB push refused after {refused:.2f} s, the loop at {during:.1f} steps/s meanwhile "
            f"({during / ros:.2f}x)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
