"""Does the explanation follow the obstacle? A counterfactual test (no ROS).

The vehicle hovers in an otherwise empty room (its walls beyond the camera's range) and one scene at a time an
obstacle is placed in front of it: pillars, boxes and wall segments at several bearings and distances, and pairs of
pillars at different distances. Every scene is rendered behind the camera the weights were trained with and mapped
onto the network's input as policy_node maps a camera's frames; the state is five copies of that frame (a hovering
vehicle). Per scene:

- `ratio`: the explanation's mass on the obstacle's pixels over their share of the image (1 = no preference); with
  two obstacles, on the nearer one;
- `hit`: the node whose mass grew most against the empty room's map sees the obstacle;
- `reason_ratio`, `reason_top`: the same mass ratio on what the privileged planner's decision from the hovering pose is
  about (its reason, docs/INSIGHT.md: an obstacle the camera shows that bounds the clearance of the plan kept or rules
  out an action), and whether the map's top node sees it; only in scenes where the decision has a reason in view.

The obstacle's pixels are those the obstacle makes nearer in the exact depth (no sensor noise), so no labelling
is needed. SAM is explained by the attention its decision uses, the CNN by Grad-CAM (uav_policy.insight).

The sanity check (Adebayo et al. 2018, cascading randomisation): the network's layers are re-initialised from the
output down to the input, one group at a time, and each time the maps are measured again; an explanation that
depends on what the network learnt changes (its rank correlation with the trained network's map falls).

    grounding --model sam --model cnn --out runs/grounding     # the packaged policies
    grounding --model sam --weights A.safetensors B.safetensors --sanity
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import torch

from uav_policy.insight import explanation, increase_on
from uav_policy.map_checks import reason_measures
from uav_policy.masking import mass_ratio, received

ROOM_M = 26.0  # the empty room's side: its walls stand beyond the 10 m range from its centre
START = (0.0, 0.0, 1.0)
OBSTACLE_HEIGHT_M = 3.0
CLOSER_M = 0.05  # a pixel is the obstacle's when the obstacle brings it this much nearer


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    kind: str  # pillar | box | wall | pair
    obstacles: tuple  # uav_sim.world.Obstacle, the measured one first


def _at(bearing_deg: float, distance_m: float) -> tuple[float, float]:
    """The point `distance_m` ahead at `bearing_deg` (positive = left, REP 103) of the vehicle at START facing +x."""
    b = math.radians(bearing_deg)
    return START[0] + distance_m * math.cos(b), START[1] + distance_m * math.sin(b)


def scenes(hfov_deg: float) -> list[Scene]:
    """The scene set; bearings are spread over the inner 70 % of the camera's field of view."""
    from uav_sim.world import Obstacle

    half = 0.35 * hfov_deg
    bearings = [round(b, 1) for b in np.linspace(-half, half, 5)]
    out = []
    for d in (1.5, 2.5, 4.0):
        for b in bearings:
            x, y = _at(b, d)
            out.append(
                Scene(f"pillar {b:+g} deg {d:g} m", "pillar", (Obstacle("cylinder", x, y, OBSTACLE_HEIGHT_M, radius_m=0.2),))
            )
    for d in (2.0, 3.5):
        for b in bearings[::2]:
            x, y = _at(b, d)
            out.append(Scene(f"box {b:+g} deg {d:g} m", "box", (Obstacle("box", x, y, OBSTACLE_HEIGHT_M, 0.8, 0.8, yaw_deg=b),)))
    for b in bearings[::2]:
        x, y = _at(b, 3.0)  # a 2.5 m wall segment facing the vehicle
        out.append(Scene(f"wall {b:+g} deg 3 m", "wall", (Obstacle("box", x, y, OBSTACLE_HEIGHT_M, 0.2, 2.5, yaw_deg=b),)))
    for side in (1, -1):
        near, far = _at(side * bearings[3], 1.5), _at(-side * bearings[3], 4.0)
        out.append(
            Scene(
                f"pair: near {side * bearings[3]:+g} deg 1.5 m, far {-side * bearings[3]:+g} deg 4 m",
                "pair",
                (
                    Obstacle("cylinder", *near, OBSTACLE_HEIGHT_M, radius_m=0.2),
                    Obstacle("cylinder", *far, OBSTACLE_HEIGHT_M, radius_m=0.2),
                ),
            )
        )
    return out


