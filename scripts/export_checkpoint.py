"""Write the networks of trainer checkpoints as policy weights files, to fly or evaluate them.

    python scripts/export_checkpoint.py runs/sam_seed0/checkpoints/ckpt-*

A run keeps its last three checkpoints (one every 1000 updates, checkpoint_interval_updates, and
one at the end of training); each holds the online and target networks (and the weight average
when the run kept one). For every checkpoint given this writes policy_<model>_step<N>.safetensors
(N: the checkpoint's environment steps; with `--net target` or `ema` the name ends in _target /
_ema) into the run's folder, or `--out-dir`. The camera and reward window recorded in the files
are taken from the run's own policy_<model>.safetensors when it exists, else from the options.
Nothing is unpickled; the tensors are checked as any weights file is. Exit code 2 names a
checkpoint that cannot be exported.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src" / p) for p in ("uav_sim", "uav_policy", "uav_trainer")]

from uav_policy import weights as wio  # noqa: E402
from uav_trainer import checkpoint  # noqa: E402


def out_name(meta: dict, net: str) -> str:
    """policy_<model>_step<N>[_<net>].safetensors for a checkpoint's meta.json."""
    model, steps = meta["net_config"]["model"], int(meta["counters"]["env_steps"])
    return f"policy_{model}_step{steps}" + ("" if net == "online" else f"_{net}") + ".safetensors"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", type=Path, help="checkpoint folders (ckpt-<updates>-<steps>)")
    ap.add_argument("--net", choices=checkpoint.NETS, default="online")
    ap.add_argument("--out-dir", type=Path, default=None, help="default: the run's folder (above checkpoints/)")
    ap.add_argument("--camera-hfov-deg", type=float, default=None, help="when the run's weights file does not say")
    ap.add_argument("--reward-window-fraction", type=float, default=None, help="when the run's weights file does not say")
    a = ap.parse_args(argv)
    for ckpt in a.checkpoints:
        run = Path(os.path.relpath(ckpt.resolve().parent.parent))  # printed as given: runs/X, not /abs/runs/X
        try:
            meta, _ = checkpoint.read_meta(ckpt)
            own = run / f"policy_{meta['net_config']['model']}.safetensors"
            camera, window = a.camera_hfov_deg, a.reward_window_fraction
            if own.is_file():
                camera = wio.read_file_camera(own) if camera is None else camera
                window = wio.read_file_window(own) if window is None else window
            out = (a.out_dir or run) / out_name(meta, a.net)
            out.parent.mkdir(parents=True, exist_ok=True)
            cfg = checkpoint.export_weights(ckpt, out, a.net, camera, window)
        except (OSError, KeyError, TypeError, ValueError) as e:
            print(f"export_checkpoint: {ckpt}: {e}", file=sys.stderr)
            return 2
        cam = "camera not recorded" if camera is None else f"camera {camera:g} deg"
        print(f"{out}: {a.net} network of {ckpt.name} ({cfg.model}, {cam})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
