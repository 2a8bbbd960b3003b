"""Atomic checkpoints: weights, target, Adam state, counters and RNG states; safetensors + JSON, no pickle.

Layout under `dir`: ckpt-<updates>-<steps>/{state.safetensors, meta.json}, a `latest` file naming the
newest complete one, and replay/: the replay memory's journal. The memory is large (8 KiB per 64 x 64
frame), so a checkpoint carries only the segment written since the one before (ReplayMemory.segment),
which joins the journal once the checkpoint is `latest`; segments the memory has since overwritten are
removed. A checkpoint directory is renamed into place only when complete, and `latest` is replaced
atomically after it, so a crash mid-write never corrupts a resume, and the journal never holds a write
the latest checkpoint has not seen.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import safetensors.numpy
import torch
from safetensors.torch import load_file, save_file

from uav_policy.networks import NetConfig
from uav_policy.weights import write_atomic

from .learner import Learner

KEEP = 3


def _optimizer_tensors(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], list]:
    sd = opt.state_dict()
    tensors = {}
    for idx, st in sd["state"].items():
        for k, v in st.items():
            tensors[f"optimizer.state.{idx}.{k}"] = torch.as_tensor(v).detach().cpu().contiguous()
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in sd["param_groups"]]
    return tensors, groups


SEGMENT_FILE = "replay_segment.safetensors"  # in a checkpoint until it joins the journal
JOURNAL_DIR = "replay"


def save(
    dir_: str | os.PathLike,
    learner: Learner,
    counters: dict,
    extra_rng: dict,
    segment: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a checkpoint named after the update count, with the replay journal's `segment`
    (ReplayMemory.segment) when given; returns its directory."""
    root = Path(dir_)
    root.mkdir(parents=True, exist_ok=True)
    name = f"ckpt-{learner.updates:09d}-{counters.get('env_steps', 0):09d}"
    final = root / name
    tmp = root / f".{name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        _write(tmp, learner, counters, extra_rng, segment)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # a failed write (a full disk) leaves nothing behind
        raise
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    write_atomic(root / "latest", name.encode())
    # The newest by name, this one always kept (an earlier run's in the same folder may be named higher).
    for old in sorted(p for p in root.glob("ckpt-*") if p.is_dir() and p != final)[: -(KEEP - 1)]:
        shutil.rmtree(old, ignore_errors=True)
    if segment is not None:
        _to_journal(root, final / SEGMENT_FILE, segment["span"])
    return final


def _segment_name(span: tuple[int, int]) -> str:
    return f"seg-{span[0]:012d}-{span[1]:012d}.safetensors"


def _to_journal(root: Path, seg: Path, span) -> None:
    """Move a checkpoint's replay segment into the journal (once the checkpoint is `latest`)."""
    journal = root / JOURNAL_DIR
    journal.mkdir(exist_ok=True)
    os.replace(seg, journal / _segment_name((int(span[0]), int(span[1]))))


def prune_journal(dir_: str | os.PathLike, before: int) -> int:
    """Remove the journal's segments that end at or before write `before` (overwritten since); how many."""
    gone = 0
    for f in (Path(dir_) / JOURNAL_DIR).glob("seg-*.safetensors"):
        try:
            end = int(f.stem.split("-")[2])
        except (IndexError, ValueError):
            continue
        if end <= before:
            f.unlink(missing_ok=True)
            gone += 1
    return gone


def drop_journal(dir_: str | os.PathLike) -> int:
    """Remove the whole replay journal; the bytes it held."""
    journal = Path(dir_) / JOURNAL_DIR
    size = sum(f.stat().st_size for f in journal.glob("*") if f.is_file())
    shutil.rmtree(journal, ignore_errors=True)
    return size


def journal_segments(dir_: str | os.PathLike, ckpt: Path) -> list[dict[str, np.ndarray]]:
    """The replay journal's segments; a segment still inside the latest checkpoint `ckpt` (a run killed
    between writing it and moving it) joins the journal first. Raises ValueError for a file safetensors
    cannot read (no pickle is involved)."""
    root = Path(dir_)
    out = []
    pending = ckpt / SEGMENT_FILE
    files = sorted((root / JOURNAL_DIR).glob("seg-*.safetensors")) + ([pending] if pending.is_file() else [])
    for f in files:
        try:
            out.append(safetensors.numpy.load_file(str(f)))
        except Exception as e:  # safetensors raises its own error types for a truncated or bad header
            raise ValueError(f"{f}: unreadable ({e})") from e
    if pending.is_file() and getattr(out[-1].get("span"), "shape", None) == (2,):
        _to_journal(root, pending, out[-1]["span"])
    return out