@dataclasses.dataclass(frozen=True)
class Frame:
    state: np.ndarray  # (frames, H, W) on the network's input, as measured
    exact: np.ndarray  # (H, W) the exact depth on the network's input
    only_first: np.ndarray | None = None  # with several obstacles: the exact depth with the measured one alone
    reason: np.ndarray | None = None  # the pixels of the planner's reason on the input (None: nothing bounds it)


def _world(obstacles):
    from uav_sim.world import Weather, World

    return World("grounding", ROOM_M, ROOM_M, OBSTACLE_HEIGHT_M, START, 0.0, tuple(obstacles), Weather())


def render(obstacles, sim_cfg, frames: int, input_hw: tuple[int, int], hfov_deg: float) -> Frame:
    """The hovering vehicle's state in the empty room with `obstacles`, and the exact depth on the input."""
    from uav_sim.planner import SimPlanner
    from uav_sim.simulator import Simulator
    from uav_sim.stacked_sim import StackedSim

    from .flights import reason_pixels

    def exact(obs):
        sim = Simulator(_world(obs), sim_cfg)
        try:
            env = StackedSim(sim, frames, input_hw=input_hw, trained_hfov_deg=hfov_deg)
            mapped = env.to_input(sim.render()) if env.to_input is not None else sim.render()
            reason = reason_pixels(SimPlanner(sim), env)  # the planner knowing what the frames show: the scene
            return env.state.copy(), np.asarray(mapped, np.float32), reason
        finally:
            sim.close()

    state, depth, reason = exact(obstacles)
    alone = exact(obstacles[:1])[1] if len(obstacles) > 1 else None
    return Frame(state, depth, alone, reason)


def obstacle_mask(frame: Frame, empty: Frame) -> np.ndarray:
    """The pixels the measured obstacle brings nearer than the empty room."""
    scene = frame.only_first if frame.only_first is not None else frame.exact
    return _finite(scene) < _finite(empty.exact) - CLOSER_M


def _finite(depth: np.ndarray) -> np.ndarray:
    return np.nan_to_num(depth, nan=1e6, posinf=1e6)


@torch.no_grad()
def explain(net, state: np.ndarray) -> tuple[int, np.ndarray]:
    """The greedy action on `state` and its explanation as one distribution over the nodes."""
    x = torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)).unsqueeze(0)
    q, w = net(x)
    action = int(q[0].argmax())
    rows = explanation(net, state, action, None if w is None else w[0].cpu().numpy())
    return action, received(rows)


@dataclasses.dataclass
class SceneResult:
    scene: str
    kind: str
    obstacle_share: float  # the obstacle's share of the image
    ratio: float  # the explanation's mass on it over that share
    hit: bool  # the largest increase over the empty room lies on it
    action: int
    reason_ratio: float = math.nan  # the mass on the planner's reason over its share (nan: no reason in view)
    reason_top: float = math.nan  # 1 when the map's top node sees the reason, 0 when not, nan: no reason in view


def measure(net, scene_frames: list[tuple[Scene, Frame]], empty: Frame) -> list[SceneResult]:
    grid = net.grid_hw
    _, base = explain(net, empty.state)
    out = []
    for scene, frame in scene_frames:
        mask = obstacle_mask(frame, empty)
        action, dist = explain(net, frame.state)
        ratio = mass_ratio(dist, mask, grid)
        on_reason = reason_measures(dist, frame.reason, grid) if frame.reason is not None else None
        out.append(
            SceneResult(
                scene.name,
                scene.kind,
                float(mask.mean()),
                math.nan if ratio is None else ratio,
                increase_on(dist, base, mask, grid),
                action,
                *((math.nan, math.nan) if on_reason is None else (on_reason[0], float(on_reason[1]))),
            )
        )
    return out


def summarise(results: list[SceneResult]) -> dict[str, float]:
    """The mean ratio and the share of hits over the scenes whose obstacle is in view; the mean mass on the planner's
    reason and the share of top nodes on it over the scenes with a reason in view."""
    seen = [r for r in results if r.obstacle_share > 0]
    why = [r for r in results if not math.isnan(r.reason_ratio)]
    return {
        "scenes": len(seen),
        "ratio": float(np.mean([r.ratio for r in seen])) if seen else math.nan,
        "hits": float(np.mean([r.hit for r in seen])) if seen else math.nan,
        "reason_scenes": len(why),
        "reason_mass": float(np.mean([r.reason_ratio for r in why])) if why else math.nan,
        "reason_top": float(np.mean([r.reason_top for r in why])) if why else math.nan,
    }


