"""Weights files and pushes: safetensors only (no pickle), validated before anything is swapped.

A weights blob is a safetensors file whose metadata holds `format` = uav_policy/1 and
`config` = the NetConfig JSON, so a file made for the other architecture is recognised, and
optionally `camera_hfov_deg`: the horizontal field of view of the depth camera the network was
trained with (a network flies worse behind another camera; policy_node warns, evaluate and the
figures fly it with that camera). Files without it say nothing about their camera. And optionally
`reward_window_fraction`: the reward's central window the network was trained on, when it was
not the paper's 20 % (evaluate measures Table 2's reward with it); files without it were trained
with the paper's window.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import struct
import tempfile
import weakref
from pathlib import Path

import numpy as np
import torch
from safetensors.numpy import save as st_save
from safetensors.torch import load as st_load

from .networks import SIZE_FIELDS, NetConfig, QEnsemble, build_network

FORMAT = "uav_policy/1"
MAX_BYTES = 64 * 1024 * 1024
CAMERA_KEY = "camera_hfov_deg"
WINDOW_KEY = "reward_window_fraction"
DISTILLED_KEY = "distilled_from"  # the ensemble a network was distilled from: JSON [{"file", "sha256"}, ...]
HFOV_RANGE_DEG = (10.0, 170.0)  # sim_node's hfov_deg range


class WeightsError(ValueError):
    """Weights that cannot be used; the message says what was expected."""


def to_bytes(
    net: torch.nn.Module,
    cfg: NetConfig,
    camera_hfov_deg: float | None = None,
    reward_window_fraction: float | None = None,
    notes: dict[str, str] | None = None,
) -> bytes:
    """The safetensors blob; `camera_hfov_deg` (when known) records the camera the net was trained with,
    `reward_window_fraction` (when not None) the reward window it was trained on; `notes` are further metadata
    entries that loaders pass over (e.g. the ensemble a network was distilled from, DISTILLED_KEY)."""
    # As numpy arrays (views of the CPU tensors): safetensors writes the same bytes ~5x faster than from torch.
    tensors = {k: v.detach().to("cpu").contiguous().numpy() for k, v in net.state_dict().items()}
    meta = {**(notes or {}), "format": FORMAT, "config": cfg.to_json()}
    if camera_hfov_deg is not None:
        meta[CAMERA_KEY] = repr(_check_hfov(camera_hfov_deg))
    if reward_window_fraction is not None:
        meta[WINDOW_KEY] = repr(_check_window(reward_window_fraction))
    return _canonical(st_save(tensors, metadata=meta))


def _canonical(blob: bytes) -> bytes:
    """The same file with its JSON header's keys sorted: safetensors writes the header in hash-map
    order, which changes from call to call, so equal networks gave different bytes. Sorted, equal
    weights give equal files (a seeded run is reproducible byte for byte; `cmp` compares two).
    The header stays padded with spaces to 8 bytes, as safetensors writes it."""
    (n,) = struct.unpack("<Q", blob[:8])
    header = json.dumps(json.loads(blob[8 : 8 + n]), sort_keys=True, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 8)
    return struct.pack("<Q", len(header)) + header + blob[8 + n :]


def save_file(
    net: torch.nn.Module,
    cfg: NetConfig,
    path: str | os.PathLike,
    camera_hfov_deg: float | None = None,
    reward_window_fraction: float | None = None,
    notes: dict[str, str] | None = None,
) -> None:
    """Write atomically: a reader never sees a half-written file."""
    write_atomic(Path(path), to_bytes(net, cfg, camera_hfov_deg, reward_window_fraction, notes))


def _check_hfov(value) -> float:
    lo, hi = HFOV_RANGE_DEG
    return _checked_number(value, CAMERA_KEY, lambda v: lo <= v <= hi, f"a number of degrees in [{lo:g}, {hi:g}]")


def _check_window(value) -> float:
    return _checked_number(value, WINDOW_KEY, lambda v: 0.0 < v <= 1.0, "a share of the image side in (0, 1]")


def _checked_number(value, key: str, ok, what: str) -> float:
    """`value` as a float if `ok` holds for it (NaN and non-numbers never do), else WeightsError naming `key`."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if math.isnan(v) or not ok(v):
        raise WeightsError(f"'{key}' must be {what}, got {value!r}")
    return v


