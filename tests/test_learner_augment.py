"""learner.augment = "d4": each training window under one of the square's 8 symmetries, the action moved with it."""

from __future__ import annotations

import math

import _learner_helpers as H
import numpy as np
import pytest

from romannet.common.config import RewardConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.errors import ConfigError
from romannet.common.grasp_clearance import GripperFootprint, angle_bin, clear_picks
from romannet.learner.augment import (
    D4_SIZE,
    d4_index,
    transform_angle,
    transform_image,
    transform_pixel,
    transform_window,
)
from romannet.learner.targets import q_label

SYMMETRIES = range(D4_SIZE)


@pytest.mark.parametrize("g", SYMMETRIES)
def test_a_pixel_moves_with_its_image(g: int) -> None:
    image = np.zeros((12, 12), np.float32)
    image[3, 8] = 1.0
    moved = transform_image(g, image)
    assert np.argwhere(moved == 1.0).tolist() == [list(transform_pixel(g, 3, 8, (12, 12)))]


@pytest.mark.parametrize("g", SYMMETRIES)
def test_the_label_of_the_moved_action_is_the_moved_label(g: int) -> None:
    """The anisotropic Gaussian lies along the gripper's axis: computed for the transformed action it is the
    transformed label, which checks the angle's transform against the label's own convention."""
    cfg = RewardConfig()
    shape = (64, 64)
    for row, col, angle in ((20, 30, 0.4), (40, 12, -1.1), (31, 33, 2.5)):
        label, support = q_label(shape, row, col, angle, 1.0, 0.3, 0.5, cfg)
        r, c = transform_pixel(g, row, col, shape)
        moved_label, moved_support = q_label(shape, r, c, transform_angle(g, angle), 1.0, 0.3, 0.5, cfg)
        np.testing.assert_allclose(moved_label, transform_image(g, label), atol=1e-6)
        np.testing.assert_array_equal(moved_support, transform_image(g, support))


@pytest.mark.parametrize("g", SYMMETRIES)
def test_the_moved_pick_is_clear_where_the_pick_was(g: int) -> None:
    """The pick clearance rule (the hand's real footprint) agrees: a pick along bin k on the moved heightmap is
    clear where the original pick was, at the moved angle's bin."""
    res, bins = 0.005, 16
    hm = np.zeros((64, 64), np.float32)
    hm[20:30, 24:32] = 0.04
    hm[21:29, 36:42] = 0.06
    hm[40:47, 10:22] = 0.03
    hand = GripperFootprint(travel_m=0.055, pick_depth_m=0.03, tip_floor_m=0.006)
    clear = clear_picks(hm, res, hand, bins)
    moved = clear_picks(transform_image(g, hm), res, hand, bins)
    for k in range(bins):
        k2 = int(angle_bin(np.array(transform_angle(g, k * math.pi / bins)), bins))
        agree = (moved[k2] == transform_image(g, clear[k])).mean()
        assert agree > 0.99, (k, k2, agree)


def test_each_item_gets_a_fixed_symmetry_and_all_eight_occur() -> None:
    assert d4_index(17, 5) == d4_index(17, 5)
    assert {d4_index(i, 0) for i in range(64)} == set(SYMMETRIES)
    assert {d4_index(3, u) for u in range(64)} == set(SYMMETRIES)
    assert len({d4_index(i, 9) for i in range(1000)}) == D4_SIZE
    counts = np.bincount([d4_index(i, u) for i in range(200) for u in range(10)], minlength=D4_SIZE)
    assert counts.min() > 0.8 * counts.mean()


def test_a_window_that_is_not_square_is_only_mirrored() -> None:
    images = [np.arange(12, dtype=np.float32).reshape(3, 4)]
    out, r, c, a = transform_window(1 | 4, images, 1, 0, 0.3)  # transpose dropped, columns flipped
    np.testing.assert_array_equal(out[0], images[0][:, ::-1])
    assert (r, c) == (1, 3) and a == pytest.approx(math.pi - 0.3)


@pytest.mark.parametrize("primitive, item_id", [("pick", 3), ("push", 3), ("pick", 1), ("pick", 5)])
def test_a_step_under_a_symmetry_is_the_step_on_the_moved_scene(primitive: str, item_id: int) -> None:
    """Training an item under symmetry g is training on the transposed or mirrored scene with the moved action
    (the learner draws g from the item's id and the update count: here all three moves, a transpose alone,
    a column flip alone)."""
    g = d4_index(item_id, 0)
    assert g in (7, 1, 4)
    tr = H.transition(primitive=primitive, row=9, col=21, angle_rad=0.7, reward=0.5, done=True)
    r, c = transform_pixel(g, 9, 21, tr.shape)
    moved = H.transition(primitive=primitive, row=r, col=c, angle_rad=transform_angle(g, 0.7), reward=0.5, done=True,
                         color_before=transform_image(g, tr.color_before),
                         depth_before=transform_image(g, tr.depth_before))
    augmented = H.trainer(augment="d4").train_step([(tr, 1.0, item_id)])
    plain = H.trainer().train_step([(moved, 1.0, item_id)])
    assert augmented.loss == pytest.approx(plain.loss, rel=1e-5)
    assert augmented.td_errors[0] == pytest.approx(plain.td_errors[0], rel=1e-5)
    unaugmented = H.trainer().train_step([(tr, 1.0, item_id)])
    assert unaugmented.loss != pytest.approx(plain.loss, rel=1e-5)


def test_the_config_names_the_choices() -> None:
    assert LearnerConfig().augment == "none"
    with pytest.raises(ConfigError, match="learner.augment"):
        LearnerConfig(augment="d8")
