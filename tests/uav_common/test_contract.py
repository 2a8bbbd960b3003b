import math

import numpy as np
import pytest
from sensor_msgs.msg import Image

from uav_common import contract
from uav_interfaces.msg import StepOutcome


def test_depth_image_round_trip_keeps_rep117_values():
    d = np.array([[1.5, np.inf], [-np.inf, np.nan]], dtype=np.float32)
    msg = contract.depth_to_image(d, contract.stamp_from_seconds(12.5), "cam")
    assert msg.encoding == "32FC1" and msg.step == 8 and msg.header.stamp.sec == 12
    back = contract.image_to_depth(msg)
    np.testing.assert_array_equal(back, d)


def test_big_endian_and_padded_rows_are_read():
    d = np.arange(6, dtype=np.float32).reshape(2, 3)
    msg = Image(height=2, width=3, encoding="32FC1", is_bigendian=1, step=16)
    rows = np.zeros((2, 16), dtype=np.uint8)
    rows[:, :12] = np.frombuffer(d.astype(">f4").tobytes(), dtype=np.uint8).reshape(2, 12)
    msg.data = rows.tobytes()
    np.testing.assert_array_equal(contract.image_to_depth(msg), d)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(height=2, width=2, encoding="rgb8", step=6, data=bytes(12)), "must be 32FC1 or 16UC1"),
        (dict(height=2, width=2, encoding="32FC1", step=8, data=bytes(10)), "bytes"),
        (dict(height=2, width=2, encoding="32FC1", step=8, data=bytes(20)), "has 20 bytes, expected 16"),
        (dict(height=100000, width=100000, encoding="16UC1", step=200000, data=bytes(8)), "has 8 bytes"),
        (dict(height=2, width=2, encoding="32FC1", step=4, data=bytes(16)), "step"),
        (dict(height=0, width=2, encoding="32FC1", step=8, data=b""), "empty"),
    ],
)
def test_malformed_images_raise_clear_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        contract.image_to_depth(Image(**kwargs))


def test_stamp_joiner_pairs_exactly_and_counts_what_it_drops():
    j = contract.StampJoiner(("frame", "action"), max_pending=3)
    assert j.add("frame", 1, "f1") is None
    assert j.add("action", 1, "a1") == {"frame": "f1", "action": "a1"}
    # Out-of-order arrival between streams still joins.
    assert j.add("action", 2, "a2") is None
    assert j.add("frame", 2, "f2") == {"frame": "f2", "action": "a2"}
    # A frame that never gets an action is dropped once a newer stamp completes.
    j.add("frame", 3, "f3")
    j.add("frame", 4, "f4")
    assert j.add("action", 4, "a4") == {"frame": "f4", "action": "a4"}
    assert j.dropped == {"frame": 0, "action": 1}
    # A finished stamp said again is counted as late, never joined with something else.
    assert j.add("frame", 4, "f4 again") is None and j.late == 1
    # A duplicate in one stream is counted and ignored.
    j.add("frame", 5, "f5")
    assert j.add("frame", 5, "again") is None and j.duplicates == 1
    assert j.add("action", 5, "a5") == {"frame": "f5", "action": "a5"}
    # Bounded memory: pending incomplete stamps beyond max_pending are dropped.
    for s in range(10, 20):
        j.add("frame", s, s)
    assert len(j.pending) <= 3 and j.dropped["action"] == 1 + 7


def test_stamp_joiner_starts_afresh_when_its_source_restarts_and_survives_a_stamp_from_the_future():
    j = contract.StampJoiner(("frame", "outcome"), max_pending=3)
    for s in (10, 11, 12):
        j.add("frame", s, s)
        assert j.add("outcome", s, s) is not None
    # A simulator restarted: its clock begins again. Before, every frame was dropped as late for good.
    assert j.add("frame", 0, "f0") is None and j.restarts == 1
    assert j.add("outcome", 0, "o0") == {"frame": "f0", "outcome": "o0"}
    assert j.add("frame", 1, "f1") is None and j.add("outcome", 1, "o1") is not None
    # One frame stamped far in the future, never completed: given up in time, it silences nothing.
    j.add("frame", 10**15, "glitch")
    for s in (2, 3, 4):  # their outcomes are lost: the pending stamps overflow and the glitch is dropped
        j.add("frame", s, s)
    assert 10**15 not in j.pending
    for s in range(5, 8):
        j.add("frame", s, s)
        assert j.add("outcome", s, s) == {"frame": s, "outcome": s}
    # A future stamp that did complete: the next true stamp is behind it, so the join starts afresh.
    j.add("frame", 10**15 + 1, "glitch")
    assert j.add("outcome", 10**15 + 1, "glitch") is not None
    j.add("frame", 8, 8)
    assert j.add("outcome", 8, 8) == {"frame": 8, "outcome": 8} and j.restarts == 2


