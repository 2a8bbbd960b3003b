"""The teacher's room (uav_trainer.teacher): its settings by their names, the label read from sim_node's message,
the DAgger draw, and the two losses it teaches with."""

import math

import numpy as np
import pytest
import torch

from uav_common.frame_stack import node_shares
from uav_common.settings import SettingError, build, specs
from uav_interfaces.msg import TeacherLabel
from uav_trainer.teacher import DaggerDraw, TeacherConfig, label_action, large_margin_loss, reason_attention_loss, reason_shares
from uav_trainer.training_config import TrainerConfig


def test_the_teachers_settings_keep_their_names_as_parameters_and_land_in_one_place():
    names = [s.name for s in specs(TrainerConfig)]
    for name in ("teacher", "teacher_act_start", "teacher_weight", "teacher_margin", "attention_weight"):
        assert names.count(name) == 1, name
    cfg = build(TrainerConfig, {"teacher": "map", "teacher_margin": 0.5, "attention_weight": 0.25, "batch_size": 8})
    assert cfg.teaching == TeacherConfig(teacher="map", teacher_margin=0.5, attention_weight=0.25)
    assert (cfg.teacher, cfg.learner.batch_size) == ("map", 8)
    assert cfg.pulls_attention and not TrainerConfig(model="cnn", teaching=cfg.teaching).pulls_attention
    with pytest.raises(SettingError, match="teacher"):
        build(TrainerConfig, {"teacher": "oracle"})
    assert TrainerConfig().teacher_act_probability(0) == 0.0, "no teacher: it never flies"
    taught = TrainerConfig(total_steps=1000, teaching=TeacherConfig(teacher="stack", teacher_act_start=0.8))
    assert [taught.teacher_act_probability(s) for s in (0, 500, 1000)] == pytest.approx([0.8, 0.4, 0.0])


def test_a_label_that_names_no_action_or_scores_another_number_of_actions_is_no_label():
    label = TeacherLabel(action=2, scores=[0.1, 0.2, 0.9, 0.3])
    assert label_action(label, 4) == 2
    assert label_action(TeacherLabel(action=4, scores=[0.0] * 4), 4) == -1, "no such action"
    assert label_action(TeacherLabel(action=1, scores=[0.0] * 3), 4) == -1, "scores for another table"
    assert label_action(TeacherLabel(action=-1, scores=[0.0] * 4), 4) == -1


def test_the_dagger_draw_is_seeded_draws_only_for_labels_and_follows_its_probability():
    a, b = DaggerDraw(3), DaggerDraw(3)
    draws = [a(1, 0.5) for _ in range(200)]
    assert draws == [b(1, 0.5) for _ in range(200)], "the same seed, the same draws"
    assert 60 < sum(d == 1 for d in draws) < 140 and set(draws) <= {1, None}
    c, d = DaggerDraw(4), DaggerDraw(4)
    assert c(-1, 1.0) is None, "no label: the student flies"
    assert [c(2, 0.5) for _ in range(50)] == [d(2, 0.5) for _ in range(50)], "a frame without a label takes no draw"
    assert all(c(3, 1.0) == 3 for _ in range(20)) and all(c(3, 0.0) is None for _ in range(20))


def test_the_reason_is_shared_over_the_image_cells_as_the_network_orders_its_nodes():
    mask = np.zeros((64, 64), bool)
    mask[:8, :16] = True  # the top-left two cells of an 8 x 8 grid
    shares = reason_shares(mask, (8, 8))
    assert np.array_equal(shares, node_shares(mask, (8, 8))) and shares[:2].tolist() == [1.0, 1.0] and shares[2:].sum() == 0


def test_the_margin_loss_is_zero_once_the_teacher_leads_by_the_margin_and_positive_until_then():
    q = torch.tensor([[1.0, 0.0, 0.1, 0.2], [1.0, 0.5, 0.0, 0.0], [0.0, 3.0, 0.0, 0.0]])
    teacher = torch.tensor([0, 0, -1])  # the third state has no teacher action
    assert large_margin_loss(q[:1], teacher[:1], 0.8) == 0.0, "leads by 0.8: nothing to learn"
    assert large_margin_loss(q[1:2], teacher[1:2], 0.8) == pytest.approx(0.3), "0.5 + 0.8 - 1.0"
    assert large_margin_loss(q, teacher, 0.8) == pytest.approx(0.15), "the mean over labelled states only"
    assert large_margin_loss(q[2:], teacher[2:], 0.8) == 0.0, "no label, no loss"


def test_the_attention_loss_is_zero_on_the_reason_positive_off_it_and_needs_a_reason():
    """-log of the map's mass on the reason's cells (their shares over the largest): 0 when every head and query attend
    only to cells the reason fills, log 2 with half the map there, nothing from a state without a reason in view."""
    reason = torch.tensor([[0.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    on = torch.tensor([0.0, 0.5, 0.5, 0.0]).expand(2, 3, 5, 4)  # (batch, heads, queries, cells)
    half = torch.tensor([0.5, 0.25, 0.25, 0.0]).expand(2, 3, 5, 4)
    assert reason_attention_loss(on, reason) == pytest.approx(0.0, abs=1e-6)
    assert reason_attention_loss(half, reason) == pytest.approx(math.log(2.0))
    assert reason_attention_loss(half, torch.zeros(2, 4)) == 0.0, "no reason in view, no loss"
    partial = torch.tensor([[0.0, 0.5, 1.0, 0.0]])  # a cell half covered counts half
    assert reason_attention_loss(on[:1], partial) == pytest.approx(-math.log(0.75))
