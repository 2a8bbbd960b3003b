"""An actor on another host (docs/TRAINING.md, "Across machines"), simulated with two network namespaces joined by a
veth pair: trainer_node in one, a sim_node/policy_node actor in the other, discovery through static peers over UDP
(Fast DDS's shared-memory transport is switched off, so nothing can pass outside the veth link). Measured while
writing it: ROS_AUTOMATIC_DISCOVERY_RANGE=OFF with ROS_STATIC_PEERS discovers nothing on these wheels; LOCALHOST with
the peers, and SUBNET alone, do."""

import os
import shutil
import subprocess

import pytest

from conftest import ROOT, executable

DOMAIN = "83"
LEARNER_IP, ACTOR_IP = "10.213.7.1", "10.213.7.2"  # inside this test's own namespaces only


def sh(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True)


@pytest.fixture
def two_hosts():
    """Two network namespaces joined by a veth pair; skipped with the reason where they cannot be made."""
    if os.geteuid() != 0 or not shutil.which("ip"):
        pytest.skip("simulating two hosts needs root and iproute2 (ip netns)")
    tag = f"uav{os.getpid() % 100000}"
    learner, actor = f"{tag}l", f"{tag}a"
    steps = [
        ("ip", "netns", "add", learner),
        ("ip", "netns", "add", actor),
        ("ip", "link", "add", f"{tag}vl", "type", "veth", "peer", "name", f"{tag}va"),
        ("ip", "link", "set", f"{tag}vl", "netns", learner),
        ("ip", "link", "set", f"{tag}va", "netns", actor),
        ("ip", "-n", learner, "addr", "add", f"{LEARNER_IP}/24", "dev", f"{tag}vl"),
        ("ip", "-n", actor, "addr", "add", f"{ACTOR_IP}/24", "dev", f"{tag}va"),
        *[("ip", "-n", ns, "link", "set", dev, "up") for ns, dev in ((learner, "lo"), (actor, "lo"))],
        ("ip", "-n", learner, "link", "set", f"{tag}vl", "up"),
        ("ip", "-n", actor, "link", "set", f"{tag}va", "up"),
    ]
    try:
        for cmd in steps:
            r = sh(*cmd)
            if r.returncode != 0:
                pytest.skip(f"cannot simulate two hosts here: {' '.join(cmd)}: {r.stderr.strip()}")
        ping = sh("ip", "netns", "exec", learner, "ping", "-c", "1", "-W", "2", ACTOR_IP)
        if ping.returncode != 0 and shutil.which("ping"):
            pytest.fail(f"the veth link does not carry traffic: {ping.stdout}{ping.stderr}")
        yield learner, actor
    finally:
        for ns in (learner, actor):
            sh("ip", "netns", "del", ns)  # takes its end of the veth pair with it


@pytest.mark.slow  # two hosts in network namespaces (about 20 s)
@pytest.mark.timeout(240)
def test_a_remote_actor_on_another_host_feeds_the_trainer_over_static_peers(two_hosts, tmp_path):
    learner, actor = two_hosts
    run_dir, key = tmp_path / "run", tmp_path / "push.key"  # the key file stands for the copy on the actor host
    from uav_policy.push import write_key

    write_key(key)
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=DOMAIN,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",  # OFF would switch the static peers off too (Jazzy, Fast DDS)
        ROS_STATIC_PEERS=f"{LEARNER_IP};{ACTOR_IP}",
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",
        ROS_LOG_DIR=str(tmp_path / "roslog"),
    )
    params = lambda name: ["--params-file", str(ROOT / "params" / f"{name}.yaml")]  # noqa: E731
    p = lambda *kv: [x for v in kv for x in ("-p", v)]  # noqa: E731

    def start(ns, name, pkg, exe, args):
        out = (tmp_path / f"{name}.log").open("w")
        cmd = ["ip", "netns", "exec", ns, str(executable(pkg, exe)), "--ros-args", *args]
        return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT)

    procs = [
        start(
            actor,
            "sim",
            "uav_sim",
            "sim_node",
            ["-r", "__ns:=/b0", *params("sim")]
            + p(
                "seed:=7",
                "wait_for_subscribers:=2",
                "publish_clock:=false",
                "world:=basic",
                "hfov_deg:=90.0",
                "reward_window_fraction:=0.2",
            ),
        ),
        start(
            actor,
            "policy",
            "uav_policy",
            "policy_node",
            ["-r", "__ns:=/b0", *params("policy")]
            + p(
                "model:=cnn",
                "epsilon:=1.0",
                "wait_for_trainer:=true",
                "accept_pushes:=true",
                f"push_key_file:={key}",
                "safety:=false",
                "shield:=never",
            ),
        ),
    ]
    trainer = start(
        learner,
        "trainer",
        "uav_trainer",
        "trainer_node",
        [*params("trainer")]
        + p(
            "model:=cnn",
            "total_steps:=120",
            f"run_dir:={run_dir}",
            f"push_key_file:={key}",
            "actors:=[/b0]",
            "replay_ratio:=0.1",
            "log_interval_s:=0.5",
        ),
    )
    try:
        code = trainer.wait(timeout=200)
    finally:
        for proc in [trainer, *procs]:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
    logs = {n: (tmp_path / f"{n}.log").read_text() for n in ("trainer", "sim", "policy")}
    assert code == 0, logs["trainer"][-3000:] + logs["sim"][-1500:] + logs["policy"][-1500:]
    assert "step budget of 120 reached" in logs["trainer"]
    # Every step came from /b0 (the only actor, on the other host), paired and stored; each was released to its
    # policy in lockstep (no release, no next step), and none was lost to pairing.
    assert "(120 env steps" in logs["trainer"] and "actors_missing" not in logs["trainer"], logs["trainer"][-3000:]
    progress = [line for line in logs["trainer"].splitlines() if " | unpaired " in line]
    assert progress and progress[-1].endswith("unpaired 0 breaks 0 restarts 0"), logs["trainer"][-3000:]
    assert "answering each frame once trainer_node releases it" in logs["policy"]
    assert (run_dir / "policy_cnn.safetensors").is_file()
