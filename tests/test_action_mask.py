"""Common-sense action masks (exploration.action_mask): the mask rules, the actor's choice and V(s), and the
learner's bootstrap V(s') over the same pixels."""

from __future__ import annotations

import numpy as np
import pytest
from _learner_helpers import SMALL_MODEL, transition
from _learner_helpers import trainer as small_trainer

from romannet.common.action_mask import action_masks, masked_q
from romannet.common.config import ExplorationConfig
from romannet.common.configbase import ConfigError
from romannet.common.exploration import select_action
from romannet.common.model import RoManNet
from romannet.common.policy import decide
from romannet.learner.trainer import Trainer

CFG = ExplorationConfig(action_mask=True, mask_pick_reach_px=2, mask_push_reach_px=4)


def _one_block(size: int = 32) -> np.ndarray:
    depth = np.zeros((size, size), np.float32)
    depth[14:18, 14:18] = 0.03  # a 4x4 px block
    return depth


def test_masks_follow_the_heightmap() -> None:
    masks = action_masks(_one_block(), ("push", "pick", "place"), CFG)
    assert masks["place"].sum() == 16 and masks["place"][14:18, 14:18].all()
    assert masks["pick"][12, 15] and not masks["pick"][11, 15]  # 2 px of reach around the block
    assert masks["push"][10, 15] and not masks["push"][9, 15]  # 4 px
    assert masks["pick"].sum() < masks["push"].sum()
    # An empty scene leaves every pixel valid: nothing can be touched anywhere, so nothing is worse.
    empty = action_masks(np.zeros((32, 32), np.float32), ("pick",), CFG)
    assert empty["pick"].all()


def test_the_greedy_and_the_explored_actions_stay_inside_the_mask() -> None:
    depth = _one_block()
    masks = action_masks(depth, ("pick",), CFG)
    q = np.random.default_rng(0).random((32, 32)).astype(np.float32)
    q[0, 0] = 5.0  # the raw argmax lies on the empty floor
    mq = masked_q(q, masks["pick"])
    assert mq.max() == q[masks["pick"]].max() and np.isfinite(mq).all()
    angles = {"pick": np.zeros((32, 32), np.float32)}
    greedy = select_action({"pick": mq}, angles, 0.0, CFG, np.random.default_rng(1), masks)
    assert masks["pick"][greedy.row, greedy.col] and greedy.q_value == pytest.approx(float(mq.max()))
    rng = np.random.default_rng(2)
    explored = [select_action({"pick": mq}, angles, 1.0, CFG, rng, masks) for _ in range(50)]
    assert all(masks["pick"][a.row, a.col] for a in explored)


def test_decide_masks_and_its_maps_give_the_masked_value() -> None:
    depth = _one_block()
    color = np.zeros((32, 32, 3), np.uint8)
    model = RoManNet(SMALL_MODEL, seed=0)
    action, maps = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("push", "pick"), CFG,
                          return_maps=True)
    masks = action_masks(depth, ("push", "pick"), CFG)
    assert masks[action.primitive][action.row, action.col]
    _, raw = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("push", "pick"),
                    ExplorationConfig(), return_maps=True)
    for p in ("push", "pick"):  # V(s) = max Q over the valid pixels
        assert maps.q[p].max() == pytest.approx(float(raw.q[p][masks[p]].max()))


def test_the_learners_bootstrap_takes_the_max_over_the_same_pixels() -> None:
    t = transition(32, seed=3, reward=1.0, depth_after=_one_block())
    plain = small_trainer(seed=0, actor_value_max_age=0, bootstrap_clip=False)  # the raw max, unclipped
    masked = Trainer(SMALL_MODEL, plain.cfg, plain.reward_cfg, plain.task_cfg, seed=0, exploration_cfg=CFG)
    v_plain, v_masked = plain.next_state_values([t])[0], masked.next_state_values([t])[0]
    _, raw = decide(plain.model.eval(), t.color_after, t.depth_after, False, 0.0, np.random.default_rng(0),
                    ("push", "pick"), ExplorationConfig(), return_maps=True)
    masks = action_masks(t.depth_after, ("push", "pick"), CFG)
    expected = max(float(raw.q[p][masks[p]].max()) for p in ("push", "pick"))
    assert v_masked == pytest.approx(expected, abs=1e-4) and v_masked <= v_plain + 1e-6


def test_mask_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match="exploration.mask_min_height_m"):
        ExplorationConfig(mask_min_height_m=0.0)
    with pytest.raises(ConfigError, match="exploration.mask_pick_reach_px"):
        ExplorationConfig(mask_pick_reach_px=-1)