def write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _header_metadata(blob: bytes) -> dict:
    if len(blob) < 8:
        raise WeightsError(f"weights are truncated: {len(blob)} bytes is not a safetensors file")
    (n,) = struct.unpack("<Q", blob[:8])
    if n > len(blob) - 8 or n > 16 * 1024 * 1024:
        raise WeightsError("weights are truncated or corrupt: safetensors header length is out of bounds")
    try:
        header = json.loads(blob[8 : 8 + n])
        meta = header.get("__metadata__") or {}
        meta.get("format")  # not a JSON object: AttributeError
    except (ValueError, AttributeError):
        raise WeightsError("weights are corrupt: the safetensors header is not valid JSON") from None
    if meta.get("format") != FORMAT:
        raise WeightsError(f"weights metadata 'format' must be '{FORMAT}', got {meta.get('format')!r}")
    return meta


def read_header_config(blob: bytes) -> NetConfig:
    """The network config stored in a blob's metadata (without loading the tensors)."""
    return _config_of(_header_metadata(blob))


def read_header_camera(blob: bytes) -> float | None:
    """The trained camera's horizontal field of view (deg) in a blob's metadata; None when not recorded."""
    return _camera_of(_header_metadata(blob))


def _camera_of(meta: dict) -> float | None:
    return _entry_of(meta, CAMERA_KEY, _check_hfov)


def _window_of(meta: dict) -> float | None:
    return _entry_of(meta, WINDOW_KEY, _check_window)


def _entry_of(meta: dict, key: str, check) -> float | None:
    if key not in meta:
        return None
    try:
        return check(meta[key])
    except WeightsError as e:
        raise WeightsError(f"weights metadata {e}") from None


def _config_of(meta: dict) -> NetConfig:
    try:
        return NetConfig.from_json(meta.get("config", ""))  # validated as made: out-of-range sizes stop here
    except (ValueError, TypeError) as e:
        raise WeightsError(f"weights metadata 'config' is invalid: {e}") from None


@functools.lru_cache(maxsize=16)
def _expected_tensors(cfg: NetConfig) -> dict[str, torch.Tensor]:
    """The tensors a network of `cfg` holds, built without storage (meta device): a hostile header
    claiming a huge architecture allocates nothing before its tensors are found not to fit it. Cached:
    lockstep learning loads a push every other step, and a meta build takes ~50 ms."""
    with torch.device("meta"):
        return build_network(cfg).state_dict()