def test_camera_info_field_of_view():
    from sensor_msgs.msg import CameraInfo

    info = CameraInfo(width=64, height=64)
    info.k = [32.0, 0.0, 32.0, 0.0, 32.0, 32.0, 0.0, 0.0, 1.0]
    assert contract.camera_info_hfov_deg(info) == pytest.approx(90.0)
    info.k[0] = 32.0 / math.tan(math.radians(60.0))
    assert contract.camera_info_hfov_deg(info) == pytest.approx(120.0)
    info.k[0] = 0.0  # an uncalibrated camera (REP 104: K all zero) gives no field of view
    assert contract.camera_info_hfov_deg(info) is None
    assert contract.camera_info_hfov_deg(CameraInfo()) is None


def test_step_outcome_marks_how_an_episode_began():
    stamp = contract.stamp_from_seconds(1.0)

    def outcome(**kw):
        return contract.make_outcome(2.5, stamp=stamp, frame_id="cam", min_range_m=0.1, max_range_m=10.0, fov_rad=0.4, **kw)

    flying, crash = outcome(collided=False), outcome(collided=True)
    cut, reset = outcome(collided=False, truncated=True), outcome(collided=False, truncated=True, reset=True)
    assert [m.event for m in (flying, crash, cut, reset)] == [
        StepOutcome.CONTINUES,
        StepOutcome.COLLIDED,
        StepOutcome.TIME_LIMIT,
        StepOutcome.RESET,
    ]
    assert [contract.outcome_beta(m) for m in (flying, crash, cut)] == [2.5, 0.0, 0.0], "a depth only when it continued"
    assert [contract.outcome_collided(m) for m in (flying, crash, cut, reset)] == [False, True, False, False]
    assert [contract.outcome_truncated(m) for m in (flying, crash, cut, reset)] == [False, False, True, True]
    assert [contract.outcome_new_episode(m) for m in (flying, crash, cut, reset)] == [False, True, True, True]
    # A publisher's faulty depth is clipped into the camera's range, NaN to 0.
    odd = [StepOutcome(beta_m=v, max_range_m=10.0) for v in (math.nan, math.inf, -1.0, 4.0)]
    assert [contract.outcome_beta(m) for m in odd] == [0.0, 10.0, 0.0, 4.0]


def test_a_real_cameras_16uc1_millimetres_read_as_metres_in_either_byte_order():
    mm = np.array([[0, 400, 1500], [65535, 1, 2000]], dtype=np.uint16)
    for order, big in (("<", 0), (">", 1)):
        rows = [mm[r].astype(order + "u2").tobytes() + b"\xff\xff" for r in range(2)]  # rows padded by 2 bytes
        msg = Image(height=2, width=3, encoding="16UC1", is_bigendian=big, step=8, data=b"".join(rows))
        depth = contract.image_to_depth(msg)
        assert depth.dtype == np.float32 and depth.shape == (2, 3)
        assert depth[0, 0] == np.inf, "0 is no return: nothing in range"
        np.testing.assert_allclose(depth[0, 1:], [0.4, 1.5])
        np.testing.assert_allclose(depth[1], [65.535, 0.001, 2.0], rtol=1e-6)
    with pytest.raises(ValueError, match="step 5 is smaller than 2\\*width=6"):
        contract.image_to_depth(Image(height=1, width=3, encoding="16UC1", step=5, data=bytes(5)))


def test_a_thin_pole_survives_the_way_down_to_the_network_input():
    """A 2 px pole at 2 m in an 848x480 frame of a wall at 6 m: still nearer than the wall at 64x64 (nearest
    neighbour dropped it); a NaN (no reading) never hides a reading in its cell; small frames grow."""
    from uav_common.frame_stack import fit_to_network

    frame = np.full((480, 848), 6.0, np.float32)
    frame[:, 421:423] = 2.0
    frame[10, 10] = np.nan
    net = fit_to_network(frame, 64, 64)
    assert net.shape == (64, 64) and net.dtype == np.float32
    assert np.all(net.min(axis=1) == 2.0), "the pole is in every row"
    assert np.count_nonzero(net[0] == 2.0) == 1 and np.all(net[:, :31] == 6.0)
    assert not np.isnan(net).any()
    small = np.arange(12, dtype=np.float32).reshape(3, 4)
    grown = fit_to_network(small, 6, 8)
    assert grown.shape == (6, 8) and set(np.unique(grown)) == set(small.ravel())
    np.testing.assert_array_equal(grown[::2, ::2], small)


