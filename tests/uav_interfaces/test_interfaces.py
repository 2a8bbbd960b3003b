"""The stack's own interfaces (src/uav_interfaces): built, indexed where ros2cli finds them, and every message
round-trips through rclpy's serialization with what it carries."""

import array
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from uav_common import contract

INTERFACES = ("msg/StepOutcome", "msg/TeacherLabel", "msg/ActionValues", "msg/AttentionWeights", "srv/PushWeights")


def test_the_interfaces_are_indexed_with_their_definitions_where_ros2_interface_show_reads_them():
    """`ros2 interface list/show` read the ament index's rosidl_interfaces resource and the installed files."""
    from ament_index_python.packages import get_package_share_directory, get_resource

    listed, _ = get_resource("rosidl_interfaces", "uav_interfaces")
    share = Path(get_package_share_directory("uav_interfaces"))
    for name in INTERFACES:
        kind = name.split("/")[0]
        assert f"{name}.{kind}" in listed.splitlines(), f"{name} not in the index"
        text = (share / f"{name}.{kind}").read_text()
        assert text.lstrip().startswith("#"), f"{name} has no comment saying what it means"
    assert "uint8 COLLIDED = 1" in (share / "msg/StepOutcome.msg").read_text()


def stamp():
    return contract.stamp_from_seconds(12.5)


def test_every_message_round_trips_with_what_it_carries():
    from uav_interfaces.msg import ActionValues, AttentionWeights, StepOutcome, TeacherLabel

    outcome = contract.make_outcome(1.25, False, stamp(), "cam", 0.1, 10.0, 0.4)
    reset = contract.make_outcome(1.25, False, stamp(), "cam", 0.1, 10.0, 0.4, truncated=True, reset=True)
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:40] = True
    label = TeacherLabel(action=2, scores=[1e7 + 3.5, 1e7 + 400.0, 1e7 + 400.5, 2e5])
    label.header.stamp, label.reason = stamp(), contract.mask_to_image(mask, stamp(), "cam")
    w = np.random.default_rng(0).random((3, 1, 2 * 16), dtype=np.float32)
    header = outcome.header
    values = contract.action_values_msg(header, np.array([0.5, -1.0, 2.0, 0.25]), ("a0", "a1", "a2", "a3"), 2)
    weights = contract.attention_weights_msg(header, w, (4, 4))
    for msg in (outcome, reset, label, values, weights):  # float32 fields compared as they travel: once through
        back = deserialize_message(serialize_message(msg), type(msg))
        assert deserialize_message(serialize_message(back), type(msg)) == back, type(msg).__name__
        for name in msg.get_fields_and_field_types():
            a, b = getattr(msg, name), getattr(back, name)
            assert b == a or np.allclose(np.asarray(b, np.float64), np.asarray(a, np.float64), rtol=1e-6), name
    back = deserialize_message(serialize_message(label), TeacherLabel)
    assert np.array_equal(contract.image_to_mask(back.reason), mask) and list(back.scores)[1] == 1e7 + 400.0
    assert reset.event == StepOutcome.RESET and outcome.event == StepOutcome.CONTINUES and outcome.beta_m == 1.25
    assert (weights.heads, weights.queries, weights.grid_rows, weights.grid_cols, weights.map_cells) == (3, 1, 4, 4, 16)
    assert np.array_equal(np.asarray(weights.weights, np.float32).reshape(w.shape), w)
    assert list(values.actions) == ["a0", "a1", "a2", "a3"] and values.action == 2 and isinstance(values, ActionValues)
    assert isinstance(weights, AttentionWeights)


def test_a_push_request_carries_its_fields_typed_and_its_weights_as_bytes():
    from uav_interfaces.srv import PushWeights
    from uav_policy.push import push_request, read_push

    blob = bytes(range(256)) * 40
    req = push_request(blob, 0.25, 7_000_000_000, key=b"k" * 32, seq=9, fly_action=1)
    back = deserialize_message(serialize_message(req), PushWeights.Request)
    assert isinstance(back.weights, array.array) and bytes(back.weights) == blob
    push = read_push(back, 1 << 20)
    assert (push.weights, push.epsilon, push.release_stamp_ns, push.fly_action, push.seq) == (blob, 0.25, 7e9, 1, 9)
    empty = PushWeights.Request()
    assert (empty.epsilon, empty.release_stamp_ns, empty.fly_action) == (
        PushWeights.Request.KEEP_EPSILON,
        PushWeights.Request.NO_RELEASE,
        PushWeights.Request.NETWORK_ANSWERS,
    ), "a request's defaults change nothing"
    with pytest.raises(ValueError, match="an empty push"):
        read_push(empty, 1 << 20)
