"""The learner's target math: eta, V(s_t+1), Y, the label map and the orientation symmetry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from romannet.common.config import RewardConfig
from romannet.common.model import SYMMETRIC_PRIMITIVES, encode_angle
from romannet.common.reward import tpg_label
from romannet.learner import targets as T

CFG = RewardConfig()
SHAPE = (48, 48)


def test_eta_is_one_only_for_positive_reward():
    assert T.eta(0.7) == 1.0
    assert T.eta(0.0) == 0.0
    assert T.eta(-0.1) == 0.0
    with pytest.raises(ValueError):
        T.eta(math.nan)


def test_td_target_success_failure_and_eta_cut():
    assert T.td_target(1.0, 0.8, 0.5) == pytest.approx(1.4)  # success bootstraps
    assert T.td_target(0.0, 5.0, 0.5) == 0.0  # eta = 0 cuts the bootstrap however large V is
    assert T.td_target(0.2, -1.0, 0.5) == pytest.approx(-0.3)
    with pytest.raises(ValueError):
        T.td_target(1.0, 0.0, 1.0)


def test_bootstrap_value_uses_allowed_primitives_and_episode_end():
    maps = {"push": np.full((4, 4), 3.0), "pick": np.array([[0.1, 0.9]]), "place": np.full((2, 2), 7.0)}
    assert T.bootstrap_value(maps, holding_after=False, primitives=("push", "pick", "place"), done=False) == 3.0
    assert T.bootstrap_value(maps, holding_after=False, primitives=("pick",), done=False) == pytest.approx(0.9)
    assert T.bootstrap_value(maps, holding_after=True, primitives=("pick", "place"), done=False) == 7.0
    assert T.bootstrap_value(maps, holding_after=True, primitives=("pick", "place"), done=True) == 0.0
    assert T.bootstrap_value({"pick": torch.tensor([[0.25]])}, False, ("pick",), False) == 0.25
    with pytest.raises(ValueError, match="place"):
        T.bootstrap_value({"pick": 1.0}, holding_after=True, primitives=("pick", "place"), done=False)
    with pytest.raises(ValueError, match="non-finite"):
        T.bootstrap_value({"pick": np.array([np.nan])}, False, ("pick",), False)


@pytest.mark.parametrize("normalization", ["peak", "paper"])
def test_label_at_executed_pixel_is_the_target(normalization):
    cfg = RewardConfig(kernel_normalization=normalization)
    label, support = T.q_label(SHAPE, 20, 30, 0.4, 0.8, v_next=1.5, gamma=0.5, cfg=cfg)
    assert label[20, 30] == pytest.approx(T.td_target(0.8, 1.5, 0.5))
    reward_map, tpg_support = tpg_label(SHAPE, 20, 30, 0.4, 0.8, cfg)
    np.testing.assert_array_equal(support, tpg_support)
    np.testing.assert_allclose(label[support], reward_map[support] + 0.75, rtol=1e-6)
    assert not label[~support].any()


def test_failed_action_label_is_zero_on_an_unchanged_support():
    label, support = T.q_label(SHAPE, 5, 5, 1.0, 0.0, v_next=9.0, gamma=0.5, cfg=CFG)
    assert not label.any()
    np.testing.assert_array_equal(support, tpg_label(SHAPE, 5, 5, 1.0, 1.0, CFG)[1])


@pytest.mark.parametrize("primitive", ["pick", "place"])
@pytest.mark.parametrize("theta", [0.0, 0.3, -1.2, math.pi / 2])
def test_opposite_orientation_label_is_identical(primitive, theta):
    """The paper's 'gradients for the opposite orientation' are exact: both labels coincide."""
    opposite = theta + math.pi
    a = T.q_label(SHAPE, 24, 17, theta, 1.0, v_next=0.6, gamma=0.5, cfg=CFG)
    b = T.q_label(SHAPE, 24, 17, opposite, 1.0, v_next=0.6, gamma=0.5, cfg=CFG)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    np.testing.assert_allclose(T.rotation_target(theta, primitive), T.rotation_target(opposite, primitive),
                               atol=1e-12)
    assert primitive in SYMMETRIC_PRIMITIVES


def test_push_is_directional():
    assert "push" not in SYMMETRIC_PRIMITIVES
    assert T.rotation_target(0.3, "push") == pytest.approx(encode_angle(0.3, "push"))
    c, s = T.rotation_target(0.3, "push")
    c2, s2 = T.rotation_target(0.3 + math.pi, "push")
    assert c == pytest.approx(-c2) and s == pytest.approx(-s2)


def test_rotation_targets_imitate_successes_only():
    # A pick at 0 that succeeded: (cos 0, sin 0), weight 1; one at pi/4 that failed: its encoding, weight 0.
    targets, weights = T.rotation_targets([0.0, math.pi / 4], [True, False], "pick", 1)
    assert targets.dtype == weights.dtype == torch.float32 and targets.shape == (2, 2)
    np.testing.assert_allclose(targets.numpy(), [[1.0, 0.0], [0.0, 1.0]], atol=1e-7)
    assert weights.tolist() == [1.0, 0.0]
    # a push at pi/2 with two harmonics: four values, (cos, sin) of theta and of 2 theta.
    targets, weights = T.rotation_targets([math.pi / 2], [True], "push", 2)
    np.testing.assert_allclose(targets.numpy(), [[0.0, 1.0, -1.0, 0.0]], atol=1e-7)
    assert weights.tolist() == [1.0]


def test_return_range_and_clipping_the_bootstrap():
    from romannet.common.config import RewardConfig

    assert T.return_range(RewardConfig(), 0.5) == (0.0, 2.0)  # rewards <= 1 (pick/place), gamma 0.5
    assert T.return_range(RewardConfig(pick_weight=0.5, place_weight=0.5, push_weight=0.2), 0.75) == (0.0, 2.0)
    assert T.clip_value(7.6, (0.0, 2.0)) == 2.0 and T.clip_value(-0.5, (0.0, 2.0)) == 0.0
    assert T.clip_value(0.3, (0.0, 2.0)) == 0.3
    with pytest.raises(ValueError, match="gamma"):
        T.return_range(RewardConfig(), 1.0)
