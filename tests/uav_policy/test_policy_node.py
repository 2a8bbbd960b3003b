"""Integration: installed sim_node + policy_node in lockstep, observed and pushed to with rclpy."""

import array
import itertools
import signal
import time

import numpy as np
import pytest
import torch
from builtin_interfaces.msg import Time
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import SetParameters
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from sensor_msgs.msg import Image

from conftest import deep_qos, run_to_exit, start_up_error
from uav_common import contract
from uav_interfaces.msg import ActionValues, AttentionWeights
from uav_policy import weights as wio
from uav_policy.networks import NetConfig, build_network
from uav_policy.policy_node import PolicyNode
from uav_policy.push import PushService, load_key, push_request, write_key

SAM = NetConfig(model="sam")


class Watch:
    def __init__(self, ros, actions_only=False):
        # rclpy's spin_once takes one callback at a time: subscribe only to what a test reads.
        self.frames, self.actions, self.att, self.q = [], [], [], []
        n, qos = ros.node, deep_qos()
        n.create_subscription(TwistStamped, contract.ACTION_TOPIC, self.actions.append, qos)
        if actions_only:
            return
        n.create_subscription(Image, contract.DEPTH_TOPIC, self.frames.append, qos)
        n.create_subscription(Image, contract.ATTENTION_TOPIC, self.att.append, 10)
        n.create_subscription(ActionValues, contract.Q_VALUES_TOPIC, self.q.append, 10)

    def frame_stamps(self):
        return [contract.stamp_ns(m.header.stamp) for m in self.frames]

    def action_stamps(self):
        return [contract.stamp_ns(m.header.stamp) for m in self.actions]


def push_args(ros):
    """policy_node arguments to take pushes signed with this test's key (written on first use)."""
    key = ros.tmp / "push.key"
    if not key.exists():
        write_key(key)
    return ("-p", "accept_pushes:=true", "-p", f"push_key_file:={key}", "-p", "safety:=false", "-p", "shield:=never")


IDEAL_87 = ("-p", "sensor:=ideal", "-p", "hfov_deg:=87.0")  # the packaged weights' field of view, exact depth


def start_pair(ros, *policy_args, sim_args=()):
    """sim_node and a policy_node that takes this test's pushes."""
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.5", *sim_args)
    return ros.start("uav_policy", "policy_node", *push_args(ros), *policy_args)


def insight_said(ros) -> list[dict]:
    """policy_node's /diagnostics values, one dict per report."""
    from diagnostic_msgs.msg import DiagnosticArray

    said = []
    ros.node.create_subscription(
        DiagnosticArray,
        contract.DIAGNOSTICS_TOPIC,
        lambda m: said.extend({kv.key: kv.value for kv in s.values} for s in m.status if s.name == "uav_policy"),
        10,
    )
    return said


def test_policy_answers_each_frame_once_and_explains_it(ros):
    w = Watch(ros)
    said = insight_said(ros)
    # An ideal camera of the packaged weights' field of view, at their input size: frames are the input as they are,
    # so the maps' absolute scale can be checked exactly (a camera's mapping: the camera tests below).
    proc = start_pair(ros, "-p", "model:=sam", "-p", "insight_every:=2", sim_args=IDEAL_87)
    assert ros.spin_until(lambda: len(w.actions) >= 300, 60), ros.log_of(proc)
    ros.spin_for(0.3)
    acts = w.action_stamps()
    assert len(acts) == len(set(acts)), "a frame was answered more than once"
    frames = sorted(set(w.frame_stamps()))
    # Every action answers a published frame, and every frame but the newest got an answer.
    # Topics are ordered only within themselves: an action may arrive here before its frame does.
    # Our reader may also match the simulator's publisher after the policy's: from the first frame heard on.
    assert {a for a in acts if frames[0] <= a <= frames[-1]} <= set(frames)
    assert all(a - frames[-1] <= 1_000_000_000 for a in acts), "an action answered a frame never published"
    answered = set(acts)
    # Frames newer than the newest action read here may have their answer still in flight, and
    # our reader may match the policy's publisher after the simulator's (discovery order: one CI
    # run missed the early actions). So: from the first action heard on (300 or more of them), no
    # frame goes unanswered.
    missing = [f for f in frames if min(acts) <= f <= max(acts) and f not in answered]
    assert not missing, f"unanswered frames {missing[:5]} (of {len(frames)}; newest action {max(acts)})"
    att = {contract.stamp_ns(m.header.stamp): m for m in w.att}
    frame_msgs = {contract.stamp_ns(m.header.stamp): m for m in w.frames}
    common = set(att) & set(frame_msgs)
    assert len(common) > 100
    for s in list(common)[:20]:
        a, f = att[s], frame_msgs[s]
        assert (a.width, a.height, a.encoding, a.header.frame_id) == (f.width, f.height, "32FC1", f.header.frame_id)
        amap = contract.image_to_depth(a)
        # The mass each region receives relative to a uniform share: no per-frame stretch, so it averages 1.
        assert amap.min() >= 0.0 and abs(float(amap.mean()) - 1.0) < 1e-3
    q = w.q[-1]
    assert len(q.values) == 4 and q.actions[3] == "a3_forward_2mps" and q.header.stamp in [f.header.stamp for f in w.frames]
    assert 0 <= q.action < 4
    assert ros.spin_until(lambda: said and int(said[-1].get("insight_frames", 0)) >= 50, 10), said[-1:]
    last = said[-1]
    assert last["explained_by"] == "attention" and int(last["insight_frames"]) >= 50
    # The shipped SAM's attention forms its Q-values (the attend readout): not uniform, and it follows the
    # frames (a uniform map is 1 everywhere; the max readout's stayed within 0.93-1.08 on every frame).
    assert float(last["insight_entropy"]) < 0.9, last
    maps = [contract.image_to_depth(att[s]) for s in sorted(common)[-20:]]
    assert max(float(np.abs(m - maps[0]).max()) for m in maps[1:]) > 0.25, "the attention map never changed"


