"""Copy a trained weights file into uav_policy's packaged weights, recording its training camera.

    python scripts/package_weights.py runs/turn_sam_seed3/policy_sam.safetensors --model sam --camera-hfov-deg 120

Writes src/uav_policy/weights/<model>.safetensors (atomically): the same tensors, with the
camera field of view the run was trained with in the metadata (files written before the trainers
recorded it lack it). Rebuild with colcon afterwards so the installed package has it too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src" / p) for p in ("uav_sim", "uav_policy")]

from safetensors.torch import load_file  # noqa: E402

from uav_policy import weights as wio  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", help="trained policy_<model>.safetensors")
    ap.add_argument("--model", choices=("sam", "cnn"), required=True)
    ap.add_argument("--camera-hfov-deg", type=float, required=True, help="the camera the run was trained with")
    ap.add_argument("--out", default=None, help="default: src/uav_policy/weights/<model>.safetensors")
    a = ap.parse_args(argv)
    try:
        recorded = wio.read_file_camera(a.weights)
        if recorded is not None and abs(recorded - a.camera_hfov_deg) > 1e-6:
            ap.error(f"{a.weights} records a {recorded:g} deg camera, not {a.camera_hfov_deg:g}")
        cfg = wio.config_for(a.model, a.weights)
        net = wio.load_file(a.weights, cfg)
        out = Path(a.out or ROOT / "src" / "uav_policy" / "weights" / f"{a.model}.safetensors")
        wio.save_file(net, cfg, out, camera_hfov_deg=a.camera_hfov_deg)
    except wio.WeightsError as e:
        ap.error(str(e))
    before, after = load_file(a.weights), load_file(str(out))
    if before.keys() != after.keys() or any(not before[k].equal(after[k]) for k in before):
        raise SystemExit(f"{out}: the tensors differ from {a.weights}")
    print(f"{out}: {len(after)} tensors identical to {a.weights}, camera {wio.read_file_camera(out):g} deg, {cfg.to_json()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
