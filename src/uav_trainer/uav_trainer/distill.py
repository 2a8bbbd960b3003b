"""distill: one network that acts as an ensemble does (policy distillation, DAgger; no ROS).

    distill --ensemble runs/sam_seed0/policy_sam_step*.safetensors runs/sam_seed0/policy_sam.safetensors \\
        --recipe shipped --out runs/distilled/policy_sam.safetensors

The ensemble (a run's ten files, say) flies as one policy on the mean of their Q-values, as policy_node flies them.
The student is one network of the same architecture, started from the last file of the ensemble (or from scratch,
`--init random`), and trained to give the ensemble's Q-values on the states the policy actually meets:

- the first DAgger round flies the ensemble, the next ones the student, each with exploration `--epsilon`, over the training
  worlds of the recipe the ensemble was trained with (its sim_node section: worlds, camera, sensor);
- every state visited is labelled with the ensemble's Q-values and joins the data set (DAgger, Ross et al. 2011);
- after each round the student fits the whole data set: squared error on the Q-values' differences between
  actions (the greedy action and its leads), a little on their mean (q_loss).

The student's agreement with the ensemble's greedy action on each round's fresh states (before it trains on them)
is printed: the share of the states the policy meets where student and ensemble act alike. The file written names
its ensemble (file names and SHA-256) in its header, with their camera and reward window. Seeded: the same
ensemble, recipe and seed give the same student, byte for byte.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

FRAMES_DTYPE = np.float16  # stored states: half the memory; depth in metres needs no more


def ensemble_notes(files: list[str]) -> dict[str, str]:
    from uav_policy.weights import DISTILLED_KEY

    return {
        DISTILLED_KEY: json.dumps(
            [{"file": Path(f).name, "sha256": hashlib.sha256(Path(f).read_bytes()).hexdigest()} for f in files]
        )
    }


def load_ensemble(files: list[str], model: str | None):
    """(the ensemble's network, its config, camera, reward window); ValueError when the files mix architectures, cameras
    or reward windows, or are not of `model`."""
    from uav_policy import weights as wio
    from uav_sim.reward import CENTER_WINDOW_FRACTION

    configs = {wio.read_file_config(f) for f in files}
    if len(configs) != 1:
        models = sorted({c.model for c in configs})
        raise ValueError(
            f"an ensemble of mixed architectures ({', '.join(models)}; {len(configs)} configurations): give one model's files"
        )
    cfg = configs.pop()
    if model is not None and cfg.model != model:
        raise ValueError(f"the ensemble's files are {cfg.model} networks, not {model}")
    cameras = {wio.read_file_camera(f) for f in files}
    if len(cameras) != 1:
        raise ValueError(f"an ensemble trained behind different cameras ({sorted(map(str, cameras))}): give one camera's files")
    net, cfg, hfov, window = wio.load_policy(cfg.model, files, None, None, CENTER_WINDOW_FRACTION)
    return net.eval(), cfg, hfov, window


@torch.no_grad()
def q_of(net, states: np.ndarray, batch: int = 256) -> np.ndarray:
    out = []
    for i in range(0, len(states), batch):
        x = torch.from_numpy(states[i : i + batch].astype(np.float32))
        out.append(net(x)[0].numpy())
    return np.concatenate(out) if out else np.zeros((0, 0), np.float32)


VALUE_WEIGHT = 0.01  # the loss on the mean Q (the state's value) against that on the actions' differences


def q_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Squared error on the actions' Q-values about their mean (what decides, and by how much), plus a small
    weight on the mean itself: the members' values differ by more than their actions' differences (one run's
    snapshots: by 16 where the actions differ by 5), and a plain squared error spent the fit on the value."""
    qm, tm = q.mean(dim=1, keepdim=True), target.mean(dim=1, keepdim=True)
    return torch.nn.functional.mse_loss(q - qm, target - tm) + VALUE_WEIGHT * torch.nn.functional.mse_loss(qm, tm)


def fit(student, states: np.ndarray, targets: np.ndarray, epochs: int, batch: int, lr: float, rng) -> float:
    """Fit the student's Q-values to `targets` (q_loss, Adam); the last epoch's mean loss."""
    opt = torch.optim.Adam(student.parameters(), lr=lr)
    student.train()
    loss_sum = 0.0
    for _ in range(epochs):
        order = rng.permutation(len(states))
        loss_sum, n = 0.0, 0
        for i in range(0, len(order), batch):
            idx = order[i : i + batch]
            x = torch.from_numpy(states[idx].astype(np.float32))
            q, _ = student(x)
            loss = q_loss(q, torch.from_numpy(targets[idx]))
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss_sum, n = loss_sum + loss.item() * len(idx), n + len(idx)
        loss_sum /= max(n, 1)
    student.eval()
    return loss_sum


def agreement(student, ensemble_q: np.ndarray, states: np.ndarray) -> float:
    """The share of `states` on which the student's greedy action is the ensemble's."""
    return float((q_of(student, states).argmax(1) == ensemble_q.argmax(1)).mean()) if len(states) else float("nan")


def collect(env, actor, steps: int, epsilon: float, rng, frames: int, hw, desc: str = "") -> np.ndarray:
    """`steps` states met flying `actor` (a network) with exploration `epsilon`, as stored states (a progress bar on a
    terminal)."""
    from tqdm import tqdm

    out = np.empty((steps, frames, *hw), FRAMES_DTYPE)
    for i in tqdm(range(steps), desc=desc, unit="step", disable=None, leave=False):
        out[i] = env.state
        if rng.random() < epsilon:
            action = int(rng.integers(len(env.actions)))
        else:
            with torch.no_grad():
                q, _ = actor(torch.from_numpy(np.ascontiguousarray(env.state, dtype=np.float32))[None])
            action = int(q[0].argmax())
        env.step(action)
    return out


@dataclasses.dataclass(frozen=True)
class Schedule:
    """How a distillation runs: DAgger rounds, states met per round, passes over the data set after each, exploration
    while collecting, the optimiser's step and batch, where the student starts (the ensemble's `last` file or `random`), seed."""

    rounds: int = 4
    steps_per_round: int = 2500
    epochs: int = 3
    epsilon: float = 0.1
    lr: float = 1e-4
    batch: int = 64
    init: str = "last"
    seed: int = 0


def distill(
    files: list[str],
    recipe_name: str,
    out: Path,
    model: str | None = None,
    how: Schedule = Schedule(),
    params_dir="params",
    log=print,
) -> dict:
    """Distil the ensemble into one network written to `out`; a summary (agreement per round, data set size)."""
    from uav_policy import weights as wio
    from uav_policy.networks import build_network
    from uav_sim.simulator import Simulator, with_sensor
    from uav_sim.stacked_sim import StackedSim

    from .inprocess import sim_settings
    from .recipes import load_recipe

    ensemble, cfg, hfov, _ = load_ensemble(files, model)
    rounds, seed = how.rounds, how.seed
    recipe = load_recipe(recipe_name, params_dir)
    sim_cfg, worlds = sim_settings(recipe.node("sim_node"), seed, cfg.width)
    sim_cfg = with_sensor(sim_cfg)
    if abs(sim_cfg.hfov_deg - (hfov if hfov is not None else sim_cfg.hfov_deg)) > 0.5:
        raise ValueError(
            f"recipe {recipe.path} flies a {sim_cfg.hfov_deg:g} deg camera, but the ensemble was trained behind {hfov:g} deg: "
            "give the recipe they were trained with"
        )
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    members = list(getattr(ensemble, "members", [ensemble]))
    student = build_network(cfg, seed=seed)
    if how.init == "last":
        student.load_state_dict(members[-1].state_dict())
    first, layouts = worlds.load(seed)
    sim = Simulator(first, sim_cfg, next_worlds=layouts)
    hw = (cfg.height, cfg.width)
    env = StackedSim(sim, cfg.frames, input_hw=hw, trained_hfov_deg=hfov, map_grid=cfg.map_grid)
    states = np.empty((0, cfg.channels, *hw), FRAMES_DTYPE)
    targets = np.empty((0, cfg.actions), np.float32)
    summary = {"rounds": [], "ensemble": len(files)}
    t0 = time.monotonic()
    try:
        for r in range(rounds):
            actor = ensemble if r == 0 else student
            fresh = collect(env, actor, how.steps_per_round, how.epsilon, rng, cfg.channels, hw, f"round {r + 1}/{rounds}")
            labels = q_of(ensemble, fresh).astype(np.float32)
            agree = agreement(student, labels, fresh)
            states, targets = np.concatenate([states, fresh]), np.concatenate([targets, labels])
            loss = fit(student, states, targets, how.epochs, how.batch, how.lr, rng)
            after = agreement(student, labels, fresh)
            summary["rounds"].append({"flown_by": "ensemble" if r == 0 else "student", "agreement_before": agree, "after": after})
            log(
                f"round {r + 1}/{rounds} ({'the ensemble' if r == 0 else 'student'} flying, {len(states)} states, "
                f"{time.monotonic() - t0:.0f} s): agreement with the ensemble on the new states {100 * agree:.1f} % "
                f"before fitting, {100 * after:.1f} % after; loss {loss:.4f}"
            )
    finally:
        sim.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    wio.save_file(student, cfg, out, hfov, wio.read_file_window(files[0]), notes=ensemble_notes(files))  # the ensemble's own
    summary["states"] = len(states)
    return summary


def main(argv=None) -> int:
    from uav_policy.weights import WeightsError

    ap = argparse.ArgumentParser(prog="distill", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ensemble", nargs="+", required=True, help="the ensemble's weights files (one model, one camera)")
    ap.add_argument("--model", choices=("sam", "cnn"), default=None, help="check the ensemble's files are of this model")
    ap.add_argument("--recipe", required=True, help="the recipe the ensemble was trained with (its worlds and camera)")
    ap.add_argument("--params-dir", default="params", help="folder with recipes/ (default: params)")
    ap.add_argument("--out", required=True, help="the student's weights file")
    ap.add_argument("--rounds", type=int, default=4, help="DAgger rounds (default 4: the ensemble flies the first)")
    ap.add_argument("--steps-per-round", type=int, default=2500, help="states met per round (default 2500)")
    ap.add_argument("--epochs", type=int, default=3, help="passes over the data set after each round (default 3)")
    ap.add_argument("--epsilon", type=float, default=0.1, help="exploration while collecting (default 0.1)")
    ap.add_argument("--init", choices=("last", "random"), default="last", help="start from the last file of the ensemble or anew")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    a = ap.parse_args(argv)
    if a.rounds < 1 or a.steps_per_round < 1 or a.epochs < 1:
        ap.error("--rounds, --steps-per-round and --epochs must be >= 1")
    if not 0.0 <= a.epsilon <= 1.0:
        ap.error("--epsilon must lie in [0, 1]")
    if Path(a.out).resolve() in {Path(f).resolve() for f in a.ensemble}:
        ap.error("--out must not be one of the ensemble's files")
    torch.set_num_threads(a.threads)
    try:
        how = Schedule(a.rounds, a.steps_per_round, a.epochs, a.epsilon, init=a.init, seed=a.seed)
        summary = distill(a.ensemble, a.recipe, Path(a.out), a.model, how, a.params_dir)
    except (ValueError, OSError, WeightsError) as e:
        ap.error(str(e))
    last = summary["rounds"][-1]
    print(
        f"student: {a.out} (one network for {summary['ensemble']} ensemble files, {summary['states']} states); it acts as the "
        f"ensemble on {100 * last['agreement_before']:.1f} % of the states it meets itself"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