def test_the_cnn_explains_its_decisions_with_saliency_on_its_own_topics(ros):
    """The CNN has no attention: Grad-CAM saliency on saliency and saliency/overlay (never called attention),
    measured on /diagnostics like SAM's attention; the overlay is upscaled, with a legend."""
    maps, overlays, atts = [], [], []
    ros.node.create_subscription(Image, contract.SALIENCY_TOPIC, maps.append, 10)
    ros.node.create_subscription(Image, contract.SALIENCY_OVERLAY_TOPIC, overlays.append, 10)
    ros.node.create_subscription(Image, contract.ATTENTION_TOPIC, atts.append, 10)
    said = insight_said(ros)
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.5", *IDEAL_87)
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn", "-p", "insight_every:=1")
    enough = lambda: len(maps) >= 10 and len(overlays) >= 3 and said and int(said[-1].get("insight_frames", 0)) >= 10  # noqa: E731
    assert ros.spin_until(enough, 60), ros.log_of(proc)[-2000:]
    assert not atts, "the CNN publishes no attention"
    amaps = [contract.image_to_depth(m) for m in maps[-10:]]
    assert all(abs(float(m.mean()) - 1.0) < 1e-3 for m in amaps), "an absolute scale: mass relative to uniform"
    assert any(not np.allclose(amaps[0], m) for m in amaps[1:]), "the saliency follows the frames"
    o = overlays[-1]
    assert o.encoding == "rgb8" and o.width >= 256 and o.height >= 256 + 40
    assert said[-1]["explained_by"] == "saliency (Grad-CAM)" and float(said[-1]["insight_entropy"]) < 1.0


def test_a_stalled_policy_does_not_answer_a_repeated_frame_twice(ros):
    """The lockstep sim says a frame again when no command came for lockstep_republish_s. A policy
    that was only slow (its command had a listener) must not answer again: the sim would step
    twice, and from then on every command would act on a later frame than the one it answered."""
    actions, odoms = {}, {}
    qos = deep_qos()
    ros.node.create_subscription(
        TwistStamped, contract.ACTION_TOPIC, lambda m: actions.setdefault(contract.stamp_ns(m.header.stamp), m.twist), qos
    )
    ros.node.create_subscription(
        Odometry, contract.ODOM_TOPIC, lambda m: odoms.setdefault(contract.stamp_ns(m.header.stamp), m.twist.twist), qos
    )
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.05")
    policy = ros.start(
        "uav_policy", "policy_node", "-p", "model:=cnn", "-p", "safety:=false", "-p", "shield:=never"
    )  # the network's own commands
    assert ros.spin_until(lambda: len(actions) >= 30, 60), ros.log_of(policy)
    policy.send_signal(signal.SIGSTOP)  # a busy machine: the sim says its frame again about 10 times
    ros.spin_for(0.5)
    policy.send_signal(signal.SIGCONT)
    step_ns = 500_000_000
    # Steps whose odometry and the answer to the frame before both reached this reader (it may match the
    # publishers late, and a loaded machine may drop a message of a deep queue): at least 60 after the stall.
    pairs = lambda: [(stamp, odoms[stamp], actions[stamp - step_ns]) for stamp in sorted(odoms) if stamp - step_ns in actions]  # noqa: E731
    assert ros.spin_until(lambda: len(actions) >= 80 and len(pairs()) >= 60, 60), ros.log_of(policy)
    for stamp, executed, answered in pairs():  # the command the policy chose for the previous frame
        assert (executed.linear.x, executed.angular.z) == (answered.linear.x, answered.angular.z), (
            f"the step to {stamp} executed a command that was not the answer to the frame before it"
        )


_push_seq = itertools.count(1)


def call_push(ros, blob: bytes | None, timeout_s=30.0, key: bytes | None | str = "test", **extra):
    """A push signed with this test's key (`key`: another key, or None for an unsigned push)."""
    key = load_key(ros.tmp / "push.key") if key == "test" else key
    return send_push(ros, push_request(blob, key=key, seq=next(_push_seq) if key else None, **extra), timeout_s)


def send_push(ros, request, timeout_s=30.0):
    client = ros.node.create_client(PushService, contract.PUSH_WEIGHTS_SERVICE)
    assert client.wait_for_service(timeout_sec=20)
    fut = client.call_async(request)
    assert ros.spin_until(fut.done, timeout_s)
    return fut.result()


HEAVY = NetConfig(model="sam", conv_channels=(16,), d_model=384, heads=6, relational_blocks=2, mlp_hidden=96)


def forcing_action(index: int, camera_hfov_deg: float | None = None, cfg: NetConfig = SAM, lead: float = 5.0) -> bytes:
    """Weights whose advantage stream always prefers `index` (by `lead` over the other actions)."""
    net = build_network(cfg, seed=0)
    with torch.no_grad():
        last = net.dueling_head.advantage[-1]
        last.weight.zero_()
        last.bias.zero_()
        last.bias[index] = lead
    return wio.to_bytes(net, cfg, camera_hfov_deg)


def test_layer_sizes_come_from_the_weights_file_and_from_pushes(ros, tmp_path):
    """SAM's layer sizes are no parameter: policy_node takes them from the weights file (here two
    heads, two relational blocks) and flies it; a push (the trainer owns the network) may bring others."""
    other = NetConfig(model="sam", d_model=24, heads=2, relational_blocks=2, mlp_hidden=32)
    path = tmp_path / "other_sizes.safetensors"
    path.write_bytes(forcing_action(0, cfg=other))
    w = Watch(ros, actions_only=True)
    weights = []
    ros.node.create_subscription(AttentionWeights, contract.ATTENTION_WEIGHTS_TOPIC, weights.append, 10)
    proc = start_pair(ros, "-p", f"weights:={path}")
    assert ros.spin_until(lambda: len(w.actions) >= 20 and weights, 60), ros.log_of(proc)
    assert all((m.twist.linear.x, m.twist.angular.z) == (1.0, 0.0) for m in w.actions[-10:]), "the file forces a0"
    assert weights[-1].heads == 2, "two attention heads"
    n = sum(p.numel() for p in build_network(other).parameters())
    assert f"model sam ({n} parameters, weights from {path}" in ros.log_of(proc)
    r = call_push(ros, forcing_action(3))  # the default sizes
    assert r.success, r.message
    all_a3 = lambda: len(w.actions) >= 20 and all(m.twist.linear.x == 2.0 for m in w.actions[-20:])  # noqa: E731
    assert ros.spin_until(all_a3, 20), "after the push every action should be a3 (forward 2 m/s)"
    # Messages from before the push may still be queued here: wait for a three-head one.
    assert ros.spin_until(lambda: weights[-1].heads == 3, 10), "three heads again"


