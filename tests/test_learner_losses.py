"""The training loss's pieces (learner/losses.py) on small hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch

from romannet.learner import losses as L


def _values(t: torch.Tensor) -> list[float]:
    return [float(v) for v in t]


def test_huber_is_quadratic_within_delta_and_linear_beyond():
    assert _values(L.huber(torch.tensor([0.5, -1.0, 3.0]))) == [0.125, 0.5, 2.5]
    # delta = 2: 0.5 * 1^2 inside; 2 * (3 - 0.5 * 2) = 4 beyond.
    assert _values(L.huber(torch.tensor([1.0, -3.0]), delta=2.0)) == [0.5, 4.0]


def test_support_loss_sums_or_averages_over_the_support_only():
    q = torch.zeros(2, 2)
    label = torch.tensor([[1.0, 3.0], [0.0, 9.0]])
    support = torch.tensor([[True, True], [False, False]])
    assert float(L.support_loss(q, label, support, 1.0, "sum")) == 3.0  # 0.5 + 2.5; the 9 is off the support
    assert float(L.support_loss(q, label, support, 1.0, "mean")) == 1.5
    assert float(L.support_loss(q, label, torch.zeros(2, 2, dtype=torch.bool), 1.0, "mean")) == 0.0
    with pytest.raises(ValueError, match="reduction"):
        L.support_loss(q, label, support, 1.0, "max")


def test_q_loss_is_each_items_support_loss():
    q = torch.tensor([[[0.0, 0.0], [0.0, 0.0]], [[2.0, 0.0], [0.0, 0.5]]])
    label = torch.tensor([[[1.0, 3.0], [0.0, 9.0]], [[0.0, 0.0], [0.0, 0.0]]])
    support = torch.tensor([[[True, True], [False, False]], [[True, False], [False, True]]])
    # item 0: 0.5 + 2.5; item 1: Huber(2) = 1.5 and Huber(0.5) = 0.125.
    assert _values(L.q_loss(q, label, support, 1.0, "sum")) == [3.0, 1.625]
    assert _values(L.q_loss(q, label, support, 1.0, "mean")) == [1.5, 0.8125]


def test_executed_pixel_loss_is_the_huber_of_the_td_error():
    q_exec = torch.tensor([1.0, 0.25])
    y = torch.tensor([0.5, 2.25])
    assert _values(L.executed_pixel_loss(q_exec, y, 1.0)) == [0.125, 1.5]  # errors 0.5 and -2


def test_rotation_pixel_loss_is_the_weighted_squared_distance_to_the_target():
    rot_exec = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    target = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    assert _values(L.rotation_pixel_loss(rot_exec, target, torch.tensor([1.0, 1.0]))) == [2.0, 0.0]
    assert _values(L.rotation_pixel_loss(rot_exec, target, torch.tensor([0.5, 3.0]))) == [1.0, 0.0]
    assert _values(L.rotation_pixel_loss(rot_exec, -target, torch.tensor([0.0, 0.25]))) == [0.0, 1.0]


def test_rotation_kernel_loss_averages_the_squared_distance_over_the_support():
    rot = torch.zeros(2, 2, 2, 2)  # (k, 2, h, w)
    rot[0, 0, 0, 0] = 1.0  # pixel (0, 0): |(1, 0) - (0, 0)|^2 = 1
    rot[0, 1, 1, 1] = 2.0  # pixel (1, 1): |(0, 2) - (0, 0)|^2 = 4; (0, 1) is off the support
    rot[0, 0, 0, 1] = 7.0
    target = torch.zeros(2, 2)
    support = torch.tensor([[[True, False], [False, True]], [[False, False], [False, False]]])
    weight = torch.tensor([2.0, 1.0])
    # item 0: 2 * (1 + 4) / 2 pixels; item 1: an empty support trains nothing.
    assert _values(L.rotation_kernel_loss(rot, target, weight, support)) == [5.0, 0.0]


def test_item_loss_adds_the_weighted_terms_and_leaves_out_a_zero_weight_pixel_term():
    q, rot, pixel = torch.tensor([1.0, 2.0]), torch.tensor([0.5, 1.0]), torch.tensor([4.0, 8.0])
    assert _values(L.item_loss(q, rot, 2.0, pixel, 0.5)) == [4.0, 8.0]  # 1 + 2 * 0.5 + 0.5 * 4, ...
    assert _values(L.item_loss(q, rot, 0.0, pixel, 1.0)) == [5.0, 10.0]
    # lambda_t = 0 leaves the term out rather than multiplying it by 0 (a NaN would survive 0 * NaN).
    assert _values(L.item_loss(q, rot, 2.0, torch.tensor([math.nan, math.inf]), 0.0)) == [2.0, 4.0]


def test_weighted_sum_applies_the_importance_sampling_weights():
    assert float(L.weighted_sum(torch.tensor([1.0, 0.5]), torch.tensor([2.0, 4.0]))) == 4.0
    assert float(L.weighted_sum(torch.tensor([0.25]), torch.tensor([3.0]))) == 0.75


def test_gradients_flow_through_the_terms_that_are_trained():
    q = torch.tensor([[[0.0, 0.0], [0.0, 0.0]]], requires_grad=True)
    label = torch.tensor([[[1.0, 0.0], [0.0, 0.0]]])
    support = torch.tensor([[[True, False], [False, False]]])
    q_exec = q[0, 1, 1].reshape(1)
    loss = L.weighted_sum(torch.tensor([2.0]), L.item_loss(
        L.q_loss(q, label, support, 1.0, "sum"), torch.zeros(1), 1.0,
        L.executed_pixel_loss(q_exec, torch.tensor([0.5]), 1.0), 1.0))
    loss.backward()
    # d/dq of 2 * (0.5 (q00 - 1)^2 + 0.5 (q11 - 0.5)^2) at 0: -2 at the label's pixel, -1 at the executed one.
    assert q.grad.tolist() == [[[-2.0, 0.0], [0.0, -1.0]]]
