#!/usr/bin/env python3
"""Copy trained weights files into uav_policy's packaged weights, recording their training camera.

    choose runs/sam_seed{0..4} --across-runs        # names one file, chosen on the validation worlds
    python scripts/package_weights.py runs/sam_seed2/policy_sam_step25000.safetensors --model sam

Replaces the files of src/uav_policy/weights/<model>/ with <model>_00.safetensors (and <model>_01, ... when
several files are given: policy_node flies several as one policy, acting on the mean of their Q-values;
the packaged defaults are one network each): the same tensors, with the camera field of view and the reward
window the run was trained with in the metadata. Files written before the trainers recorded the
camera lack it: give --camera-hfov-deg then. Each file is written atomically. Rebuild with colcon
afterwards so the installed package has them too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src" / p) for p in ("uav_sim", "uav_policy")]

from safetensors.torch import load_file  # noqa: E402

from uav_policy import weights as wio  # noqa: E402


def camera_of(src: str, hfov_deg: float | None) -> float:
    """The camera `src` was trained with: the one it records, else `hfov_deg` (WeightsError when they
    differ or neither says)."""
    recorded = wio.read_file_camera(src)
    if recorded is not None and hfov_deg is not None and abs(recorded - hfov_deg) > 1e-6:
        raise wio.WeightsError(f"{src} records a {recorded:g} deg camera, not {hfov_deg:g}")
    if recorded is None and hfov_deg is None:
        raise wio.WeightsError(f"{src} records no camera: give --camera-hfov-deg")
    return recorded if recorded is not None else hfov_deg


def package(src: str, model: str, camera: float, out: Path) -> str:
    """Write `src` to `out` with `camera` and its reward window; a line saying what was written."""
    cfg = wio.config_for(model, src)
    net = wio.load_file(src, cfg)
    notes = wio.read_file_notes(src)  # e.g. the ensemble a distilled network was distilled from
    wio.save_file(net, cfg, out, camera_hfov_deg=camera, reward_window_fraction=wio.read_file_window(src), notes=notes)
    before, after = load_file(src), load_file(str(out))
    if before.keys() != after.keys() or any(not before[k].equal(after[k]) for k in before):
        raise SystemExit(f"{out}: the tensors differ from {src}")
    window = wio.read_file_window(out)
    window_text = "the paper's" if window is None else f"{window:g}"
    return f"{out}: {len(after)} tensors identical to {src}, camera {camera:g} deg, reward window {window_text}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", nargs="+", help="weights files of one run, e.g. its snapshots and final weights")
    ap.add_argument("--model", choices=("sam", "cnn"), required=True)
    ap.add_argument("--camera-hfov-deg", type=float, default=None, help="the run's camera, if the files do not say")
    ap.add_argument("--out", default=None, help="folder (default: src/uav_policy/weights/<model>)")
    a = ap.parse_args(argv)
    out = Path(a.out or ROOT / "src" / "uav_policy" / "weights" / a.model)
    try:  # everything is checked before anything is replaced
        for src in a.weights:
            wio.load_file(src, wio.config_for(a.model, src))
        cameras = [camera_of(src, a.camera_hfov_deg) for src in a.weights]
    except wio.WeightsError as e:
        ap.error(str(e))
    if len(set(cameras)) != 1:
        ap.error(f"the files were trained with different cameras ({', '.join(f'{c:g}' for c in sorted(set(cameras)))} deg)")
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("*.safetensors"):
        old.unlink()
    for i, (src, camera) in enumerate(zip(a.weights, cameras, strict=True)):
        print(package(src, a.model, camera, out / f"{a.model}_{i:02d}.safetensors"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