def test_a_list_of_weights_files_flies_as_one_policy_on_the_mean_q_values(ros, tmp_path):
    """weights:=b,a: b alone would fly a0 (by 2), a alone a3 (by 5); their mean Q picks a3. The
    attention carries both members' heads; a push replaces the ensemble."""
    a, b = tmp_path / "a3.safetensors", tmp_path / "a0.safetensors"
    a.write_bytes(forcing_action(3, camera_hfov_deg=120.0))
    b.write_bytes(forcing_action(0, camera_hfov_deg=120.0, lead=2.0))
    w = Watch(ros, actions_only=True)
    heads = []
    ros.node.create_subscription(AttentionWeights, contract.ATTENTION_WEIGHTS_TOPIC, heads.append, 10)
    proc = start_pair(ros, "-p", f"weights:={b},{a}")
    assert ros.spin_until(lambda: len(w.actions) >= 20 and heads, 60), ros.log_of(proc)
    assert all(m.twist.linear.x == 2.0 for m in w.actions[-10:]), "the mean Q-values prefer a3 (forward 2 m/s)"
    assert heads[-1].heads == 2 * SAM.heads, "each member's heads"
    assert f"an ensemble of 2 weights files acting on their mean Q-values: {b.name}, {a.name} in {tmp_path}" in ros.log_of(proc)
    r = call_push(ros, forcing_action(0))
    assert r.success, r.message
    all_a0 = lambda: len(w.actions) >= 20 and all(m.twist.linear.x == 1.0 for m in w.actions[-20:])  # noqa: E731
    assert ros.spin_until(all_a0, 20), "after the push every action should be a0 (forward 1 m/s)"
    assert ros.spin_until(lambda: heads[-1].heads == SAM.heads, 10), "one network's heads again"
    assert "pushed weights replace the ensemble of 2 networks" in ros.log_of(proc)


