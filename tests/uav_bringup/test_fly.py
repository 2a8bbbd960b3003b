"""Integration: `fly` brings up a namespaced sim/policy pair with the recorder, stops them all cleanly,
and the bag it keeps becomes pictures with `attention_figures --bag`."""

from __future__ import annotations

import re
import subprocess

import numpy as np
from test_record import read_bag

from conftest import executable


def test_fly_records_a_namespaced_flight_and_the_bag_becomes_figures(ros, tmp_path):
    bag = tmp_path / "flight"
    fly = subprocess.run(
        [
            str(executable("uav_bringup", "fly")),
            *("--model", "sam", "--world", "complex", "--namespace", "uav2", "--lockstep", "--duration", "12"),
            *("--record", str(bag), "--log-dir", str(tmp_path / "logs")),
        ],
        env=ros.env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-1500:]}" for p in sorted((tmp_path / "logs").glob("*.log")))
    assert fly.returncode == 0, fly.stdout + fly.stderr + logs
    got = read_bag(bag)
    # What the recorder fell behind on and lost, as the middleware told it ("/uav2/q_values 650 (2 lost)"): a
    # lockstep flight outpaces the recorder on a busy machine. Nothing else may be missing.
    closed = [line for line in (tmp_path / "logs" / "record.log").read_text().splitlines() if " closed: " in line]
    assert len(closed) == 1, logs
    lost = {t: int(n) for t, n in re.findall(r"(/\S+) \d+ \((\d+) lost\)", closed[0])}
    depth, actions = got["/uav2/depth/image_raw"][1], got["/uav2/action"][1]
    frames = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in depth}
    answered = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in actions]
    assert len(answered) >= 20, f"only {len(answered)} steps flown in 12 s"
    assert len(set(answered) - frames) <= lost.get("/uav2/depth/image_raw", 0), "every command answers a recorded frame"
    # A frame the simulator says again (lockstep_republish_s, on a loaded machine) is answered again with the same stamp.
    # The simulator is paused, not stopped, at the end: its last frame reaches the policy and is answered, and the
    # recorder writes all both nodes said before they stop. Every recorded frame is answered on record, the last too.
    assert "the bag lacks" not in fly.stderr and "did not answer its pause" not in fly.stderr, fly.stderr + logs
    unanswered = len(frames) - len(set(answered))
    assert 0 <= unanswered <= lost.get("/uav2/action", 0), (unanswered, closed)
    assert depth[0].header.frame_id == "uav2/camera_depth_optical_frame"
    assert got["/uav2/odom"][1][0].header.frame_id == "uav2/odom"
    assert actions[0].header.frame_id == "uav2/base_link"
    markers = got["/uav2/world/markers"][1][0].markers
    assert len([m for m in markers if m.ns == "obstacles"]) == 9  # complex
    att = got["/uav2/attention"][1]
    # Each answer's attention, the last too.
    att_stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in att]
    assert set(att_stamps) <= set(answered) and att[0].encoding == "32FC1"
    assert 0 <= len(set(answered)) - len(set(att_stamps)) <= lost.get("/uav2/attention", 0), closed

    out = tmp_path / "figures"
    r = subprocess.run(
        [str(executable("uav_eval", "attention_figures")), "--bag", str(bag), "--namespace", "/uav2", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    from PIL import Image as Picture

    with Picture.open(out / "attention_flight.png") as png, Picture.open(out / "flight_flight.gif") as gif:
        assert png.width >= 256 and png.height >= 256 and gif.n_frames >= 2, (png.size, gif.n_frames)
    assert f"({len(frames)} frames, {len(att)} with attention)" in r.stdout

    r = subprocess.run(
        [str(executable("uav_eval", "attention_figures")), "--bag", str(bag), "--namespace", "/uav5"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "no /uav5/depth/image_raw" in r.stderr and "/uav2/depth/image_raw" in r.stderr

    from uav_eval.figures import frames_from_bag

    flown = frames_from_bag(bag, "/uav2")
    assert all(a is not None for _, amap, a, _ in flown if amap is not None), "every answered frame maps to an action"
    assert not np.array_equal(flown[0][0], flown[-1][0]), "the frames are the flight's, not one frame repeated"