def load_bytes(
    blob: bytes, expected: NetConfig, sizes_from_blob: bool = False, into: torch.nn.Module | None = None
) -> torch.nn.Module:
    """A network with the blob's weights, after checking everything (nothing is written before every check passed).
    `sizes_from_blob`: take the layer sizes (networks.SIZE_FIELDS) and SAM readout from the blob's header instead of
    `expected`; the network's `cfg` then says which were built. `into`: a network nothing reads meanwhile (policy_node's
    spare, the in-process loop's acting copy), written over when it has the blob's architecture (a copy instead of a
    build: weight pushes come every other step); else a new one is built."""
    if not isinstance(blob, (bytes, bytearray)) or len(blob) == 0:
        raise WeightsError("weights are empty")
    if len(blob) > MAX_BYTES:
        raise WeightsError(f"weights are {len(blob)} bytes, more than the {MAX_BYTES} allowed")
    meta = _header_metadata(bytes(blob))
    cfg = _config_of(meta)
    _camera_of(meta)  # a malformed camera or window entry is refused like any other bad metadata
    _window_of(meta)
    if sizes_from_blob:
        expected = with_sizes_of(expected, cfg)
    if cfg.model != expected.model:
        raise WeightsError(f"weights are for model '{cfg.model}', but this policy runs model '{expected.model}'")
    if cfg != expected:
        raise WeightsError(f"weights were made for architecture {cfg.to_json()}, expected {expected.to_json()}")
    try:
        tensors = st_load(bytes(blob))
    except Exception as e:  # safetensors raises SafetensorError and others on corrupt input
        raise WeightsError(f"weights are corrupt or truncated: {e}") from None
    want = _expected_tensors(expected)
    missing, extra = set(want) - set(tensors), set(tensors) - set(want)
    if missing or extra:
        raise WeightsError(f"weights tensor names differ: missing {sorted(missing)[:5]}, unexpected {sorted(extra)[:5]}")
    for name, t in tensors.items():
        if t.shape != want[name].shape:
            raise WeightsError(f"tensor '{name}' has shape {tuple(t.shape)}, expected {tuple(want[name].shape)}")
        if t.dtype != want[name].dtype:
            raise WeightsError(f"tensor '{name}' has dtype {t.dtype}, expected {want[name].dtype}")
    if not _all_finite(blob):  # then find the tensor, to name it
        for name, t in tensors.items():
            if t.is_floating_point() and not torch.isfinite(t).all():
                raise WeightsError(f"tensor '{name}' has non-finite values (NaN or Inf)")
    if into is not None and not isinstance(into, QEnsemble) and getattr(into, "cfg", None) == expected:
        targets = _TARGETS.get(into)
        if targets is None:
            targets = _TARGETS[into] = into.state_dict(keep_vars=True)
        with torch.no_grad():  # names and shapes are checked: one copy per tensor (load_bytes 0.5 -> 0.23 ms)
            for name, t in tensors.items():
                targets[name].copy_(t)
        return into
    net = build_network(expected)
    net.load_state_dict(tensors)
    return net


_TARGETS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # a reused network's tensors by name


def _all_finite(blob: bytes) -> bool:
    """Whether the data of a checked blob read as float32 (the networks' one dtype) is all finite: one pass over
    the bytes instead of one per tensor. False may also mean data of another dtype; the caller then looks closer."""
    (n,) = struct.unpack("<Q", blob[:8])
    data = memoryview(blob)[8 + n :]
    return len(data) % 4 == 0 and bool(np.isfinite(np.frombuffer(data, np.float32)).all())


def load_file(path: str | os.PathLike, expected: NetConfig, sizes_from_blob: bool = False) -> torch.nn.Module:
    p = Path(path).expanduser()
    try:
        size = p.stat().st_size
        if size > MAX_BYTES:  # not read into memory
            raise WeightsError(f"{p}: weights are {size} bytes, more than the {MAX_BYTES} allowed")
        blob = p.read_bytes()
    except OSError as e:
        raise WeightsError(f"cannot read weights file '{p}': {e.strerror}") from None
    try:
        return load_bytes(blob, expected, sizes_from_blob)
    except WeightsError as e:
        raise WeightsError(f"{p}: {e}") from None


def _read_file_metadata(path: str | os.PathLike) -> dict:
    p = Path(path).expanduser()
    try:
        with p.open("rb") as f:
            blob = f.read(8 + 16 * 1024 * 1024)
    except OSError as e:
        raise WeightsError(f"cannot read weights file '{p}': {e.strerror}") from None
    try:
        meta = _header_metadata(blob)
        _config_of(meta)  # the whole header is checked, whichever part the caller wants
        _camera_of(meta)
        _window_of(meta)
        return meta
    except WeightsError as e:
        raise WeightsError(f"{p}: {e}") from None


def read_file_notes(path: str | os.PathLike) -> dict[str, str]:
    """A weights file's metadata entries beyond the format, config, camera and window (e.g. DISTILLED_KEY)."""
    meta = _read_file_metadata(path)
    return {k: v for k, v in meta.items() if k not in ("format", "config", CAMERA_KEY, WINDOW_KEY)}


def read_file_config(path: str | os.PathLike) -> NetConfig:
    """The network config a weights file was made for (its header only; the tensors are not checked)."""
    return _config_of(_read_file_metadata(path))


def read_file_camera(path: str | os.PathLike) -> float | None:
    """The camera field of view (deg) a weights file was trained with; None when the file does not say."""
    return _camera_of(_read_file_metadata(path))


