"""learner.augment = "rotate": each training window centred on its executed pixel, turned and mirrored, the
action's angle moved with it."""

from __future__ import annotations

import math

import _learner_helpers as H
import numpy as np
import pytest
import torch

from romannet.common.config import ModelConfig, RewardConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.errors import ConfigError
from romannet.common.grasp_clearance import GripperFootprint, angle_bin, clear_picks
from romannet.common.model import preprocess_batch
from romannet.learner.augment import SYMMETRIES, TURNS, moved_angle, moved_window, symmetry_index
from romannet.learner.targets import q_label

CASES = [(0, False), (0, True), (3, False), (8, True), (13, False), (21, True), (30, False)]


def _window(label, support, k, mirrored, row, col, angle, size=64):
    color = np.zeros((*label.shape, 3), np.uint8)
    depth = np.zeros(label.shape, np.float32)
    return moved_window(label, support, color, depth, row, col, angle, k, mirrored, size)


@pytest.mark.parametrize("k, mirrored", CASES)
def test_the_label_of_the_moved_action_is_the_moved_label(k: int, mirrored: bool) -> None:
    """The anisotropic Gaussian lies along the gripper's axis: computed for the moved action on the window it
    matches the moved label, and not the label of a turn the other way (the angle's sign is right)."""
    cfg = RewardConfig(sigma_y_px=4.0)  # a wide label, so a pixel of resampling matters little
    row, col, angle = 60, 70, 0.4
    label, support = q_label((128, 128), row, col, angle, 1.0, 0.3, 0.5, cfg)
    (win_label, win_support, _, _), r, c, a = _window(label, support, k, mirrored, row, col, angle)
    assert win_label[r, c] == pytest.approx(label[row, col])  # the executed pixel keeps its target
    ideal, ideal_support = q_label(win_label.shape, r, c, a, 1.0, 0.3, 0.5, cfg)
    on = win_support | ideal_support
    assert np.abs(win_label - ideal)[on].mean() < 0.025  # resampled to the nearest pixel: a part-pixel off
    assert (win_support == ideal_support).mean() > 0.99
    if k % (TURNS // 4):  # not a quarter turn's multiple: the label of a turn the other way is far off
        wrong, _ = q_label(win_label.shape, r, c, moved_angle(angle, -k, mirrored), 1.0, 0.3, 0.5, cfg)
        assert np.abs(win_label - wrong)[on].mean() > 0.1


def test_the_moved_pick_is_clear_where_the_pick_was() -> None:
    """The pick clearance rule (the hand's own footprint) agrees: at the window's centre a pick at the moved
    angle is clear where the original pick was, over every closing angle and several symmetries."""
    res, bins = 0.005, 16
    hm = np.zeros((96, 96), np.float32)
    hm[40:50, 44:52] = 0.04
    hm[41:49, 56:62] = 0.06
    hm[60:67, 30:42] = 0.03
    hand = GripperFootprint(travel_m=0.055, pick_depth_m=0.03, tip_floor_m=0.006)
    clear = clear_picks(hm, res, hand, bins)
    agree, total = 0, 0
    for row, col in ((45, 48), (63, 36), (44, 58)):
        for k, mirrored in CASES:
            color = np.zeros((*hm.shape, 3), np.uint8)
            (_, _, _, depth), r, c, _ = moved_window(hm, hm > 0, color, hm, row, col, 0.0, k, mirrored, 96)
            moved = clear_picks(depth, res, hand, bins)
            for b in range(bins):
                b2 = int(angle_bin(np.array(moved_angle(b * math.pi / bins, k, mirrored)), bins))
                agree += bool(moved[b2, r, c] == clear[b, row, col])
                total += 1
    assert agree / total > 0.95, (agree, total)


def test_each_item_gets_a_fixed_symmetry_and_all_occur() -> None:
    assert symmetry_index(17, 5) == symmetry_index(17, 5)
    drawn = [symmetry_index(i, u) for i in range(200) for u in range(10)]
    index = [k + TURNS * m for k, m in drawn]
    counts = np.bincount(index, minlength=SYMMETRIES)
    assert counts.min() > 0.5 * counts.mean()
    assert len({symmetry_index(3, u) for u in range(400)}) == SYMMETRIES


def test_a_mirror_maps_an_angle_to_its_reflection() -> None:
    assert moved_angle(0.3, 0, True) == pytest.approx(math.pi - 0.3)
    assert moved_angle(0.3, 8, False) == pytest.approx(0.3 + math.pi / 2)
    assert moved_angle(0.3, 16, False) == pytest.approx(0.3 - math.pi)  # a half turn: the push reverses


@pytest.mark.parametrize("item_id", [1, 2, 3, 4])
def test_a_step_trains_the_moved_window_at_the_moved_angle(item_id: int) -> None:
    """The learner's step under an item's symmetry: its TD error is the net's Q on the moved window, at the
    executed pixel's new place and, for a net with a Q per closing angle, at the moved angle's map."""
    cfg = ModelConfig(channels=8, residual_blocks=1, q_head_init="default", pick_angle_bins=16, precision="fp32")
    tr = H.transition(primitive="pick", row=9, col=21, angle_rad=0.7, reward=0.5, done=True, size=48)
    k, mirrored = symmetry_index(item_id, 0)
    t = H.trainer(model=cfg, augment="rotate", train_crop_px=32)
    label, support = q_label(tr.shape, 9, 21, 0.7, 0.5, 0.0, t.cfg.gamma, t.reward_cfg)
    (_, _, color, depth), r, c, a = moved_window(label, support, tr.color_before, tr.depth_before, 9, 21, 0.7,
                                                 k, mirrored, 32)
    with torch.no_grad():  # train mode, as the step's own forward pass
        q, _ = t.model.nets["pick"](preprocess_batch(color[None], depth[None]))
    expected = abs(float(q[0, int(angle_bin(np.array(a), 16)), r, c]) - 0.5)
    stats = t.train_step([(tr, 1.0, item_id)])
    assert stats.td_errors[0] == pytest.approx(expected, rel=1e-4)


def test_without_a_turn_the_window_is_the_plain_crop_centred_on_the_pixel() -> None:
    rng = np.random.default_rng(0)
    label = rng.random((64, 64)).astype(np.float32)
    (win, *_), r, c, a = _window(label, label > 0.5, 0, False, 30, 40, 0.2, size=32)
    np.testing.assert_array_equal(win, label[14:46, 24:56])
    assert (r, c, a) == (16, 16, pytest.approx(0.2))


def test_the_config_names_the_choices() -> None:
    assert LearnerConfig().augment == "none"
    with pytest.raises(ConfigError, match="learner.augment"):
        LearnerConfig(augment="d4")