def test_bad_pushes_are_rejected_while_control_continues_and_a_good_push_changes_actions(ros):
    w = Watch(ros, actions_only=True)
    proc = start_pair(ros, "-p", "model:=sam")
    assert ros.spin_until(lambda: len(w.actions) >= 20, 60), ros.log_of(proc)
    good = forcing_action(3)
    tensors = st_load(good)
    name = "dueling_head.value.2.weight"
    meta = {"format": wio.FORMAT, "config": SAM.to_json()}
    bad_pushes = {
        "corrupt": b"\x13" * 5000,
        "truncated": good[: len(good) // 3],
        "wrong shape": st_save(dict(tensors, **{name: torch.zeros(2, 2)}), metadata=meta),
        "non-finite": st_save(dict(tensors, **{name: torch.full_like(tensors[name], float("inf"))}), metadata=meta),
        "other architecture": forcing_action_cnn(),
        "hostile camera entry": st_save(tensors, metadata=dict(meta, camera_hfov_deg="__import__('os')")),
        # 1,024 nodes, 6 heads, 2 blocks: about 500 times the flown network's operations a frame (6 GFLOP).
        "over the control period": wio.to_bytes(build_network(HEAVY, seed=0), HEAVY),
    }
    reasons = {}
    for label, blob in bad_pushes.items():
        before = len(w.actions)
        r = call_push(ros, blob)
        assert not r.success and r.message, f"{label} push was accepted"
        reasons[label] = r.message
        assert ros.spin_until(lambda b=before: len(w.actions) > b + 5, 10), f"control stalled after the {label} push"
    assert "control period (control_rate_hz)" in reasons["over the control period"], reasons
    # Refused by its length before anything of the weights is read (over the 64 MiB limit), or by a field no
    # trainer sends.
    hostile = {
        "oversize": (PushService.Request(weights=array.array("B", bytes(wio.MAX_BYTES + 8))), "more than the 67108864"),
        "malformed": (PushService.Request(epsilon=float("nan")), "'epsilon' must lie in [0, 1]"),
    }
    for label, (request, why) in hostile.items():
        before = len(w.actions)
        r = send_push(ros, request, timeout_s=60)
        assert not r.success and why in r.message, (label, r.message)
        assert ros.spin_until(lambda b=before: len(w.actions) > b + 5, 10), f"control stalled after the {label} push"
    assert proc.poll() is None
    assert any(m.twist.linear.x != 2.0 for m in w.actions[-20:]), "the random net should not always pick a3"
    r = call_push(ros, good)
    assert r.success, r.message
    # The reader lags the 250 Hz loop: wait until what arrives is post-push.
    all_a3 = lambda: len(w.actions) >= 20 and all(m.twist.linear.x == 2.0 for m in w.actions[-20:])  # noqa: E731
    assert ros.spin_until(all_a3, 20), "after the push every action should be a3 (forward 2 m/s)"
    log = ros.log_of(proc)
    assert "weights push rejected" in log and "'camera_hfov_deg' must be a number" in log
    assert "trained with a 87 deg camera)" in log, "the start-up line names the packaged weights' camera"
    assert "depth/camera_info says" not in log, "the packaged weights' camera is the sim's default: no warning"
    # Weights trained behind another camera still fly, with a warning naming the camera to use.
    r = call_push(ros, forcing_action(3, camera_hfov_deg=90.0))
    assert r.success, r.message
    assert ros.spin_until(lambda: "trained with a 90 deg camera" in ros.log_of(proc), 10), ros.log_of(proc)
    assert "depth/camera_info says 87.0 deg: frames cover" in ros.log_of(proc)


def forcing_action_cnn() -> bytes:
    cfg = NetConfig(model="cnn")
    return wio.to_bytes(build_network(cfg, seed=0), cfg)


def test_policy_start_up_errors(tmp_path):
    # The process's exit path once; the other bad parameters with the node built in this process.
    r = run_to_exit("uav_policy", "policy_node", "-p", "model:=transformer")
    assert r.returncode == 2 and "[FATAL] parameter 'model'" in r.stderr and "Traceback" not in r.stderr
    err = start_up_error(PolicyNode, "-p", f"weights:={tmp_path / 'missing.safetensors'}")
    assert "parameter 'weights'" in err and "cannot read" in err
    cnn = tmp_path / "cnn.safetensors"
    cnn.write_bytes(forcing_action_cnn())
    err = start_up_error(PolicyNode, "-p", "model:=sam", "-p", f"weights:={cnn}")
    assert "model 'cnn'" in err and "runs model 'sam'" in err
    big, cfg84 = tmp_path / "sam84.safetensors", NetConfig(model="sam", height=84, width=84)
    wio.save_file(build_network(cfg84, seed=0), cfg84, big)
    err = start_up_error(PolicyNode, "-p", f"weights:={big}")
    assert "parameter 'weights'" in err and "set input_height:=84 input_width:=84" in err
    deep, cfg10 = tmp_path / "sam10.safetensors", NetConfig(model="sam", frames=10)
    wio.save_file(build_network(cfg10, seed=0), cfg10, deep)
    err = start_up_error(PolicyNode, "-p", f"weights:={deep}")
    assert "the file stacks 10 frames: set frame_stack:=10" in err
    assert "input_height" not in err.split("parameter 'weights'")[1]
    # A list of files (an ensemble) must share the model, the layer sizes and the camera.
    sam90, sam120 = tmp_path / "sam90.safetensors", tmp_path / "sam120.safetensors"
    sam90.write_bytes(forcing_action(0, camera_hfov_deg=90.0))
    sam120.write_bytes(forcing_action(0, camera_hfov_deg=120.0))
    for files, says in (
        ([sam120, cnn], "model 'cnn'"),
        ([sam120, big], "set input_height:=84 input_width:=84"),
        ([sam90, sam120], "different cameras (90 deg, 120 deg)"),
        ([sam120, tmp_path / "missing.safetensors"], "cannot read"),
    ):
        err = start_up_error(PolicyNode, "-p", f"weights:={','.join(map(str, files))}")
        assert "parameter 'weights'" in err and says in err, (files, err[-500:])
    err = start_up_error(PolicyNode, "-p", f"weights:={sam90},,{sam90}")
    assert "parameter 'weights': an empty file name in the list" in err
    err = start_up_error(PolicyNode, "-p", "sam_readout:=max")
    assert "parameter 'sam_readout' was removed" in err and "comes from the weights files" in err
    err = start_up_error(PolicyNode, "-p", "ensemble_rule:=median")
    assert "parameter 'ensemble_rule' was removed" in err
    err = start_up_error(PolicyNode, "-p", "epsilon:=1.5")
    assert "epsilon" in err


def test_malformed_frames_are_ignored_counted_and_shown_on_diagnostics(ros):
    """A frame that cannot be read gets no answer, and /diagnostics says so (WARN); good frames
    before and after it are answered."""
    import numpy as np
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from uav_interfaces.msg import StepOutcome

    w = Watch(ros, actions_only=True)
    diag = []
    ros.node.create_subscription(
        DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: diag.extend(s for s in m.status if s.name == "uav_policy"), 10
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, contract.STREAM_QOS)
    pub_out = ros.node.create_publisher(StepOutcome, contract.OUTCOME_TOPIC, contract.STREAM_QOS)
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn")
    assert ros.spin_until(lambda: pub_img.get_subscription_count() and pub_out.get_subscription_count() and diag, 30), ros.log_of(
        proc
    )
    assert diag[-1].level == DiagnosticStatus.OK and diag[-1].message == "waiting for depth frames"

    def send(sec: int, img: Image) -> None:
        img.header.stamp.sec = sec
        pub_out.publish(StepOutcome(header=img.header, beta_m=5.0, max_range_m=10.0))
        pub_img.publish(img)

    good = lambda: contract.depth_to_image(np.full((64, 64), 4.0, np.float32), Time(), "cam")  # noqa: E731
    send(1, good())
    assert ros.spin_until(lambda: len(w.actions) == 1, 10), ros.log_of(proc)
    short = good()
    short.data = short.data[:100]  # says 64x64, carries 25 floats
    wrong = good()
    wrong.encoding = "rgb8"
    narrow = good()
    narrow.step = 4 * 63  # rows shorter than the width says
    empty = good()
    empty.height, empty.data = 0, b""
    absurd = good()
    absurd.height, absurd.width, absurd.step = 1_000_000, 1_000_000, 4_000_000  # 4 TB said, 16 KiB carried
    # Each hostile frame gets no answer, and the valid frame right after it does.
    for sec, bad in enumerate((short, wrong, narrow, empty, absurd), start=2):
        send(10 * sec, bad)
        send(10 * sec + 1, good())
        assert ros.spin_until(lambda sec=sec: w.action_stamps()[-1:] == [(10 * sec + 1) * 10**9], 10), ros.log_of(proc)
    assert w.action_stamps() == [10**9] + [(10 * s + 1) * 10**9 for s in range(2, 7)]  # the malformed frames got no answer
    # What each one is told (the node's warning is throttled: the log shows the first of a burst).
    told = ((wrong, "got 'rgb8'"), (narrow, "step 252 is smaller"), (empty, "empty size 64x0"))
    told += ((absurd, "expected 4000000000000"),)
    for bad, said in told:
        with pytest.raises(ValueError, match=said):
            contract.image_to_depth(bad)
    values = lambda s: {kv.key: kv.value for kv in s.values}  # noqa: E731
    assert ros.spin_until(lambda: values(diag[-1])["malformed_frames"] == "5", 5), [values(d) for d in diag]
    warned = next(d for d in diag if values(d)["malformed_frames"] != "0")  # the two may fall into two reports
    assert warned.level == DiagnosticStatus.WARN and "malformed depth frame(s) ignored" in warned.message, warned.message
    last = values(diag[-1])
    assert last["frames_answered"] == "6" and last["model"] == "cnn" and "packaged pretrained weights" in last["weights"]
    # With no more malformed frames the next report is OK again; the count stays.
    n = len(diag)
    assert ros.spin_until(lambda: len(diag) > n + 1, 5)
    assert diag[-1].level == DiagnosticStatus.OK and values(diag[-1])["malformed_frames"] == "5"
    assert proc.poll() is None and "ignoring malformed depth frame" in ros.log_of(proc)


def test_waiting_for_the_trainer_answers_a_frame_only_once_released_with_the_pushed_weights_and_epsilon(ros):
    """wait_for_trainer (lockstep learning): a frame is held until a push releases its stamp; the push's
    weights and epsilon act on it; refused weights do not hold the frame their push releases."""
    w = Watch(ros)
    proc = start_pair(ros, "-p", "wait_for_trainer:=true", "-p", "wait_for_trainer_timeout_s:=60.0")
    assert ros.spin_until(lambda: len(w.frames) >= 1, 30), ros.log_of(proc)
    ros.spin_for(1.0)
    assert w.actions == [], "a held frame must not be answered before its release"
    first = w.frame_stamps()[0]
    # Pushes not from this run's trainer take nothing and release nothing: unsigned, signed with another key,
    # or a signed push played again.
    r = call_push(ros, forcing_action(3), key=None, epsilon=0.0, release_stamp_ns=first)
    assert not r.success and "unsigned push refused" in r.message, r.message
    r = call_push(ros, forcing_action(3), key=b"k" * 32, epsilon=0.0, release_stamp_ns=first)
    assert not r.success and "signature does not match" in r.message, r.message
    ros.spin_for(1.0)
    assert w.actions == [], "a refused push released a frame"
    good = push_request(
        forcing_action(3), epsilon=0.0, release_stamp_ns=first, key=load_key(ros.tmp / "push.key"), seq=next(_push_seq)
    )
    r = send_push(ros, good)
    assert r.success, r.message
    r = send_push(ros, good)  # the same push played again
    assert not r.success and "not newer" in r.message, r.message
    assert ros.spin_until(lambda: len(w.actions) == 1, 10)
    assert contract.stamp_ns(w.actions[0].header.stamp) == first and w.actions[0].twist.linear.x == 2.0, "a3, pushed"
    ros.spin_for(1.0)
    assert len(w.actions) == 1, "the next frame waits for its own release"
    # A release whose weights are refused still releases (it was held up to the timeout before): the
    # frame is answered at once on the weights in use.
    second = min(s for s in w.frame_stamps() if s > first)
    r = call_push(ros, forcing_action_cnn(), release_stamp_ns=second)
    assert not r.success and "its frame release was applied" in r.message, r.message
    assert ros.spin_until(lambda: len(w.actions) == 2, 10), "a refused push's release must not wait for the timeout"
    assert contract.stamp_ns(w.actions[1].header.stamp) == second and w.actions[1].twist.linear.x == 2.0, "a3, in use"
    # A release far beyond every frame seen would answer frames without their updates: refused, nothing taken.
    r = call_push(ros, None, epsilon=1.0, release_stamp_ns=max(w.frame_stamps()) + 60 * 10**9)
    assert not r.success and "beyond the newest frame seen" in r.message, r.message
    ros.spin_for(1.0)
    assert len(w.actions) == 2, "a refused release released a frame"
    # Releases go by stamp: one a few steps ahead releases every frame up to it, here with no weights at all.
    while len(w.actions) < 20:
        before = len(w.actions)  # the answers may come while the push is answered
        assert call_push(ros, None, epsilon=0.0, release_stamp_ns=max(w.frame_stamps()) + 2 * 10**9).success
        assert ros.spin_until(lambda n=before: len(w.actions) > n, 10), "released frames are answered"
    assert all(m.twist.linear.x == 2.0 for m in w.actions), "epsilon 0 with the pushed weights: always a3"
    assert "answering each frame once trainer_node releases it (lockstep learning)" in ros.log_of(proc)
    bad = call_push(ros, None, epsilon=1.5)
    assert not bad.success and "'epsilon' must lie in [0, 1]" in bad.message
    # The epsilon parameter shows what the node acts with (ros2 param get, Foxglove); a user cannot set it.
    assert call_push(ros, None, epsilon=0.25).success
    assert get_parameter(ros, "epsilon") == 0.25
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue

    client = ros.node.create_client(SetParameters, "/policy_node/set_parameters")
    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=0.9)
    answer = ros.call(client, SetParameters.Request(parameters=[Parameter(name="epsilon", value=value)]))
    res = answer.results[0]
    assert not res.successful and "is set by the trainer's pushes" in res.reason, res.reason
    assert get_parameter(ros, "epsilon") == 0.25


