"""attention_figures: pictures of what the agent attends to, made with the node's own overlay code.

    ros2 run uav_eval attention_figures --model sam --weights W --worlds basic turbulent --out runs/figures
    ros2 run uav_eval attention_figures --bag runs/bags/flight1        # what was flown and recorded

Writes attention_<world>.png (depth frames and their attention overlays at representative
steps, like the paper's attention figure; saliency_<world>.png for the CNN: its Grad-CAM) and
flight_<world>.gif (an exploit-only flight). The maps are on the nodes' absolute scale. With
--bag, the same two pictures (attention_<bag>.png, flight_<bag>.gif) of a flight recorded with
`record` (or `fly --record`, `evaluate --record`): its depth frames, attention maps, actions and
collisions, joined by stamp.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from uav_common.actions import PAPER_ACTIONS
from uav_policy import weights as wio
from uav_policy.agent import Agent
from uav_policy.attention import OVERLAY_MIN_PX, attention_map, colourise_depth, overlay
from uav_policy.insight import explanation
from uav_policy.networks import build_network
from uav_policy.rollout import Flight


def fly(model: str, files: list[str], world: str, steps: int, seed: int = 0):
    """Frames of an exploit-only flight of `files` (several: one policy on their mean Q-values; none: a
    seeded random initialisation): (depth, map of what the decision looks at (SAM's attention, the CNN's
    saliency), action index, collided)."""
    from uav_sim.sensor import TRAINING_SCALE, preset_for_camera
    from uav_sim.simulator import SimConfig, Simulator
    from uav_sim.world import load_world

    net = wio.load_files(files, model) if files else build_network(wio.config_for(model, None), seed=seed)
    cfg = net.cfg
    agent = Agent(net, cfg, seed=seed)
    # The camera the weights were trained with (their header; behind a sensor preset of that field of view, the
    # preset), else the simulator's default; an ideal camera's image at the network's input size.
    camera = wio.camera_for(files[0] if files else None, wio.UNRECORDED_HFOV_DEG)
    sensor = preset_for_camera(camera)
    scale = TRAINING_SCALE if sensor != "ideal" else 1.0
    sim_cfg = SimConfig(
        seed=seed, hfov_deg=camera, image_width=cfg.width, image_height=cfg.height, sensor=sensor, sensor_scale=scale
    )
    sim = Simulator(load_world(world), sim_cfg)
    from uav_sim.stacked_sim import StackedSim

    flight = Flight(
        StackedSim(sim, cfg.frames, input_hw=(cfg.height, cfg.width), trained_hfov_deg=camera, map_grid=cfg.map_grid), agent
    )
    out = []
    try:
        for _ in range(steps):
            state = flight.env.state
            s = flight.step(0.0)
            rows = explanation(net, state, s.action, s.attention)
            view = flight.env.to_input.view if flight.env.to_input is not None else None
            amap = attention_map(rows, net.grid_hw, s.before.depth_m.shape, view)
            out.append((s.before.depth_m, amap, s.action, s.before.collided))
    finally:
        sim.close()
    return out


def frames_from_bag(path: Path, namespace: str = ""):
    """The frames of a recorded flight as `fly` gives them: (depth, attention or saliency map or None, action index
    or None, collided), joined by header stamp over NAMESPACE/depth/image_raw, attention (saliency), action and
    step_outcome. ValueError names what the bag lacks."""
    from rosbags.highlevel import AnyReader

    from uav_common import contract
    from uav_common.actions import match_action

    folder = path.parent if path.is_file() else path
    ns = namespace.rstrip("/")
    names = {f"{ns}/{t}": t for t in ("depth/image_raw", "attention", "saliency", "action", "step_outcome")}
    by_stamp: dict[int, dict] = {}
    with AnyReader([folder]) as reader:
        conns = [c for c in reader.connections if c.topic in names]
        if not any(names[c.topic] == "depth/image_raw" for c in conns):
            found = sorted({c.topic for c in reader.connections})
            raise ValueError(f"{folder} has no {ns}/depth/image_raw (topics: {' '.join(found)}); --namespace?")
        for conn, _t, raw in reader.messages(connections=conns):
            # Converted as read: only the arrays the pictures need are kept.
            msg, topic = reader.deserialize(raw, conn.msgtype), names[conn.topic]
            if topic in ("depth/image_raw", "attention", "saliency"):
                value = contract.image_to_depth(msg)
            elif topic == "action":
                value = (float(msg.twist.linear.x), float(msg.twist.angular.z))
            else:
                value = contract.outcome_collided(msg)
            by_stamp.setdefault(contract.stamp_ns(msg.header.stamp), {})[topic] = value
    stamps = sorted(s for s, got in by_stamp.items() if "depth/image_raw" in got)
    step_s = float(np.median(np.diff(stamps))) / 1e9 if len(stamps) > 1 else 0.5
    frames = []
    for s in stamps:
        got = by_stamp[s]
        act = got.get("action")
        action = match_action(PAPER_ACTIONS, act[0], act[1], step_s) if act else None
        amap = got.get("attention", got.get("saliency"))  # a SAM's attention, a CNN's saliency
        frames.append((got["depth/image_raw"], amap, action, got.get("step_outcome", False)))
    return frames


def action_label(action: int | None) -> str:
    return PAPER_ACTIONS[action].name.split("_", 1)[0] if action is not None else "-"


def representative(frames, k: int) -> list[int]:
    """k steps spread over the flight, preferring frames with something near in view."""
    nearest = np.array([np.nanmin(np.where(np.isfinite(f[0]), f[0], 10.0)) for f in frames])
    chunks = np.array_split(np.arange(len(frames)), k)
    return [int(c[np.argmin(nearest[c])]) for c in chunks if len(c)]


def grid_png(frames, picks, path: Path, title: str, max_range_m: float = 10.0, kind: str = "attention") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(picks), figsize=(2.2 * len(picks), 4.8), squeeze=False)
    for col, i in enumerate(picks):
        depth, amap, action, _ = frames[i]
        axes[0, col].imshow(colourise_depth(depth, max_range_m))
        axes[0, col].set_title(f"step {i}\n{action_label(action)}", fontsize=8)
        axes[1, col].imshow(picture(depth, amap, max_range_m, kind))
        for ax in axes[:, col]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_ylabel("depth (near = bright)", fontsize=8)
    axes[1, 0].set_ylabel(f"{kind} (green)", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def picture(depth, amap, max_range_m: float, kind: str, label: str = "") -> np.ndarray:
    """The node's overlay (absolute scale, legend), or the depth alone at the overlay's size when there is no map."""
    if amap is not None:
        return overlay(depth, amap, max_range_m, label, kind)
    k = max(1, -(-OVERLAY_MIN_PX // min(depth.shape)))
    return np.kron(colourise_depth(depth, max_range_m), np.ones((k, k, 1), np.uint8))


def flight_gif(frames, path: Path, max_range_m: float = 10.0, every: int = 1, limit: int = 100, kind: str = "attention") -> None:
    from PIL import Image, ImageDraw

    images = []
    for i, (depth, amap, action, collided) in enumerate(frames[: limit * every : every]):
        im = Image.fromarray(picture(depth, amap, max_range_m, kind))
        draw = ImageDraw.Draw(im)
        draw.text((4, 4), f"step {i * every} {action_label(action)}", fill=(255, 255, 0))
        if collided:
            draw.text((4, 16), "collision: back at start", fill=(255, 60, 60))
        images.append(im)
    images[0].save(path, save_all=True, append_images=images[1:], duration=120, loop=0, optimize=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="attention_figures", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--model", choices=("sam", "cnn"), default="sam")
    ap.add_argument(
        "--weights",
        default="",
        help="safetensors weights file, or files a,b,c flown as one on their mean Q-values (default: the packaged "
        "files, else a random initialisation)",
    )
    ap.add_argument("--worlds", nargs="+", default=["basic", "turbulent"])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--panels", type=int, default=6)
    ap.add_argument("--out", default="runs/figures", help="output folder (default: runs/figures)")
    ap.add_argument("--bag", default="", help="pictures of a recorded flight (a bag folder) instead of flying")
    ap.add_argument("--namespace", default="", help="with --bag: the vehicle's namespace in the bag, e.g. /uav1")
    a = ap.parse_args(argv)
    if a.bag:
        return figures_from_bag(Path(a.bag), a.namespace, Path(a.out), a.panels)
    if a.weights:
        files = [f for f in a.weights.split(",") if f]
    else:
        files = [str(p) for p in wio.packaged_weights(a.model)]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for world in a.worlds:
        frames = fly(a.model, files, world, a.steps)
        picks = representative(frames, a.panels)
        kind = "attention" if a.model == "sam" else "saliency"
        png = out / f"{kind}_{world}.png"
        grid_png(frames, picks, png, f"D3QN-{a.model.upper()} in {world}: depth (top) and {kind} (bottom)", kind=kind)
        gif = out / f"flight_{world}.gif"
        flight_gif(frames, gif, kind=kind)
        print(f"written: {png} {gif}")
    return 0


def lost_in_bag(bag: Path) -> dict[str, int]:
    """{topic: messages lost to the recorder} that a bag's metadata records (uav_bringup.record); {} when none were or
    the bag does not say."""
    import yaml

    from uav_common import contract

    folder = bag.parent if bag.is_file() else bag
    try:
        meta = yaml.safe_load((folder / "metadata.yaml").read_text()) or {}
        custom = meta.get("rosbag2_bagfile_information", {}).get("custom_data") or {}
        lost = {k[len(contract.LOST_KEY) :]: int(v) for k, v in custom.items() if k.startswith(contract.LOST_KEY)}
    except (OSError, yaml.YAMLError, AttributeError, ValueError):
        return {}
    return {t: n for t, n in lost.items() if n}


def figures_from_bag(bag: Path, namespace: str, out: Path, panels: int) -> int:
    if not bag.exists():
        print(f"attention_figures: --bag {bag}: no such bag", file=sys.stderr)
        return 2
    try:
        frames = frames_from_bag(bag, namespace)
    except ValueError as e:
        print(f"attention_figures: --bag {bag}: {e}", file=sys.stderr)
        return 2
    if not frames:
        print(f"attention_figures: --bag {bag}: no depth frames recorded", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    name = (bag.parent if bag.is_file() else bag).name
    png, gif = out / f"attention_{name}.png", out / f"flight_{name}.gif"
    with_attention = sum(f[1] is not None for f in frames)
    grid_png(frames, representative(frames, panels), png, f"{name}: depth (top) and attention (bottom), recorded")
    flight_gif(frames, gif)
    print(f"written: {png} {gif} ({len(frames)} frames, {with_attention} with attention)")
    lost = lost_in_bag(bag)
    if lost:
        each = ", ".join(f"{t} {n}" for t, n in lost.items())
        print(f"the recorder lost {sum(lost.values())} message(s) of this flight ({each}): frames may lack their answer")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
