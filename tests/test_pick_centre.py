"""Picking on the middle of the object under the chosen pixel (task.pick_on_object_centre): the run of object
along the closing axis found on the heightmap, and the robot-frame position every environment closes at."""

from __future__ import annotations

import math

import numpy as np
import pytest

from romannet.common.action import pick_position, pixel_to_position
from romannet.common.config import WorkspaceConfig
from romannet.common.grasp import closing_axis_offset, closing_axis_run

WS = WorkspaceConfig()  # 224 x 224 px at 2 mm
RES = WS.resolution_m


def _blocks(*blocks: tuple[int, int, int, int, float]) -> np.ndarray:
    """A heightmap with one box top per (row0, col0, rows, cols, height_m)."""
    hm = np.zeros((WS.height_px, WS.width_px), np.float32)
    for r0, c0, nr, nc, z in blocks:
        hm[r0:r0 + nr, c0:c0 + nc] = np.maximum(hm[r0:r0 + nr, c0:c0 + nc], z)
    return hm


def test_the_offset_to_the_middle_of_a_block_along_either_axis():
    hm = _blocks((100, 60, 25, 25, 0.05))  # a 5 cm block: columns 60..84, rows 100..124
    # closing along the columns (angle 0) from 2 px inside its left edge: the middle is column 72
    assert closing_axis_offset(hm, 110, 62, 0.0, RES) == pytest.approx(10 * RES)
    # the same pixel closing the opposite way round: the same point, so the same offset with the sign flipped
    assert closing_axis_offset(hm, 110, 62, math.pi, RES) == pytest.approx(-10 * RES)
    # closing along the rows (angle 90 degrees) from its last row: 12 rows back up
    assert closing_axis_offset(hm, 124, 70, math.pi / 2, RES) == pytest.approx(-12 * RES)
    # already in the middle: no move
    assert closing_axis_offset(hm, 112, 72, 0.0, RES) == pytest.approx(0.0)


def test_the_run_reaches_the_block_s_outer_edges():
    hm = _blocks((100, 60, 25, 25, 0.05))  # columns 60..84: from column 62, 2 px behind and 22 ahead
    assert closing_axis_run(hm, 110, 62, 0.0, RES) == pytest.approx((-2.5 * RES, 22.5 * RES))


def test_the_run_is_the_pixel_s_own_object_not_a_lower_one_beside_it():
    # a 5 cm block with a 1.5 cm slab touching its right side: less than half its height, not part of the run
    hm = _blocks((100, 60, 25, 25, 0.05), (100, 85, 25, 20, 0.015))
    assert closing_axis_offset(hm, 110, 80, 0.0, RES) == pytest.approx(-8 * RES)


def test_nothing_to_centre_on_gives_none():
    hm = _blocks((100, 60, 25, 25, 0.05), (100, 85, 25, 25, 0.05))  # two blocks touching side by side
    assert closing_axis_offset(hm, 110, 30, 0.0, RES) is None  # the floor
    assert closing_axis_offset(hm, 110, 80, 0.0, RES) is None  # a 10 cm run: too long to grasp across
    assert closing_axis_offset(hm, 110, 80, math.pi / 2, RES) is not None  # across the other way: one block
    edge = _blocks((100, 0, 25, 25, 0.05))
    assert closing_axis_offset(edge, 110, 5, 0.0, RES) is None  # runs off the heightmap: its middle unseen


def test_bad_arguments_name_the_problem():
    hm = _blocks()
    with pytest.raises(ValueError, match="outside"):
        closing_axis_offset(hm, 300, 10, 0.0, RES)
    with pytest.raises(ValueError, match="angle_rad"):
        closing_axis_offset(hm, 10, 10, float("nan"), RES)


def test_pick_position_moves_along_the_closing_axis_only_when_asked():
    hm = _blocks((100, 60, 25, 25, 0.05))
    angle = math.pi / 4  # the diagonal: the run from (104, 64) ends at the block's corner region
    x0, y0, _ = pixel_to_position(104, 64, hm, WS)
    assert pick_position(hm, 104, 64, angle, WS, on_object_centre=False) == (x0, y0)
    x, y = pick_position(hm, 104, 64, angle, WS, on_object_centre=True)
    offset = closing_axis_offset(hm, 104, 64, angle, RES)
    assert offset is not None and offset > 0
    assert (x - x0, y - y0) == pytest.approx((offset * math.cos(angle), offset * math.sin(angle)))
    # the floor: the pixel's own position
    assert pick_position(hm, 10, 10, angle, WS, on_object_centre=True) == pixel_to_position(10, 10, hm, WS)[:2]