def get_parameter(ros, name: str):
    from rcl_interfaces.srv import GetParameters

    answer = ros.call(ros.node.create_client(GetParameters, "/policy_node/get_parameters"), GetParameters.Request(names=[name]))
    return answer.values[0].double_value


def test_an_unreleased_frame_is_answered_after_the_timeout_with_a_warning(ros):
    w = Watch(ros, actions_only=True)
    proc = start_pair(ros, "-p", "wait_for_trainer:=true", "-p", "wait_for_trainer_timeout_s:=0.5")
    assert ros.spin_until(lambda: len(w.actions) >= 3, 30), ros.log_of(proc)
    assert "trainer_node did not release the frame" in ros.log_of(proc) and "no longer in lockstep" in ros.log_of(proc)


def test_a_flying_policy_takes_no_pushes_and_no_parameter_changes(ros):
    """Without accept_pushes (flying) there is no push service, epsilon cannot be set at run time, and
    wait_for_trainer without accept_pushes, or accept_pushes without a key, stop the node at start-up."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue

    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn")
    client = ros.node.create_client(SetParameters, "/policy_node/set_parameters")
    assert client.wait_for_service(timeout_sec=30), ros.log_of(proc)
    services = dict(ros.node.get_service_names_and_types())
    assert "/policy_node/get_parameters" in services and contract.PUSH_WEIGHTS_SERVICE not in services
    assert "/" + contract.PUSH_WEIGHTS_SERVICE not in services, sorted(services)
    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=1.0)
    answer = ros.call(client, SetParameters.Request(parameters=[Parameter(name="epsilon", value=value)]))
    res = answer.results[0]
    assert not res.successful and "fixed at start-up while flying" in res.reason, res.reason
    answer = ros.call(client, SetParameters.Request(parameters=[Parameter(name="step_duration_s", value=value)]))
    res = answer.results[0]
    assert not res.successful and "read-only" in res.reason, res.reason
    r = run_to_exit("uav_policy", "policy_node", "-p", "wait_for_trainer:=true")
    assert r.returncode == 2 and "needs accept_pushes:=true" in r.stderr, r.stderr
    r = run_to_exit("uav_policy", "policy_node", "-p", "accept_pushes:=true")
    assert r.returncode == 2 and "needs 'push_key_file'" in r.stderr, r.stderr
    r = run_to_exit("uav_policy", "policy_node", "-p", "accept_pushes:=true", "-p", "push_key_file:=/tmp/k")
    assert r.returncode == 2 and "set safety:=false (train does)" in r.stderr, "training flies the network's own actions"


def test_stamps_going_back_or_from_the_future_restart_the_join_and_frames_without_outcome_warn(ros):
    """A restarted simulator (stamps begin again) and a glitch stamped far in the future are answered
    past, counted on /diagnostics; frames that are never answered turn /diagnostics to WARN."""
    import numpy as np
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from uav_interfaces.msg import StepOutcome

    w = Watch(ros, actions_only=True)
    diag = []
    ros.node.create_subscription(
        DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: diag.extend(s for s in m.status if s.name == "uav_policy"), 10
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, deep_qos())
    pub_out = ros.node.create_publisher(StepOutcome, contract.OUTCOME_TOPIC, deep_qos())
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn")
    assert ros.spin_until(lambda: pub_img.get_subscription_count() and pub_out.get_subscription_count() and diag, 30)

    def send(sec: int, outcome: bool = True) -> None:
        img = contract.depth_to_image(np.full((64, 64), 4.0, np.float32), Time(sec=sec), "cam")
        if outcome:
            pub_out.publish(StepOutcome(header=img.header, beta_m=5.0, max_range_m=10.0))
        pub_img.publish(img)

    sent = [10, 11, 12, 0, 1, 1_000_000, 2, 3]  # a restart at 0, a glitch from the future at 1e6 s
    for k, sec in enumerate(sent):
        send(sec)
        assert ros.spin_until(lambda k=k: len(w.actions) == k + 1, 10), (sec, ros.log_of(proc)[-2000:])
    assert [s // 1_000_000_000 for s in w.action_stamps()] == sent
    values = lambda s: {kv.key: kv.value for kv in s.values}  # noqa: E731
    assert ros.spin_until(lambda: values(diag[-1])["stamp_restarts"] == "2", 5), [values(d) for d in diag[-2:]]
    assert "the source restarted" in ros.log_of(proc)
    for sec in (20, 21, 22):  # a simulator's frames whose step_outcome never comes get no answer
        send(sec, outcome=False)
    assert ros.spin_until(lambda: diag[-1].level == DiagnosticStatus.WARN and "none answered" in diag[-1].message, 5), [
        (d.level, d.message) for d in diag[-3:]
    ]
    assert values(diag[-1])["frames_received"] == str(len(sent) + 3) and len(w.actions) == len(sent)


def test_a_restarted_simulator_is_answered_again(ros):
    w = Watch(ros, actions_only=True)
    sim = ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.5", name="sim1")
    ros.start("uav_policy", "policy_node", "-p", "model:=cnn")
    assert ros.spin_until(lambda: len(w.actions) >= 20, 60)
    assert ros.stop(sim) == 0
    last = max(w.action_stamps())
    n = len(w.actions)
    ros.start("uav_sim", "sim_node", "-p", "lockstep_republish_s:=0.5", name="sim2")
    after = lambda: [s for s in w.action_stamps()[n:] if s < last]  # noqa: E731
    assert ros.spin_until(lambda: len(after()) >= 10, 30), "policy_node did not answer the restarted simulator"
    assert after()[:3] == [0, 500_000_000, 1_000_000_000], "answered from the new simulator's first frame on"


def test_two_cameras_on_one_topic_are_never_stacked_together(ros):
    """Frames of a second camera (another frame_id) on the depth topic are dropped and counted, with an ERROR on
    /diagnostics: the network input after them is the first camera's alone. Once the first camera has been silent
    for camera_switch_s, the second is taken with a new stack."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from uav_interfaces.msg import StepOutcome

    w = Watch(ros)
    diag = []
    ros.node.create_subscription(
        DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: diag.extend(s for s in m.status if s.name == "uav_policy"), 10
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, contract.STREAM_QOS)
    pub_out = ros.node.create_publisher(StepOutcome, contract.OUTCOME_TOPIC, contract.STREAM_QOS)
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn", "-p", "camera_switch_s:=1.0")
    ready = lambda: pub_img.get_subscription_count() and pub_out.get_subscription_count() and diag  # noqa: E731
    assert ros.spin_until(ready, 30), ros.log_of(proc)

    def send(sec: int, camera: str, depth_m: float, outcome: bool = True) -> None:
        img = contract.depth_to_image(np.full((64, 64), depth_m, np.float32), Time(sec=sec), camera)
        if outcome:
            pub_out.publish(StepOutcome(header=img.header, beta_m=5.0, max_range_m=10.0))
        pub_img.publish(img)

    values = lambda s: {kv.key: kv.value for kv in s.values}  # noqa: E731
    for sec in (1, 2):
        send(sec, "cam_a", 4.0)
        assert ros.spin_until(lambda n=sec: len(w.q) == n, 10), ros.log_of(proc)
    for sec in (3, 4):  # the second camera, its frames alternating with the first's
        send(sec, "cam_b", 0.6, outcome=False)
        ros.spin_for(0.2)
        send(sec + 2, "cam_a", 4.0)
        assert ros.spin_until(lambda n=sec: len(w.q) == n, 10), ros.log_of(proc)
    assert w.action_stamps() == [s * 10**9 for s in (1, 2, 5, 6)], "the other camera's frames are not answered"
    assert list(w.q[2].values) == list(w.q[3].values) == list(w.q[1].values), "the stack holds the first camera alone"
    assert ros.spin_until(lambda: values(diag[-1])["other_camera_frames_dropped"] == "2", 5), [values(d) for d in diag]
    last = diag[-1]
    assert last.level == DiagnosticStatus.ERROR and "another camera (cam_b)" in last.message, last.message
    assert values(last)["camera_frame_id"] == "cam_a" and values(last)["other_camera_frame_ids"] == "cam_b"
    assert "dropping depth frames of camera 'cam_b'" in ros.log_of(proc)
    # The first camera stops for good: after camera_switch_s the second is taken, on a stack of its own.
    ros.spin_for(1.2)
    for sec in (7, 8):
        send(sec, "cam_b", 0.6)
        assert ros.spin_until(lambda n=sec - 2: len(w.q) == n, 10), ros.log_of(proc)
    assert list(w.q[4].values) == list(w.q[5].values) != list(w.q[3].values), "a new stack: the second camera's frames alone"
    assert ros.spin_until(lambda: values(diag[-1])["camera_switches"] == "1", 5)
    assert values(diag[-1])["camera_frame_id"] == "cam_b" and "taking it, with a new frame stack" in ros.log_of(proc)
    assert ros.spin_until(lambda: diag[-1].level != DiagnosticStatus.ERROR, 5), "the ERROR lasts while foreign frames come"