def table_row(s: dict[str, float]) -> str:
    """A summary's cells in grounding.md ('-' where no scene was measured)."""

    def cell(v: float, unit: str) -> str:
        return "-" if math.isnan(v) else f"{100 * v:.0f} %" if unit == "%" else f"{v:.2f}x"

    return (
        f"| {s['scenes']} | {cell(s['ratio'], 'x')} | {cell(s['hits'], '%')} "
        f"| {s['reason_scenes']} | {cell(s['reason_mass'], 'x')} | {cell(s['reason_top'], '%')} |"
    )


def layer_groups(net) -> list[tuple[str, list[torch.nn.Module]]]:
    """The network's layers from the output down to the input (an ensemble: the same layer of every member at once),
    for cascading randomisation."""
    members = list(getattr(net, "members", [net]))

    def groups(m) -> list[tuple[str, torch.nn.Module]]:
        out = []
        for name, child in m.named_children():
            if name == "trunk":
                convs = [(f"trunk.{i}", c) for i, c in enumerate(child.net) if isinstance(c, torch.nn.Conv2d)]
                out += convs
            elif isinstance(child, torch.nn.ModuleList):
                out += [(f"{name}.{i}", c) for i, c in enumerate(child)]
            elif any(True for _ in child.parameters()):
                out.append((name, child))
        return out[::-1]  # named_children runs input to output for these networks

    per_member = [groups(m) for m in members]
    return [(name, [g[i][1] for g in per_member]) for i, (name, _) in enumerate(per_member[0])]


