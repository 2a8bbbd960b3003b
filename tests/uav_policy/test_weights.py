import dataclasses
import json
import struct

import pytest
import torch
from safetensors.torch import save as st_save

from uav_policy import weights as wio
from uav_policy.networks import NetConfig, build_network

SAM = NetConfig(model="sam")


def blob(model="sam", seed=0):
    cfg = NetConfig(model=model)
    return wio.to_bytes(build_network(cfg, seed=seed), cfg)


def test_round_trip_file(tmp_path):
    net = build_network(SAM, seed=3)
    wio.save_file(net, SAM, tmp_path / "w.safetensors")
    back = wio.load_file(tmp_path / "w.safetensors", SAM)
    x = torch.rand(1, 5, 64, 64) * 10
    torch.testing.assert_close(net(x)[0], back(x)[0])
    assert not list(tmp_path.glob(".*tmp")), "atomic write leaves no temp files"


def test_equal_networks_give_equal_bytes():
    """safetensors writes its header in hash-map order; to_bytes sorts it, so files can be compared with cmp."""
    net = build_network(SAM, seed=3)
    blobs = {wio.to_bytes(net, SAM, 120.0) for _ in range(20)}
    assert len(blobs) == 1
    (only,) = blobs
    (n,) = struct.unpack("<Q", only[:8])
    assert n % 8 == 0 and list(json.loads(only[8 : 8 + n])["__metadata__"]) == ["camera_hfov_deg", "config", "format"]
    back = wio.load_bytes(only, SAM)
    for a, b in zip(net.state_dict().values(), back.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert wio.read_header_camera(only) == 120.0


def test_the_bytes_are_those_safetensors_writes_from_torch():
    """to_bytes hands safetensors numpy views (faster); the file is the one its torch writer makes, header sorted."""
    net = build_network(SAM, seed=4)
    meta = {"format": wio.FORMAT, "config": SAM.to_json(), "camera_hfov_deg": repr(87.0)}
    reference = st_save({k: v.contiguous() for k, v in net.state_dict().items()}, metadata=meta)
    (n,) = struct.unpack("<Q", reference[:8])
    header = json.dumps(json.loads(reference[8 : 8 + n]), sort_keys=True, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 8)
    assert wio.to_bytes(net, SAM, 87.0) == struct.pack("<Q", len(header)) + header + reference[8 + n :]


def test_a_push_is_loaded_into_a_spare_network_of_its_architecture_only():
    x = torch.rand(1, 5, 64, 64) * 10
    pushed = wio.to_bytes(build_network(SAM, seed=5), SAM)
    fresh = wio.load_bytes(pushed, SAM)
    spare = build_network(SAM, seed=6)
    loaded = wio.load_bytes(pushed, SAM, into=spare)
    assert loaded is spare and torch.equal(loaded(x)[0], fresh(x)[0])
    other = NetConfig(model="sam", d_model=60)
    kept = build_network(other, seed=6)
    before = {k: v.clone() for k, v in kept.state_dict().items()}
    assert wio.load_bytes(pushed, SAM, into=kept) is not kept  # another architecture: built anew
    assert all(torch.equal(before[k], v) for k, v in kept.state_dict().items())
    t = tensors_of(pushed)
    name = "dueling_head.value.2.weight"
    bad = dict(t, **{name: t[name].clone().index_fill_(1, torch.tensor([3]), float("inf"))})  # one value
    spare_before = {k: v.clone() for k, v in spare.state_dict().items()}
    with pytest.raises(wio.WeightsError, match=f"'{name}' has non-finite"):
        wio.load_bytes(rewrap(bad), SAM, into=spare)
    assert all(torch.equal(spare_before[k], v) for k, v in spare.state_dict().items())  # a refused push writes nothing


def test_rejects_the_other_architecture():
    with pytest.raises(wio.WeightsError, match="model 'cnn'.*runs model 'sam'"):
        wio.load_bytes(blob("cnn"), SAM)


def test_rejects_truncated_and_corrupt():
    good = blob()
    with pytest.raises(wio.WeightsError, match="truncated|corrupt"):
        wio.load_bytes(good[: len(good) // 2], SAM)
    with pytest.raises(wio.WeightsError):
        wio.load_bytes(b"\x00" * 3, SAM)
    with pytest.raises(wio.WeightsError, match="header"):
        wio.load_bytes(struct.pack("<Q", 10**12) + b"{}", SAM)
    with pytest.raises(wio.WeightsError, match="empty"):
        wio.load_bytes(b"", SAM)


def test_rejects_pickle_files():
    import io

    buf = io.BytesIO()
    torch.save(build_network(SAM).state_dict(), buf)  # a pickle-based .pt is never unpickled
    with pytest.raises(wio.WeightsError):
        wio.load_bytes(buf.getvalue(), SAM)


def tensors_of(b):
    from safetensors.torch import load

    return load(b)


def rewrap(tensors, cfg=SAM):
    return st_save(tensors, metadata={"format": wio.FORMAT, "config": cfg.to_json()})


def test_rejects_wrong_shape_dtype_names_and_non_finite():
    t = tensors_of(blob())
    name = "dueling_head.value.2.weight"
    bad = dict(t, **{name: torch.zeros(1, 7)})
    with pytest.raises(wio.WeightsError, match="shape"):
        wio.load_bytes(rewrap(bad), SAM)
    bad = dict(t, **{name: t[name].double()})
    with pytest.raises(wio.WeightsError, match="dtype"):
        wio.load_bytes(rewrap(bad), SAM)
    bad = dict(t)
    del bad[name]
    with pytest.raises(wio.WeightsError, match="names differ"):
        wio.load_bytes(rewrap(bad), SAM)
    bad = dict(t, **{name: torch.full_like(t[name], float("nan"))})
    with pytest.raises(wio.WeightsError, match="non-finite"):
        wio.load_bytes(rewrap(bad), SAM)


def test_rejects_a_different_sam_architecture():
    other = NetConfig(model="sam", d_model=60)
    b = wio.to_bytes(build_network(other), other)
    with pytest.raises(wio.WeightsError, match="architecture"):
        wio.load_bytes(b, SAM)


def test_loaders_take_the_layer_sizes_from_the_file_and_nothing_else(tmp_path):
    other = NetConfig(model="sam", d_model=24, heads=2, relational_blocks=2, mlp_hidden=32, sam_readout="flatten")
    net = build_network(other, seed=4)
    wio.save_file(net, other, tmp_path / "other.safetensors")
    assert wio.config_for("sam", tmp_path / "other.safetensors") == other
    x = torch.rand(2, 5, 64, 64) * 10
    torch.testing.assert_close(wio.load_file(tmp_path / "other.safetensors", other)(x)[0], net(x)[0])
    assert wio.with_sizes_of(SAM, other) == other  # the layer sizes and the readout
    assert wio.load_file(tmp_path / "other.safetensors", SAM, sizes_from_blob=True).cfg == other
    with pytest.raises(wio.WeightsError, match="architecture"):
        wio.load_file(tmp_path / "other.safetensors", SAM)  # without sizes_from_blob the sizes must match
    # The frame stack is the file's too (evaluate flies a file with its own); the model, actions and
    # depth range are the stack's.
    with pytest.raises(wio.WeightsError, match="model 'sam'"):
        wio.load_file(tmp_path / "other.safetensors", wio.config_for("cnn", tmp_path / "other.safetensors"))
    six = NetConfig(model="sam", frames=6)
    wio.save_file(build_network(six), six, tmp_path / "six.safetensors")
    assert wio.load_file(tmp_path / "six.safetensors", wio.config_for("sam", tmp_path / "six.safetensors")).cfg == six
    with pytest.raises(wio.WeightsError, match='"frames": 6'):
        wio.load_file(tmp_path / "six.safetensors", SAM)  # policy_node's own frame_stack (5) must match


def test_a_header_claiming_a_huge_network_is_refused_before_anything_is_allocated(monkeypatch):
    """The header decides the sizes a loader builds, so the tensors are checked against a network on
    the meta device (no storage) before a real one is built."""
    huge = NetConfig(model="sam", d_model=1024, heads=8, relational_blocks=16, mlp_hidden=4096, conv_channels=(512, 512))
    b = rewrap(tensors_of(blob()), huge)
    built_on = []
    real_build = wio.build_network

    def build(cfg, seed=None):
        built_on.append(torch.empty(0).device.type)
        return real_build(cfg, seed)

    monkeypatch.setattr(wio, "build_network", build)
    wio._expected_tensors.cache_clear()  # the meta build is cached per architecture
    with pytest.raises(wio.WeightsError, match="names differ|shape"):
        wio.load_bytes(b, SAM, sizes_from_blob=True)  # as policy_node loads files and pushes
    assert built_on == ["meta"]
    wio.load_bytes(blob(), SAM)  # a good blob: checked on the meta device, then built for real
    assert built_on[1:] == ["meta", "cpu"]
    wio.load_bytes(blob(), SAM)  # the same architecture again (a lockstep push every other step): no meta build
    assert built_on[3:] == ["cpu"]


def test_a_file_over_the_size_limit_is_not_read(tmp_path):
    big = tmp_path / "big.safetensors"
    with big.open("wb") as f:
        f.truncate(wio.MAX_BYTES + 1)  # sparse: nothing is written
    with pytest.raises(wio.WeightsError, match="more than the 67108864 allowed"):
        wio.load_file(big, SAM)


@pytest.mark.parametrize(
    "sizes, match",
    [
        ({"d_model": 0}, "d_model must be integer"),
        ({"mlp_hidden": 5000}, r"mlp_hidden must be integer\(s\) in \[1, 4096\]"),
        ({"conv_channels": ()}, "conv_channels"),
        ({"conv_channels": (16, 1000)}, "conv_channels"),
        ({"relational_blocks": "2"}, "relational_blocks"),
        ({"heads": 5}, "divisible by heads"),
    ],
)
def test_layer_sizes_out_of_range_are_refused_in_a_header(sizes, match):
    cfg = json.loads(SAM.to_json()) | sizes
    b = st_save(tensors_of(blob()), metadata={"format": wio.FORMAT, "config": json.dumps(cfg)})
    with pytest.raises(wio.WeightsError, match=match):
        wio.load_bytes(b, SAM)
    with pytest.raises(ValueError, match=match):
        NetConfig(**json.loads(SAM.to_json()) | sizes).validate()


def test_the_sam_readout_is_part_of_the_architecture(tmp_path):
    flat = NetConfig(model="sam", sam_readout="flatten")
    wio.save_file(build_network(flat, seed=1), flat, tmp_path / "flat.safetensors")
    assert wio.read_file_config(tmp_path / "flat.safetensors") == flat
    wio.load_file(tmp_path / "flat.safetensors", flat)
    with pytest.raises(wio.WeightsError, match='"sam_readout": "flatten"'):
        wio.load_file(tmp_path / "flat.safetensors", SAM)
    # Files written before the readout existed carry no such field: they are max-readout SAMs.
    net = build_network(SAM, seed=2)
    old = json.loads(SAM.to_json())
    del old["sam_readout"]
    tensors = {k: v.contiguous() for k, v in net.state_dict().items()}
    b = st_save(tensors, metadata={"format": wio.FORMAT, "config": json.dumps(old)})
    x = torch.rand(1, 5, 64, 64) * 10
    torch.testing.assert_close(wio.load_bytes(b, SAM)(x)[0], net(x)[0])


def test_missing_file_message(tmp_path):
    with pytest.raises(wio.WeightsError, match="cannot read weights file"):
        wio.load_file(tmp_path / "nope.safetensors", SAM)


def assert_entry_refused(net, tmp_path, key, bad_values, message, read_header):
    """Every one of `bad_values` as metadata `key` is refused when loading and by `read_header` on a file."""
    tensors = {k: v.contiguous() for k, v in net.state_dict().items()}
    for bad in bad_values:
        b = st_save(tensors, metadata={"format": wio.FORMAT, "config": SAM.to_json(), key: bad})
        with pytest.raises(wio.WeightsError, match=f"'{key}' {message}"):
            wio.load_bytes(b, SAM)
        (tmp_path / "bad.safetensors").write_bytes(b)
        with pytest.raises(wio.WeightsError, match=f"bad.safetensors: .*{key}"):
            read_header(tmp_path / "bad.safetensors")


def test_the_trained_camera_is_recorded_and_hostile_entries_are_refused(tmp_path):
    net = build_network(SAM, seed=3)
    wio.save_file(net, SAM, tmp_path / "cam.safetensors", camera_hfov_deg=120.0)
    wio.save_file(net, SAM, tmp_path / "plain.safetensors")
    assert wio.read_file_camera(tmp_path / "cam.safetensors") == 120.0
    assert wio.read_file_camera(tmp_path / "plain.safetensors") is None  # files older than the entry say nothing
    assert wio.camera_for(tmp_path / "cam.safetensors", 90.0) == 120.0
    assert wio.camera_for(tmp_path / "plain.safetensors", 90.0) == 90.0 and wio.camera_for(None, 75.0) == 75.0
    assert wio.read_header_camera(wio.to_bytes(net, SAM, 90.0)) == 90.0
    wio.load_file(tmp_path / "cam.safetensors", SAM)  # the entry does not change what loads
    bad = ("__import__('os')", "nan", "1e9", "5", "")
    assert_entry_refused(net, tmp_path, "camera_hfov_deg", bad, "must be a number of degrees in", wio.read_file_config)
    with pytest.raises(wio.WeightsError, match="camera_hfov_deg"):
        wio.to_bytes(net, SAM, 400.0)


def test_the_reward_window_is_recorded_when_given_and_hostile_entries_are_refused(tmp_path):
    net = build_network(SAM, seed=3)
    wio.save_file(net, SAM, tmp_path / "w.safetensors", camera_hfov_deg=150.0, reward_window_fraction=0.078)
    wio.save_file(net, SAM, tmp_path / "plain.safetensors", camera_hfov_deg=150.0)
    assert wio.read_file_window(tmp_path / "w.safetensors") == 0.078
    assert wio.read_file_window(tmp_path / "plain.safetensors") is None  # the paper's window is not recorded
    assert wio.window_for(tmp_path / "w.safetensors", 0.2) == 0.078 and wio.window_for(tmp_path / "plain.safetensors", 0.2) == 0.2
    assert wio.window_for(None, 0.2) == 0.2
    wio.load_file(tmp_path / "w.safetensors", SAM)  # the entry does not change what loads
    bad = ("__import__('os')", "nan", "0", "-0.1", "1.5", "")
    assert_entry_refused(
        net, tmp_path, "reward_window_fraction", bad, "must be a share of the image side in", wio.read_file_camera
    )
    with pytest.raises(wio.WeightsError, match="reward_window_fraction"):
        wio.to_bytes(net, SAM, 150.0, 0.0)


def test_a_push_reads_back_and_bad_pushes_are_named():
    from uav_policy.push import PushService, push_request, read_push

    def read(request):
        return read_push(request, wio.MAX_BYTES)

    def raw(**fields):
        return PushService.Request(**fields)

    p = read(push_request(b"abc", epsilon=0.25, release_stamp_ns=1_500_000_000))
    assert (p.weights, p.epsilon, p.release_stamp_ns) == (b"abc", 0.25, 1_500_000_000)
    assert read(push_request(b"abc")) == type(p)(b"abc", None, None)  # a plain weights push
    blob = wio.to_bytes(build_network(SAM, seed=0), SAM)
    assert read(push_request(blob, 0.5, 7)) == type(p)(blob, 0.5, 7), "the request carries the same push"
    assert read(push_request(None, epsilon=1)).epsilon == 1.0
    assert read(push_request(None, epsilon=0)).epsilon == 0.0, "0 is a rate; only KEEP_EPSILON means unchanged"
    # Refused by the weights' length, before anything of them is read.
    with pytest.raises(ValueError, match=r"weights \(8 bytes\) are more than the 3 bytes allowed"):
        read_push(push_request(b"abcdefgh"), 3)
    with pytest.raises(ValueError, match="an empty push"):
        read(raw())
    for eps in (float("nan"), float("inf"), 1.5, -0.5):
        with pytest.raises(ValueError, match="'epsilon' must lie in"):
            read(raw(epsilon=eps))
    with pytest.raises(ValueError, match="'release_stamp_ns' must be >= 0"):
        read(raw(release_stamp_ns=-2))
    with pytest.raises(ValueError, match="'fly_action' must be an action index >= 0 and come with 'release_stamp_ns'"):
        read(raw(epsilon=0.5, fly_action=1))
    with pytest.raises(ValueError, match="'fly_action' must be an action index >= 0"):
        read(raw(release_stamp_ns=5, fly_action=-3))


def test_a_push_is_taken_only_signed_with_the_runs_key_and_newer_than_the_last(tmp_path):
    import os
    import stat

    from uav_policy.push import load_key, push_request, read_push, verify, write_key

    key = load_key(write_key(tmp_path / "push.key"))
    assert stat.S_IMODE(os.stat(tmp_path / "push.key").st_mode) == 0o600 and len(key) == 32
    blob = wio.to_bytes(build_network(SAM, seed=0), SAM)
    good = read_push(push_request(blob, 0.5, 7, key=key, seq=5), wio.MAX_BYTES)
    verify(key, good, last_seq=4)  # no error
    with pytest.raises(ValueError, match="not newer than 5"):
        verify(key, good, last_seq=5)
    with pytest.raises(ValueError, match="unsigned push refused"):
        verify(key, read_push(push_request(blob, 0.5, 7), wio.MAX_BYTES), last_seq=0)
    with pytest.raises(ValueError, match="signature does not match"):
        verify(b"x" * 32, good, last_seq=0)
    # Every field is covered: the same signature over other weights, epsilon, release or number fails.
    for changed in (
        dataclasses.replace(good, weights=blob[:-1] + b"\0"),
        dataclasses.replace(good, epsilon=0.25),
        dataclasses.replace(good, release_stamp_ns=8),
        dataclasses.replace(good, seq=6),
    ):
        with pytest.raises(ValueError, match="signature does not match"):
            verify(key, changed, last_seq=0)
    os.chmod(tmp_path / "push.key", 0o644)
    with pytest.raises(ValueError, match="can be read by others"):
        load_key(tmp_path / "push.key")
    with pytest.raises(ValueError, match="No such file"):
        load_key(tmp_path / "missing.key")


def test_a_weights_folder_stands_for_its_files_in_name_order(tmp_path):
    for name in ("b.safetensors", "a.safetensors", "notes.md"):
        (tmp_path / name).write_bytes(b"x")
    assert wio.parse_files(f"{tmp_path}, c.safetensors") == [
        str(tmp_path / "a.safetensors"),
        str(tmp_path / "b.safetensors"),
        "c.safetensors",
    ]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no .safetensors file"):
        wio.parse_files(str(tmp_path / "empty"))