def test_a_depth_camera_alone_is_flown_behind_the_shield_and_the_safety_layer(ros):
    """No simulator: a RealSense-like stream (848x480 16UC1 millimetres, sensor-data QoS, an 87 deg
    CameraInfo) with odometry is answered on cmd_vel_stamped, shielded (shield auto); a wall at 0.4 m gives no
    forward command; frames without odometry give none either (the shield vouches for nothing); when frames stop,
    stop commands (zero velocity) follow within the timeout, counted on /diagnostics; a CameraInfo with a
    zero focal length is counted and ignored."""
    import math

    import numpy as np
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo

    cmds = []
    ros.node.create_subscription(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, cmds.append, deep_qos())
    diag = []
    ros.node.create_subscription(
        DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: diag.extend(s for s in m.status if s.name == "uav_policy"), 10
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, contract.SENSOR_QOS)
    pub_info = ros.node.create_publisher(CameraInfo, contract.CAMERA_INFO_TOPIC, contract.SENSOR_QOS)
    pub_odom = ros.node.create_publisher(Odometry, contract.ODOM_TOPIC, contract.SENSOR_QOS)
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=cnn", "-p", "publish_stamped:=true", "-p", "frame_timeout_s:=0.5")
    subscribed = lambda: all(p.get_subscription_count() for p in (pub_img, pub_info, pub_odom))  # noqa: E731
    assert ros.spin_until(lambda: subscribed() and diag, 30)
    f = 424 / math.tan(math.radians(87 / 2))
    info = CameraInfo(width=848, height=480, k=[f, 0.0, 424.0, 0.0, f, 240.0, 0.0, 0.0, 1.0])
    clock = ros.node.get_clock()

    def answering(stamps):
        return [c for c in cmds if contract.stamp_ns(c.header.stamp) in stamps]

    def publish_odometry(stamp) -> None:
        odom = Odometry()
        odom.header.stamp, odom.pose.pose.position.z, odom.pose.pose.orientation.w = stamp, 1.0, 1.0
        pub_odom.publish(odom)

    def stream(depth_m: float, answers: int, odometry: bool = True, counts=lambda c: True) -> set[int]:
        """Frames of a wall at depth_m at 15 Hz (with the vehicle's odometry, hovering at the origin) until `answers`
        of them are answered so that `counts` (best effort loses some, more on a loaded machine); their stamps."""
        frame = np.full((480, 848), depth_m, np.float32)
        stamps = set()
        deadline = time.monotonic() + 30
        while len([c for c in answering(stamps) if counts(c)]) < answers and time.monotonic() < deadline:
            stamp = clock.now().to_msg()
            info.header.stamp = stamp
            if odometry:
                publish_odometry(stamp)
            pub_info.publish(info)
            pub_img.publish(contract.depth_to_image(frame, stamp, "camera_depth_optical_frame", "16UC1"))
            stamps.add(contract.stamp_ns(stamp))
            ros.spin_for(1 / 15)
        ros.spin_for(0.2)  # the answer to the last frame
        return stamps

    for _ in range(3):
        pub_info.publish(CameraInfo(width=848, height=480))  # a zero focal length: counted, ignored
        ros.spin_for(0.05)
    # The shield has odometry before the first frame (a frame may overtake the odometry stamped with it, and then
    # takes the newest one within odom_timeout_s).
    values = lambda s: {kv.key: kv.value for kv in s.values}  # noqa: E731
    heard = lambda: diag and int(values(diag[-1]).get("shield_odometry_received", 0)) > 0  # noqa: E731
    deadline = time.monotonic() + 30
    while not heard() and time.monotonic() < deadline:
        publish_odometry(clock.now().to_msg())
        ros.spin_for(0.1)
    assert heard(), [values(d) for d in diag[-1:]]
    far = stream(6.0, 5, counts=lambda c: c.twist.linear.x > 0)
    assert len([c for c in answering(far) if c.twist.linear.x > 0]) >= 5, ros.log_of(proc)[-3000:]
    # The packaged actions all fly forward, but where the shield had no fresh odometry: a frame can overtake its own
    # odometry (another topic) and is then judged with the one before, which a stall of this test's loop (a loaded
    # machine) can leave older than odom_timeout_s. The node counts each such frame: no other answer may stop.
    held = [c for c in answering(far) if c.twist.linear.x <= 0]
    covering = lambda: diag and int(values(diag[-1])["frames_answered"]) >= len(answering(far))  # noqa: E731
    assert ros.spin_until(covering, 5), [sorted(values(d).items()) for d in diag[-1:]]
    assert len(held) <= int(values(diag[-1])["shield_frames_without_odometry"]), sorted(values(diag[-1]).items())
    near = stream(0.4, 5)
    assert len(answering(near)) >= 5, ros.log_of(proc)[-3000:]
    assert all(c.twist.linear.x == 0.0 for c in answering(near)), [c.twist.linear.x for c in answering(near)]
    ros.spin_for(0.6)  # the last odometry is older than odom_timeout_s (0.5 s) from now on
    blind = stream(6.0, 5, odometry=False)
    assert len(answering(blind)) >= 5, ros.log_of(proc)[-3000:]
    assert all(c.twist.linear.x == 0.0 for c in answering(blind)), "no odometry: the shield vouches for nothing"
    assert "shield: no odometry within odom_timeout_s of the frame" in ros.log_of(proc)
    last_frame_ns = max(contract.stamp_ns(c.header.stamp) for c in answering(blind))  # the last one that arrived
    n = len(cmds)
    stops = lambda: [c for c in cmds[n:] if contract.stamp_ns(c.header.stamp) > last_frame_ns]  # noqa: E731
    assert ros.spin_until(lambda: len(stops()) >= 3, 10), ros.log_of(proc)[-3000:]
    first_stop_s = (contract.stamp_ns(stops()[0].header.stamp) - last_frame_ns) / 1e9
    # Never before frame_timeout_s after the last frame (its arrival is later than its stamp); how soon after it depends
    # on the machine's load (the next control tick), which the wait above bounds.
    assert first_stop_s >= 0.5, first_stop_s
    assert all(c.twist.linear.x == 0.0 and c.twist.angular.z == 0.0 for c in stops())
    # The report that covers every answer seen here: stopped, with each frame answered so far counted (a report is made
    # once a second: wait for one made after the last answer, whatever else the domain carries).
    answered = {contract.stamp_ns(c.header.stamp) for c in answering(far | near | blind)}
    blind_answered = {contract.stamp_ns(c.header.stamp) for c in answering(blind)}

    def stopping() -> bool:
        v = values(diag[-1])
        return (
            "no depth frame for" in diag[-1].message
            and int(v["safety_stops_no_frames"]) >= 3
            and int(v["frames_answered"]) >= len(answered)
        )

    assert ros.spin_until(stopping, 5), [(d.message, sorted(values(d).items())) for d in diag[-2:]]
    last = values(diag[-1])
    assert last["source"] == "camera" and int(last["safety_forward_blocked"]) >= 5 and last["camera_coverage"] == "0.57"
    assert last["shield"] == "on" and int(last["shield_checked"]) >= len(answered), sorted(last.items())
    assert int(last["shield_no_odometry"]) >= len(blind_answered) >= 5, (len(blind_answered), sorted(last.items()))
    assert int(last["malformed_camera_info"]) >= 1 and "malformed depth/camera_info" in ros.log_of(proc)
    # Every 5th answered camera frame is measured on a worker thread (or skipped while it is busy).
    assert int(last["insight_frames"]) + int(last["insight_skipped"]) >= 2 and int(last["insight_frames"]) >= 1
    assert proc.poll() is None