def test_camera_info_maps_a_frame_onto_the_field_of_view_the_weights_were_trained_with():
    """An 87 deg 848x480 camera under weights trained at 150 deg fills the input's middle and the rest reads
    no return (+Inf); under weights trained at 87 deg it spans the width, padded above and below; the
    simulator's own camera maps one to one; the 2 px pole survives either way."""
    from uav_common.frame_stack import CameraView, fit_to_network

    fx = 424 / math.tan(math.radians(87 / 2))
    frame = np.full((480, 848), 6.0, np.float32)
    frame[:, 421:423] = 2.0
    for trained, columns, rows in ((150.0, range(23, 41), range(27, 37)), (87.0, range(0, 64), range(13, 51))):
        view = CameraView.from_intrinsics(fx, fx, 424, 240, 848, 480, trained, 64, 64)
        net = fit_to_network(frame, 64, 64, view)
        seen = np.isfinite(net)
        assert list(np.flatnonzero(seen.any(axis=0))) == list(columns), (trained, np.flatnonzero(seen.any(axis=0)))
        assert list(np.flatnonzero(seen.any(axis=1))) == list(rows), (trained, np.flatnonzero(seen.any(axis=1)))
        assert view.coverage == pytest.approx(seen.mean(), abs=0.04)  # partly seen cells count in part
        assert np.all(net[list(rows)].min(axis=1) == 2.0), "the pole is nearer than the wall in every row seen"
    sim_f = 32 / math.tan(math.radians(75))
    same = CameraView.from_intrinsics(sim_f, sim_f, 32, 32, 64, 64, 150.0, 64, 64)
    small = np.random.default_rng(0).uniform(0.1, 10, (64, 64)).astype(np.float32)
    np.testing.assert_array_equal(fit_to_network(small, 64, 64, same), small)
    with pytest.raises(ValueError, match="fx=0"):
        CameraView.from_intrinsics(0.0, 1.0, 1, 1, 10, 10, 90.0, 64, 64)


def test_16uc1_frames_are_written_as_camera_drivers_write_them():
    """sim_node's 16UC1: millimetres, 0 for no return or beyond 65.534 m; read back to the millimetre."""
    depth = np.array([[0.4004, 2.0, np.inf], [np.nan, 70.0, 0.0006]], np.float32)
    msg = contract.depth_to_image(depth, contract.stamp_from_seconds(1.0), "cam", "16UC1")
    assert msg.step == 6 and np.frombuffer(bytes(msg.data), "<u2").tolist() == [400, 2000, 0, 0, 0, 1]
    back = contract.image_to_depth(msg)
    np.testing.assert_allclose(back[0, :2], [0.4, 2.0])
    assert np.isinf(back[0, 2]) and np.isinf(back[1, :2]).all() and back[1, 2] == pytest.approx(0.001)
    with pytest.raises(ValueError, match="encoding must be one of"):
        contract.depth_to_image(depth, contract.stamp_from_seconds(1.0), "cam", "mono8")


def test_the_sampled_stack_holds_frames_one_step_period_apart_whatever_the_camera_rate():
    from uav_common.frame_stack import SampledStack

    s = SampledStack(5, 0.5)
    for i in range(60):  # 3 s at 20 Hz
        s.add(i / 20, np.full((2, 2), i, np.float32))
    np.testing.assert_array_equal(s.state()[:, 0, 0], [19, 29, 39, 49, 59])  # 59/20 s, then 0.5 s steps back
    assert s.state().shape == (5, 2, 2)
    fresh = SampledStack(5, 0.5)
    fresh.add(0.0, np.zeros((2, 2), np.float32))
    fresh.add(0.1, np.ones((2, 2), np.float32))
    np.testing.assert_array_equal(fresh.state()[:, 0, 0], [0, 0, 0, 0, 1]), "the oldest stands in, as at a reset"
    from uav_common.frame_stack import FrameStack

    carried = FrameStack(5)
    carried.restore(s.state())  # policy_node: a simulator found after its first frames were answered
    assert carried.push(np.full((2, 2), 60, np.float32))[:, 0, 0].tolist() == [29, 39, 49, 59, 60]
    assert s.add(1.0, np.zeros((2, 2), np.float32)) is False and s.state()[:, 0, 0].tolist() == [0] * 5


def test_the_large_frames_dds_profile_gives_a_shared_memory_segment_an_848x480_frame_fits_in():
    """docs/REAL_CAMERA.md's opt-in Fast DDS profile: a shared-memory segment several full-size frames deep, read as XML
    and shipped beside the code (package_data)."""
    import xml.etree.ElementTree as ET
    from pathlib import Path

    import uav_common

    path = Path(uav_common.__file__).parent / "fastdds_large_frames.xml"
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(path).getroot()
    shm = [t for t in root.iterfind(".//f:transport_descriptor", ns) if t.findtext("f:type", namespaces=ns) == "SHM"]
    assert shm and int(shm[0].findtext("f:segment_size", namespaces=ns)) >= 10 * 848 * 480 * 2
    assert root.find(".//f:participant[@is_default_profile='true']", ns) is not None