# The camera that weights files recording none were trained with (the 120 deg camera of the recipe that
# came before the shipped one): they fly behind it.
UNRECORDED_HFOV_DEG = 120.0


def camera_for(path: str | os.PathLike | None, default: float) -> float:
    """The field of view to fly weights with: the file's trained camera, else `default`."""
    hfov = read_file_camera(path) if path else None
    return default if hfov is None else hfov


def read_file_window(path: str | os.PathLike) -> float | None:
    """The reward window a weights file was trained on; None when the file does not say (the paper's)."""
    return _window_of(_read_file_metadata(path))


def window_for(path: str | os.PathLike | None, default: float) -> float:
    """The reward window to measure weights' reward with: the file's, else `default`."""
    w = read_file_window(path) if path else None
    return default if w is None else w


def config_for(model: str, path: str | os.PathLike | None) -> NetConfig:
    """The architecture to load `path` as `model` with: the file's input size, frame stack, SAM readout
    and layer sizes (networks.SIZE_FIELDS; the defaults without a path). The model, action count and
    depth range stay the stack's, so a file made for another model or interface still fails to load."""
    if not path:
        return NetConfig(model=model)
    made = read_file_config(path)
    cfg = NetConfig(model=model, sam_readout=made.sam_readout, height=made.height, width=made.width, frames=made.frames)
    return with_sizes_of(cfg, made)


def with_sizes_of(cfg: NetConfig, made: NetConfig) -> NetConfig:
    """`cfg` with `made`'s layer sizes (networks.SIZE_FIELDS), SAM readout, feature norm and local map input: the
    architecture a file made as `made` is loaded with."""
    return dataclasses.replace(
        cfg,
        sam_readout=made.sam_readout,
        feature_norm=made.feature_norm,
        local_map=made.local_map,
        **{name: getattr(made, name) for name in SIZE_FIELDS},
    )


def load_files(paths: list, model: str) -> torch.nn.Module:
    """The network of one weights file, or several files of one architecture as one QEnsemble acting on
    their mean Q-values (WeightsError for a bad file, ValueError when the architectures differ)."""
    nets = [load_file(p, config_for(model, p)) for p in paths]
    return nets[0] if len(nets) == 1 else QEnsemble(nets)


def load_policy(model: str, files: list[str], hfov_deg: float | None, window: float | None, unrecorded_window: float):
    """(the network, or for several files a QEnsemble on their mean Q-values; its NetConfig; the
    camera to fly with; the reward window) for weights files of one architecture. Without hfov_deg
    the members' trained camera and without `window` their reward window (`unrecorded_window` for a file that records
    none), each of which must then be the same for all (ValueError if not)."""
    net = load_files(files, model)
    if hfov_deg is None:
        cameras = {camera_for(f, UNRECORDED_HFOV_DEG) for f in files}
        if len(cameras) != 1:
            raise ValueError(f"members were trained with different cameras {sorted(cameras)}: give --sim-arg hfov_deg:=X")
        hfov_deg = cameras.pop()
    if window is None:
        windows = {window_for(f, unrecorded_window) for f in files}
        if len(windows) != 1:
            raise ValueError(
                f"members were trained with different reward windows {sorted(windows)}: give --sim-arg reward_window_fraction:=F"
            )
        window = windows.pop()
    return net, net.cfg, hfov_deg, window


def policy_network(paths: list[str], cfg: NetConfig, seed: int, warn=print):
    """What policy_node flies: open_files(paths), or without paths the packaged files, or when those are
    missing or unusable (`warn` says why) a seeded random initialisation. (network, source, camera or None)."""
    if paths:
        return open_files(paths, cfg)
    packaged = packaged_weights(cfg.model)
    if packaged:
        try:
            net, source, camera = open_files([str(p) for p in packaged], cfg)
            if net.cfg.local_map != cfg.local_map:
                raise ValueError("they " + ("lack" if cfg.local_map else "take") + " the local map input")
            return net, f"packaged pretrained weights: {source}", camera
        except ValueError as e:
            warn(f"packaged weights unusable ({e}); using a random initialisation")
    net = build_network(cfg, seed=seed)
    return net, f"no weights given or packaged: seeded random initialisation (seed {seed})", None