def test_the_packaged_default_explains_a_camera_stream_by_where_the_obstacle_is(ros):
    """The packaged default policy (sam) flown from a RealSense-like stream alone (848x480 16UC1, an 87 deg
    CameraInfo): with a pillar on the left of the view the published attention lies more on the left than with the
    same pillar on the right, and the other way round. The state spans 2.5 s of frames, so each scene is streamed
    for 3 s before its maps count, then until 5 of them have come (on a loaded machine best effort loses frames)."""
    import math

    import numpy as np
    from sensor_msgs.msg import CameraInfo

    maps = {}  # stamp -> the attention map (relative to a uniform share)
    ros.node.create_subscription(
        Image,
        contract.ATTENTION_TOPIC,
        lambda m: maps.setdefault(contract.stamp_ns(m.header.stamp), contract.image_to_depth(m)),
        50,
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, contract.SENSOR_QOS)
    pub_info = ros.node.create_publisher(CameraInfo, contract.CAMERA_INFO_TOPIC, contract.SENSOR_QOS)
    proc = ros.start("uav_policy", "policy_node", "-p", "model:=sam", "-p", "insight_every:=0")
    assert ros.spin_until(lambda: pub_img.get_subscription_count() and pub_info.get_subscription_count(), 30)
    f = 424 / math.tan(math.radians(87 / 2))
    info = CameraInfo(width=848, height=480, k=[f, 0.0, 424.0, 0.0, f, 240.0, 0.0, 0.0, 1.0])
    clock = ros.node.get_clock()
    rows = np.arange(480)[:, None]
    floor = np.where(rows > 240, np.minimum(1.0 * f / np.maximum(rows - 240, 1e-3), 9.0), np.inf)  # 1 m above a floor

    def scene(column: int) -> np.ndarray:
        depth = np.broadcast_to(floor, (480, 848)).astype(np.float32).copy()
        depth[:, column - 45 : column + 45] = 1.8  # a pillar 1.8 m away, 90 px wide
        return depth

    def stream(depth: np.ndarray, maps_wanted: int) -> list[int]:
        stamps, start = [], time.monotonic()
        while sum(s in maps for s in stamps) < maps_wanted and time.monotonic() - start < 60:
            stamp = clock.now().to_msg()
            info.header.stamp = stamp
            pub_info.publish(info)
            pub_img.publish(contract.depth_to_image(depth, stamp, "camera_depth_optical_frame", "16UC1"))
            if time.monotonic() - start > 3.0:  # the stack holds this scene only
                stamps.append(contract.stamp_ns(stamp))
            ros.spin_for(1 / 15)
        ros.spin_for(0.3)
        return [s for s in stamps if s in maps]

    left, right = scene(250), scene(598)
    on_left = stream(left, 5)
    on_right = stream(right, 5)
    assert len(on_left) >= 5 and len(on_right) >= 5, (len(on_left), len(on_right), ros.log_of(proc)[-2000:])
    mean = lambda stamps: np.mean([maps[s] for s in stamps], axis=0)  # noqa: E731
    a, b = mean(on_left), mean(on_right)
    left_half, right_half = (slice(None), slice(0, 424)), (slice(None), slice(424, 848))
    assert a[left_half].mean() > b[left_half].mean() and b[right_half].mean() > a[right_half].mean(), (
        a[left_half].mean(),
        b[left_half].mean(),
        a[right_half].mean(),
        b[right_half].mean(),
    )


