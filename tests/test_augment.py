"""learner.augment_rotation: the scene turned about the executed pixel, the action's angle with it."""

from __future__ import annotations

import math

import _learner_helpers as H
import cv2
import numpy as np
import pytest

from romannet.analyse.pick_offsets import pick_offset
from romannet.learner.augment import augment_yaws, rotate_about, rotated_transition, turned_angle

SIZE = 48
RES_M = 0.003  # 3 mm pixels: a 5 cm cube is ~16 px


def cube_scene(yaw_rad: float, centre=(24.0, 24.0), side_px: float = 16.0):
    """(colour uint8, depth float32) of one cube at `yaw` on an empty grey table; centre = (row, col)."""
    half = side_px / 2
    corners = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    pts = corners @ np.array([[c, s], [-s, c]]) + np.array([centre[1], centre[0]])  # (col, row) points
    depth = np.zeros((SIZE, SIZE), np.float32)
    cv2.fillPoly(depth, [np.round(pts * 16).astype(np.int32)], 0.05, shift=4)
    color = np.full((SIZE, SIZE, 3), 120, np.uint8)
    color[depth > 0] = (200, 40, 40)
    return color, depth


def test_rotate_about_turns_points_about_the_pixel_in_the_actions_sense():
    img = np.zeros((SIZE, SIZE), np.float32)
    img[10, 12] = 1.0  # the pivot
    img[10, 17] = 2.0  # 5 px along +col (angle 0) from it
    out = rotate_about(img, 10, 12, math.pi / 2, 0.0)
    assert out[10, 12] == pytest.approx(1.0) and out[15, 12] == pytest.approx(2.0)  # now along +row (angle +90)
    assert out[10, 17] == pytest.approx(0.0)
    color = np.full((SIZE, SIZE, 3), 7, np.uint8)
    turned = rotate_about(color, 0, 0, 0.3, (9.0, 9.0, 9.0))
    assert turned.dtype == np.uint8 and turned.shape == color.shape
    assert (turned[0, SIZE - 1] == 9).all() and (turned[SIZE - 1, 0] == 7).all()  # uncovered corner is filled
    assert turned_angle(3.0, 0.5) == pytest.approx(3.5 - 2 * math.pi) and turned_angle(-math.pi, 0.0) == math.pi


@pytest.mark.parametrize("phi_deg", [30.0, -75.0, 140.0])
def test_a_turned_pick_is_the_same_pick_relative_to_the_cube(phi_deg):
    """The pick measured against the cube under it (romannet.analyse.pick_offsets: offsets along / across the
    closing axis, angle to the faces) is the same before and after the turn, off the cube's centre included."""
    color, depth = cube_scene(math.radians(10))
    t = H.transition(size=SIZE, row=23, col=27, angle_rad=math.radians(25), color_before=color, depth_before=depth)
    turned = rotated_transition(t, math.radians(phi_deg))
    assert (turned.action.row, turned.action.col) == (23, 27)
    assert turned.action.angle_rad == pytest.approx(turned_angle(math.radians(25), math.radians(phi_deg)))
    before = pick_offset(depth, 23, 27, t.action.angle_rad, RES_M)
    after = pick_offset(turned.depth_before, 23, 27, turned.action.angle_rad, RES_M)
    assert before["face_angle_deg"] == pytest.approx(15.0, abs=3.0)  # 25 deg closing axis, cube at 10 deg
    assert after["face_angle_deg"] == pytest.approx(15.0, abs=3.0)  # both turned by phi: still 15 deg
    assert after["along_m"] == pytest.approx(before["along_m"], abs=0.0015)
    assert after["across_m"] == pytest.approx(before["across_m"], abs=0.0015)
    assert after["area_cm2"] == pytest.approx(before["area_cm2"], rel=0.1)
    assert turned.color_before[0, 0].tolist() == [120, 120, 120]  # the table's colour in uncovered corners
    assert (turned.depth_after == t.depth_after).all() and turned.reward == t.reward and turned.success


def test_the_trainer_trains_each_item_turned_by_its_seeded_random_yaw():
    """With augment_rotation, train_step on a transition is exactly train_step without it on that transition
    turned by augment_yaws(seed, update, primitive): the same turn after a resume, a new one every update."""
    color, depth = cube_scene(0.2)
    item = (H.transition(size=SIZE, row=23, col=27, angle_rad=0.4, color_before=color, depth_before=depth),
            1.0, 0)
    augmented = H.trainer(augment_rotation=True, seed=4)
    plain = H.trainer(augment_rotation=False, seed=4)
    phi = augment_yaws(4, 0, "pick", 1)[0]
    assert augment_yaws(4, 0, "pick", 3)[0] == phi and len(set(augment_yaws(4, 0, "pick", 3))) == 3
    assert augment_yaws(4, 1, "pick", 1)[0] != phi and augment_yaws(4, 0, "place", 1)[0] != phi
    assert all(-math.pi <= v < math.pi for v in augment_yaws(0, 7, "push", 50))
    a = augmented.train_step([item])
    b = plain.train_step([(rotated_transition(item[0], phi), 1.0, 0)])
    assert a.loss == pytest.approx(b.loss, rel=1e-5) and a.td_errors == pytest.approx(b.td_errors, rel=1e-5)
    unturned = H.trainer(augment_rotation=False, seed=4).train_step([item])
    assert unturned.loss != pytest.approx(a.loss, rel=1e-3)  # the turn changed what was trained

