"""The safety layer's rules on constructed inputs (policy_node applies them to every command)."""

import math

import numpy as np
import pytest
import torch

from uav_policy.safety import SafetyLayer, SafetySettings

CLEAR = np.full((64, 64), 8.0, np.float32)


def layer(**kw):
    return SafetyLayer(SafetySettings(**kw), 64, 64, 150.0)


def test_a_wall_inside_the_stop_distance_removes_forward_motion_but_not_turning():
    s = layer(stop_distance_m=0.6)
    wall = np.full((64, 64), 0.4, np.float32)
    assert s.filter(1.0, 1.05, wall)[:2] == (0.0, 1.05)
    assert s.filter(1.0, 0.0, CLEAR) == (1.0, 0.0, "")
    assert s.filter(-0.5, 0.0, wall)[:2] == (-0.5, 0.0), "backing away stays allowed"
    assert s.counts.forward_blocked == 1 and s.counts.total == 1


def test_a_blocked_straight_command_turns_the_policys_best_way_instead_of_hovering_for_good():
    s = layer(stop_distance_m=0.6)
    wall = np.full((64, 64), 0.4, np.float32)
    vx, wz, why = s.filter(2.0, 0.0, wall, turn_radps=-1.05)
    assert (vx, wz) == (0.0, -1.05) and "turning" in why
    assert s.filter(1.0, 1.05, wall)[:2] == (0.0, -1.05), "the way round is kept until clear: no dithering"
    assert s.filter(2.0, 0.0, CLEAR, turn_radps=-1.05)[:2] == (2.0, 0.0), "a clear way flies straight"
    assert s.filter(1.0, 1.05, wall)[:2] == (0.0, 1.05), "once clear, a new blockage picks its way again"


def test_only_the_flight_corridor_counts():
    """A post 0.4 m ahead and 1 m to the side (outside a 0.35 m corridor) does not block; straight ahead it does."""
    s = layer(stop_distance_m=0.6, corridor_half_width_m=0.35)
    f = 32 / math.tan(math.radians(75))
    side = CLEAR.copy()
    col = int(32 + f * 1.0 / 0.4)  # 1 m to the side at 0.4 m depth
    side[:, col] = 0.4
    assert s.filter(1.0, 0.0, side)[0] == 1.0
    ahead = CLEAR.copy()
    ahead[30:34, 31:33] = 0.4
    assert s.filter(1.0, 0.0, ahead)[0] == 0.0
    assert math.isinf(s.nearest_in_corridor_m(side)) and s.nearest_in_corridor_m(ahead) == np.float32(0.4)


def test_speed_and_yaw_rate_are_limited_and_counted():
    s = layer(max_speed_mps=1.5, max_yaw_rate_radps=0.5)
    vx, wz, why = s.filter(2.0, -1.0, CLEAR)
    assert (vx, wz) == (1.5, -0.5) and "speed limited" in why and "yaw rate limited" in why
    assert s.counts.speed_limited == 1 and s.counts.yaw_rate_limited == 1


class FixedQ(torch.nn.Module):
    """Q-values that do not depend on the state: the greedy action is the largest entry."""

    def __init__(self, q):
        super().__init__()
        self.q = torch.tensor([q], dtype=torch.float32)

    def forward(self, x):
        return self.q.expand(x.shape[0], -1), None


def pilot(q, safety=None):
    from uav_common.actions import PAPER_ACTIONS
    from uav_policy.agent import Agent
    from uav_policy.networks import NetConfig
    from uav_policy.pilot import Pilot

    return Pilot(Agent(FixedQ(q), NetConfig()), PAPER_ACTIONS, 0.5, safety)


def test_the_pilot_flies_the_networks_action_and_the_safety_layer_turns_it_the_best_way_round_a_wall():
    """uav_policy.pilot, the one decision path of policy_node and the in-process flights: without a safety layer the
    network's action is the command (a3: 2 m/s ahead); behind one, a wall at 0.4 m stops the forward motion and
    the network's best turning action (a2, left: +60 deg/s) turns it instead. The network's own action is kept."""
    state, clear, wall = np.full((5, 64, 64), 8.0, np.float32), CLEAR, np.full((64, 64), 0.4, np.float32)
    d = pilot([0.0, 1.0, 2.0, 3.0]).decide(state, wall)
    assert (d.action, d.linear_x_mps, d.yaw_rate_radps, d.safety) == (3, 2.0, 0.0, "")
    safe = pilot([0.0, 1.0, 2.0, 3.0], layer())
    d = safe.decide(state, clear)
    assert (d.action, d.linear_x_mps, d.yaw_rate_radps, d.safety) == (3, 2.0, 0.0, "")
    d = safe.decide(state, wall)
    assert d.action == 3 and d.linear_x_mps == 0.0 and d.yaw_rate_radps == pytest.approx(math.radians(30) / 0.5)
    assert "no forward motion" in d.safety and safe.safety.counts.forward_blocked == 1
    explored = [pilot([0.0, 1.0, 2.0, 3.0]).decide(state, clear, epsilon=1.0).explored for _ in range(5)]
    assert all(explored)