def remove_stale(dir_: str | os.PathLike) -> int:
    """Remove the unfinished checkpoint folders a killed run left behind; how many."""
    stale = [p for p in Path(dir_).glob(".ckpt-*.tmp") if p.is_dir()]
    for p in stale:
        shutil.rmtree(p, ignore_errors=True)
    return len(stale)


def _io(save, tensors: dict, path: Path) -> None:
    """`save(tensors, path)`, any failure to write an OSError: safetensors reports a full disk as its own
    SafetensorError ("I/O error: No space left on device")."""
    try:
        save(tensors, str(path))
    except OSError:
        raise
    except Exception as e:
        raise OSError(errno.EIO, f"{path.name}: {e}") from e


def _write(tmp: Path, learner: Learner, counters: dict, extra_rng: dict, segment) -> None:
    tensors = {f"online.{k}": v.detach().cpu().contiguous() for k, v in learner.online.state_dict().items()}
    tensors.update({f"target.{k}": v.detach().cpu().contiguous() for k, v in learner.target.state_dict().items()})
    opt_tensors, groups = _optimizer_tensors(learner.optimizer)
    tensors.update(opt_tensors)
    tensors["rng.torch"] = torch.random.get_rng_state()
    _io(save_file, tensors, tmp / "state.safetensors")
    meta = {
        "format": "uav_trainer_checkpoint/1",
        "net_config": json.loads(learner.net_cfg.to_json()),
        "learner_config": dataclasses.asdict(learner.cfg),
        "teacher_config": dataclasses.asdict(learner.teaching),
        "updates": learner.updates,
        "optimizer_param_groups": groups,
        "counters": counters,
        "rng": extra_rng,
    }
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    if segment is not None:
        _io(safetensors.numpy.save_file, segment, tmp / SEGMENT_FILE)
    for f in tmp.iterdir():
        with open(f, "rb") as fh:
            os.fsync(fh.fileno())


def latest(dir_: str | os.PathLike) -> Path | None:
    root = Path(dir_)
    try:
        name = (root / "latest").read_text().strip()
    except OSError:
        return None
    p = root / name
    return p if (p / "meta.json").is_file() and (p / "state.safetensors").is_file() else None


def read_meta(path: Path) -> tuple[dict, NetConfig]:
    """A checkpoint's meta.json and its network config. Raises ValueError when it is not a checkpoint
    (OSError when it cannot be read)."""
    meta = json.loads((path / "meta.json").read_text())
    if not isinstance(meta, dict) or meta.get("format") != "uav_trainer_checkpoint/1":
        raise ValueError(f"{path}: not a uav_trainer checkpoint")
    try:
        return meta, NetConfig.from_json(json.dumps(meta["net_config"]))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: checkpoint network config is invalid: {e}") from None


def load(path: Path, learner: Learner) -> dict:
    """Restore a learner in place; returns the meta (counters, rng). Raises ValueError on mismatch."""
    meta, cfg = read_meta(path)
    if cfg != learner.net_cfg:
        raise ValueError(f"{path}: checkpoint network {cfg.to_json()} differs from {learner.net_cfg.to_json()}")
    tensors = load_file(str(path / "state.safetensors"))
    learner.online.load_state_dict({k[7:]: v for k, v in tensors.items() if k.startswith("online.")})
    learner.target.load_state_dict({k[7:]: v for k, v in tensors.items() if k.startswith("target.")})
    state = {}
    for k, v in tensors.items():
        if k.startswith("optimizer.state."):
            _, _, idx, key = k.split(".", 3)
            state.setdefault(int(idx), {})[key] = v
    groups = meta["optimizer_param_groups"]
    for g in groups:
        if "betas" in g:
            g["betas"] = tuple(g["betas"])
    learner.optimizer.load_state_dict({"state": state, "param_groups": groups})
    learner.updates = int(meta["updates"])
    torch.random.set_rng_state(tensors["rng.torch"])
    return meta


def rng_state(rng: np.random.Generator) -> dict:
    return rng.bit_generator.state


def set_rng_state(rng: np.random.Generator, state: dict) -> None:
    rng.bit_generator.state = state