@torch.no_grad()
def randomise(modules: list[torch.nn.Module], seed: int) -> None:
    """Re-initialise every parameter of `modules` (seeded): weights drawn normal with variance 1 / fan-in, biases
    zero, LayerNorm gains drawn normal (random signs and scales)."""
    gen = torch.Generator().manual_seed(seed)
    for module in modules:
        for name, p in module.named_parameters():
            if name.endswith("bias"):
                p.zero_()
            elif p.dim() == 1:  # a LayerNorm's gain: random signs and scales
                p.copy_(torch.randn(p.shape, generator=gen))
            else:  # fan-in: all but the output dimension (a conv's input channels x kernel)
                p.copy_(torch.randn(p.shape, generator=gen) / math.sqrt(p[0].numel()))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of two maps (1 for a constant map against anything: it cannot be told apart)."""
    ra = np.argsort(np.argsort(a)).astype(float)
    rb = np.argsort(np.argsort(b)).astype(float)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return 1.0
    return float(np.corrcoef(ra, rb)[0, 1])


@dataclasses.dataclass
class SanityRow:
    randomised: str  # the layer groups re-initialised so far, from the output down to this one
    rank_correlation: float  # mean over scenes of the map's Spearman correlation with the trained network's
    ratio: float
    hits: float


def sanity(net, scene_frames: list[tuple[Scene, Frame]], empty: Frame, seed: int = 0) -> list[SanityRow]:
    """Cascading randomisation on a copy of `net`: one row per layer group, from the output down."""
    trained = [explain(net, f.state)[1] for _, f in scene_frames]
    work = copy.deepcopy(net)
    rows = []
    for i, (name, modules) in enumerate(layer_groups(work)):
        randomise(modules, seed + i)
        maps = [explain(work, f.state)[1] for _, f in scene_frames]
        s = summarise(measure(work, scene_frames, empty))
        rho = float(np.mean([spearman(a, b) for a, b in zip(trained, maps, strict=True)]))
        rows.append(SanityRow(name, rho, s["ratio"], s["hits"]))
    return rows


def sim_config(net_cfg, hfov_deg: float, sensor: str, sensor_scale: float, seed: int = 0):
    from uav_sim.simulator import SimConfig

    return SimConfig(
        seed=seed,
        hfov_deg=hfov_deg,
        image_width=net_cfg.width,
        image_height=net_cfg.height,
        sensor=sensor,
        sensor_scale=sensor_scale,
    )


def run(
    net, hfov_deg: float, sensor: str, sensor_scale: float, log=print
) -> tuple[list[Scene], list[tuple[Scene, Frame]], Frame]:
    cfg = net.cfg
    sim_cfg = sim_config(cfg, hfov_deg, sensor, sensor_scale)
    hw = (cfg.height, cfg.width)
    empty = render((), sim_cfg, cfg.frames, hw, hfov_deg)
    listed = scenes(hfov_deg)
    frames = []
    for i, scene in enumerate(listed, 1):
        frames.append((scene, render(scene.obstacles, sim_cfg, cfg.frames, hw, hfov_deg)))
        if i % 10 == 0 or i == len(listed):
            log(f"  rendered {i}/{len(listed)} scenes")
    return listed, frames, empty


def main(argv=None) -> int:
    from uav_policy import weights as wio
    from uav_policy.weights import load_policy
    from uav_sim.reward import CENTER_WINDOW_FRACTION
    from uav_sim.sensor import TRAINING_SCALE, preset_for_camera

    from .flights import weights_or_packaged

    ap = argparse.ArgumentParser(prog="grounding", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", choices=("sam", "cnn"), help="repeatable; default: sam")
    ap.add_argument("--weights", nargs="*", default=None, help="one policy's files (one model); default: the packaged ones")
    ap.add_argument(
        "--sensor", default=None, help="sensor preset to render with (default: the one the weights' camera matches, else ideal)"
    )
    ap.add_argument(
        "--sensor-scale",
        type=float,
        default=TRAINING_SCALE,
        help=f"a preset's render scale (default {TRAINING_SCALE:g}, the recipes')",
    )
    ap.add_argument("--sanity", action="store_true", help="also run the cascading-randomisation sanity check")
    ap.add_argument("--out", default="runs/grounding", help="folder for grounding.csv, sanity.csv and grounding.md")
    a = ap.parse_args(argv)
    models = a.model or ["sam"]
    if a.weights and len(models) > 1:
        ap.error("--weights names one policy's files: give one --model with it")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "| policy | scenes | mass on the obstacle / its share | largest increase on the obstacle "
        "| scenes with a reason | mass on the reason | top node on the reason |",
        "|---|---|---|---|---|---|---|",
    ]
    rows, sanity_rows = [], []
    for model in models:
        files = list(a.weights) if a.weights else weights_or_packaged(model, "")
        if not files:
            ap.error(f"no weights given and no packaged {model} weights")
        try:
            net, _, hfov, _ = load_policy(model, files, None, None, CENTER_WINDOW_FRACTION)
        except (ValueError, OSError, wio.WeightsError) as e:
            ap.error(f"--weights: {e}")
        net.eval()
        sensor = a.sensor or preset_for_camera(hfov)
        label = f"{model} ({len(files)} file{'s' * (len(files) > 1)}, {hfov:g} deg, sensor {sensor})"
        print(f"{label}: rendering the scenes", flush=True)
        _, frames, empty = run(net, hfov, sensor, a.sensor_scale)
        results = measure(net, frames, empty)
        s = summarise(results)
        lines.append(f"| {label} " + table_row(s))
        for kind in ("pillar", "box", "wall", "pair"):
            lines.append(f"| &nbsp; {kind} " + table_row(summarise([r for r in results if r.kind == kind])))
        rows += [dict(policy=model, **dataclasses.asdict(r)) for r in results]
        print(
            f"{label}: {s['ratio']:.2f}x its share on the obstacle, largest increase on it in {100 * s['hits']:.0f} % of scenes; "
            f"{s['reason_mass']:.2f}x on the planner's reason, top node on it in {100 * s['reason_top']:.0f} % "
            f"of the {s['reason_scenes']} scenes with one"
        )
        if a.sanity:
            for r in sanity(net, frames, empty):
                sanity_rows.append(dict(policy=model, **dataclasses.asdict(r)))
                print(
                    f"  randomised down to {r.randomised:20s} rank corr {r.rank_correlation:+.2f}  "
                    f"{r.ratio:.2f}x  {100 * r.hits:.0f} %"
                )
    with open(out / "grounding.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    if sanity_rows:
        with open(out / "sanity.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(sanity_rows[0]))
            w.writeheader()
            w.writerows(sanity_rows)
    (out / "grounding.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"tables: {out}/grounding.md, grounding.csv{', sanity.csv' if sanity_rows else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