def test_a_network_with_the_local_map_flies_a_camera_with_odometry_shows_its_map_and_stops_without(ros, tmp_path):
    """A network that takes the local map (its weights file says so), behind a camera with no shield: each frame is
    mapped with the odometry of its time, the map's attention is drawn top-down on attention/local_map; frames without
    odometry are answered with no forward flight, and the log says why."""
    import math

    import numpy as np
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo

    from uav_policy import weights as wio
    from uav_policy.networks import NetConfig, build_network

    w = tmp_path / "map.safetensors"
    cfg = NetConfig(sam_readout="query", local_map=True)
    wio.save_file(build_network(cfg, seed=1), cfg, w, camera_hfov_deg=90.0)
    cmds, pictures, diag = [], [], []
    ros.node.create_subscription(TwistStamped, contract.CMD_VEL_STAMPED_TOPIC, cmds.append, deep_qos())
    ros.node.create_subscription(Image, contract.ATTENTION_LOCAL_MAP_TOPIC, pictures.append, deep_qos())
    ros.node.create_subscription(
        DiagnosticArray, contract.DIAGNOSTICS_TOPIC, lambda m: diag.extend(s for s in m.status if s.name == "uav_policy"), 10
    )
    pub_img = ros.node.create_publisher(Image, contract.DEPTH_TOPIC, contract.SENSOR_QOS)
    pub_info = ros.node.create_publisher(CameraInfo, contract.CAMERA_INFO_TOPIC, contract.SENSOR_QOS)
    pub_odom = ros.node.create_publisher(Odometry, contract.ODOM_TOPIC, contract.SENSOR_QOS)
    args = ("-p", f"weights:={w}", "-p", "publish_stamped:=true", "-p", "shield:=never", "-p", "safety:=false")
    proc = ros.start("uav_policy", "policy_node", *args)
    subscribed = lambda: all(p.get_subscription_count() for p in (pub_img, pub_info, pub_odom))  # noqa: E731
    assert ros.spin_until(lambda: subscribed() and diag, 30), ros.log_of(proc)[-2000:]
    values = lambda s: {kv.key: kv.value for kv in s.values}  # noqa: E731
    assert values(diag[-1])["local_map_input"] == "on"
    f = 32 / math.tan(math.radians(45))
    info = CameraInfo(width=64, height=64, k=[f, 0.0, 32.0, 0.0, f, 32.0, 0.0, 0.0, 1.0])
    frame = np.full((64, 64), 6.0, np.float32)
    frame[:, 20:30] = 2.0  # a pillar 2 m ahead, left of centre
    clock = ros.node.get_clock()

    def stream(answers: int, odometry: bool) -> list:
        stamps, deadline = set(), time.monotonic() + 30
        answered = lambda: [c for c in cmds if contract.stamp_ns(c.header.stamp) in stamps]  # noqa: E731
        while len(answered()) < answers and time.monotonic() < deadline:
            stamp = clock.now().to_msg()
            if odometry:
                odom = Odometry()
                odom.header.stamp, odom.pose.pose.position.z, odom.pose.pose.orientation.w = stamp, 1.0, 1.0
                pub_odom.publish(odom)
            info.header.stamp = stamp
            pub_info.publish(info)
            pub_img.publish(contract.depth_to_image(frame, stamp, "camera_depth_optical_frame"))
            stamps.add(contract.stamp_ns(stamp))
            ros.spin_for(0.1)
        return answered()

    mapped = stream(5, odometry=True)
    assert len(mapped) >= 5, ros.log_of(proc)[-3000:]
    assert ros.spin_until(lambda: pictures, 5), "attention/local_map drawn for its subscriber"
    assert pictures[-1].encoding == "rgb8" and pictures[-1].width == 256
    ros.spin_for(0.6)  # the last odometry is older than odom_timeout_s from now on
    blind = stream(5, odometry=False)
    assert len(blind) >= 5 and all(c.twist.linear.x == 0.0 for c in blind), [c.twist.linear.x for c in blind]
    assert "the network's local map: no odometry within odom_timeout_s of the frame" in ros.log_of(proc)
