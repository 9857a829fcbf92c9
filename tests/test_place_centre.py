"""Placing on the centre of the top face under the chosen pixel (task.place_on_top_centre): the face found
on the heightmap, and the robot-frame position every environment places at."""

from __future__ import annotations

import numpy as np
import pytest

from romannet.common.action import pixel_to_position, place_position
from romannet.common.config import WorkspaceConfig
from romannet.common.stack import top_face_centre

WS = WorkspaceConfig()  # 224 x 224 px at 2 mm
RES, CUBE = WS.resolution_m, 0.04  # a 4 cm cube is 20 x 20 px
PATCH = 0.015


def _cubes(*tops: tuple[int, int, float]) -> np.ndarray:
    """A heightmap with one 20 x 20 px cube top per (row0, col0, height_m)."""
    hm = np.zeros((WS.height_px, WS.width_px), np.float32)
    for r0, c0, z in tops:
        hm[r0:r0 + 20, c0:c0 + 20] = np.maximum(hm[r0:r0 + 20, c0:c0 + 20], z)
    return hm


def test_the_centre_of_a_lone_cube_top_wherever_on_it_the_pixel_is():
    hm = _cubes((100, 60, 0.04))
    for row, col in ((100, 60), (109, 69), (119, 79), (104, 75)):
        assert top_face_centre(hm, row, col, RES, CUBE, PATCH) == pytest.approx((109.5, 69.5))


def test_a_pixel_beside_a_stack_goes_onto_the_stack_the_hand_is_lowered_onto():
    hm = _cubes((100, 60, 0.08), (100, 80, 0.04))  # a 2-stack with a lone cube touching it on its right
    # 3 px off the 2-stack's right edge, on the lone cube: the patch reaches the 2-stack's top, the highest
    assert top_face_centre(hm, 110, 82, RES, CUBE, PATCH) == pytest.approx((109.5, 69.5))
    # the lone cube's far side: only its own top is in the patch
    # (the median filter rounds the floor-side corners off, so within half a pixel: 1 mm)
    assert top_face_centre(hm, 110, 96, RES, CUBE, PATCH) == pytest.approx((109.5, 89.5), abs=0.5)


def test_no_face_on_the_floor_or_on_tops_that_touch_at_one_height():
    assert top_face_centre(_cubes((100, 60, 0.04)), 20, 20, RES, CUBE, PATCH) is None
    touching = _cubes((100, 60, 0.04), (100, 80, 0.04))
    assert top_face_centre(touching, 110, 79, RES, CUBE, PATCH) is None


def test_bad_arguments_are_errors():
    hm = _cubes((100, 60, 0.04))
    with pytest.raises(ValueError, match="outside"):
        top_face_centre(hm, 500, 0, RES, CUBE, PATCH)
    with pytest.raises(ValueError, match="cube_size_m"):
        top_face_centre(hm, 0, 0, RES, 0.0, PATCH)


def test_place_position_is_the_pixel_off_or_without_a_face_and_the_face_centre_on():
    hm = _cubes((100, 60, 0.04))
    x, y, _ = pixel_to_position(104, 75, hm, WS)
    assert place_position(hm, 104, 75, WS, CUBE, False) == (x, y)
    assert place_position(hm, 20, 20, WS, CUBE, True) == pixel_to_position(20, 20, hm, WS)[:2]
    cx, cy = place_position(hm, 104, 75, WS, CUBE, True)
    # the cube spans columns 60..79 = x in [x_min + 0.120, x_min + 0.160) m: its centre is x_min + 0.140
    assert cx == pytest.approx(WS.x_min_m + 0.140) and cy == pytest.approx(WS.y_min_m + 0.220)