def camera_mismatch(trained: float | None, camera: float | None) -> tuple[float, float] | None:
    """(trained, camera) field of view, rounded, when both are known and differ by more than 0.5 deg."""
    if trained is None or camera is None or abs(trained - camera) <= 0.5:
        return None
    return round(trained, 1), round(camera, 1)


def parse_files(value: str) -> list[str]:
    """The 'weights' parameter as a list of files: [] (the packaged weights), one file, or several separated
    by commas (flown as one policy); a folder stands for its .safetensors files in name order (a run's
    snapshots and final weights, or a packaged set). ValueError for an empty name or an empty folder."""
    names = [f.strip() for f in value.split(",")] if value.strip() else []
    if not all(names):
        raise ValueError(f"'weights': an empty file name in the list {value!r}")
    files = []
    for name in names:
        if os.path.isdir(name):
            inside = sorted(str(p) for p in Path(name).glob("*.safetensors"))
            if not inside:
                raise ValueError(f"'weights': the folder {name} holds no .safetensors file")
            files += inside
        else:
            files.append(name)
    return files


def open_files(paths: list[str], cfg: NetConfig) -> tuple[torch.nn.Module, str, float | None]:
    """What policy_node flies for its 'weights' files: (one network, or several of one architecture as a
    QEnsemble on their mean Q-values; where it came from, in words; the camera they were trained behind,
    or None). Layer sizes and SAM readout come from the files; everything else must match `cfg` (the node's parameters).
    WeightsError (a ValueError) says which file is wrong and, for another input size or frame stack,
    which parameters to set."""
    nets = []
    for path in paths:
        try:
            nets.append(load_file(path, cfg, sizes_from_blob=True))
        except WeightsError as e:
            raise WeightsError(f"{e}{_size_hint(path, cfg)}") from None
    net = nets[0] if len(nets) == 1 else QEnsemble(nets)
    cameras = {read_file_camera(p) for p in paths}
    if len(cameras) != 1:
        known = sorted(c for c in cameras if c is not None)
        shown = ", ".join(["none recorded"] * (None in cameras) + [f"{c:g} deg" for c in known])
        raise WeightsError(f"the files were trained with different cameras ({shown})")
    if len(nets) == 1:
        return net, f"weights from {paths[0]}", cameras.pop()
    folders = {str(Path(f).parent) for f in paths}
    named = ", ".join(paths)
    if len(folders) == 1:  # one run's snapshots, or the packaged files: the folder once
        named = ", ".join(Path(f).name for f in paths) + f" in {folders.pop()}"
    return net, f"an ensemble of {len(paths)} weights files acting on their mean Q-values: {named}", cameras.pop()


def _size_hint(path: str, cfg: NetConfig) -> str:
    """What to set when a weights file was made for another input size or frame stack ('' otherwise)."""
    try:
        made = read_file_config(path)
    except WeightsError:
        return ""
    hint = ""
    if (made.height, made.width) != (cfg.height, cfg.width):
        hint += (
            f"; the file takes {made.width}x{made.height} frames: set input_height:={made.height} "
            f"input_width:={made.width} (and sim_node's image_width/image_height to match)"
        )
    if made.frames != cfg.frames:
        hint += f"; the file stacks {made.frames} frames: set frame_stack:={made.frames}"
    return hint


def packaged_weights(model: str) -> list[Path]:
    """The pretrained weights shipped with uav_policy for `model`: the safetensors files of the
    package's weights/<model>/ folder in name order, flown as one policy when there are several
    (the installed share folder first, else the source tree's); [] when there are none."""
    folders = []
    try:
        from ament_index_python.packages import get_package_share_directory

        folders.append(Path(get_package_share_directory("uav_policy")) / "weights" / model)
    except Exception:
        pass
    folders.append(Path(__file__).resolve().parent.parent / "weights" / model)
    for folder in folders:
        files = sorted(folder.glob("*.safetensors"))
        if files:
            return files
    return []
