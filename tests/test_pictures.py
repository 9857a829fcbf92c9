"""The pictures' shared drawing (common.pictures): one orientation for camera images and heightmaps, and
actions at the workspace's edge drawn whole."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from romannet.common.heightmap import look_at
from romannet.common.pictures import (
    TITLE_PX,
    ActionGlyph,
    camera_turns,
    heightmap_panel,
    margin_px,
    tick_labels,
    titled,
    top_view,
    turn_camera,
)

W, H, F = 64, 48, 40.0  # a small pinhole camera: width, height, focal length in px


def _project(T_world_cam: np.ndarray, point: tuple[float, float, float]) -> tuple[int, int]:
    """(row, col) of a world point in the camera image (OpenCV frame: x right, y down, z forward)."""
    p = np.linalg.inv(T_world_cam) @ np.array([*point, 1.0])
    return int(round(F * p[1] / p[2] + (H - 1) / 2)), int(round(F * p[0] / p[2] + (W - 1) / 2))


def _where(image: np.ndarray, value: int) -> tuple[float, float]:
    rows, cols = np.nonzero(image == value)
    return float(rows.mean()), float(cols.mean())


@pytest.mark.parametrize("eye, up", [((0.5, 0.0, 0.75), (-1.0, 0.0, 0.0)),  # the simulator's camera
                                     ((0.5, 0.0, 0.75), (1.0, 0.0, 0.0)),
                                     ((0.5, 0.0, 0.75), (0.0, 1.0, 0.0)),
                                     ((0.5, 0.0, 0.75), (0.2, -1.0, 0.0)),
                                     ((0.2, 0.1, 0.6), (0.0, 0.0, 1.0))])  # slanted, from the robot's side
def test_camera_image_and_heightmap_share_one_orientation(eye, up) -> None:
    """Two marks, east (+x) and north (+y) of the workspace centre, land on the same sides in the turned
    camera image as in the heightmap drawn from above: east to the right, north up."""
    T = look_at(np.array(eye), np.array((0.5, 0.0, 0.0)), np.array(up))
    camera = np.zeros((H, W), np.uint8)
    heightmap = np.zeros((40, 40), np.uint8)  # rows along +y, cols along +x, centre (0.5, 0) at (20, 20)
    for value, (dx, dy) in ((1, (0.1, 0.0)), (2, (0.0, 0.1)), (3, (0.0, 0.0))):
        camera[_project(T, (0.5 + dx, dy, 0.0))] = value
        heightmap[20 + round(dy * 100), 20 + round(dx * 100)] = value
    for image in (turn_camera(camera, camera_turns(T)), top_view(heightmap)):
        centre, east, north = _where(image, 3), _where(image, 1), _where(image, 2)
        assert east[1] - centre[1] > abs(east[0] - centre[0])  # to the right, more than up or down
        assert centre[0] - north[0] > abs(north[1] - centre[1])  # up, more than left or right


def test_simulator_camera_turns_a_quarter_counter_clockwise() -> None:
    assert camera_turns(look_at(np.array((0.5, 0.0, 0.75)), np.array((0.5, 0.0, 0.0)), np.array((-1.0, 0, 0)))) == 1


@pytest.mark.parametrize("primitive", ["push", "pick"])
def test_actions_at_every_edge_are_drawn_whole(primitive: str) -> None:
    """Corners and edges of a heightmap, every 45 degrees: the drawing stays off the image's border,
    and its ring sits where the action is (row 0 is y_min, drawn at the bottom)."""
    rows = cols = 64
    push_px, gripper_px, scale = 14.0, 16.0, 2.0
    margin = margin_px(push_px, gripper_px, scale, rows * 2)
    blank = np.zeros((rows, cols, 3), np.uint8)
    for (row, col), k in itertools.product([(0, 0), (0, 63), (63, 0), (63, 63), (0, 31), (31, 0)], range(8)):
        glyph = ActionGlyph(primitive, row, col, k * math.pi / 4, push_px, gripper_px)
        panel = heightmap_panel(blank, rows * 2 + 2 * margin, glyph, margin)
        drawn = np.any(panel != panel[0, 0], axis=2)
        assert drawn.any()
        assert not (drawn[0].any() or drawn[-1].any() or drawn[:, 0].any() or drawn[:, -1].any()), (row, col, k)
        ring_y, ring_x = margin + (rows - row - 0.5) * scale, margin + (col + 0.5) * scale
        ys, xs = np.nonzero(drawn)
        near = np.hypot(ys - ring_y, xs - ring_x) < 8
        assert near.any()


def test_titled_puts_a_bar_above() -> None:
    panel = np.full((10, 300, 3), 7, np.uint8)
    out = titled(panel, "depth heightmap")
    assert out.shape == (10 + TITLE_PX, 300, 3) and (out[TITLE_PX:] == 7).all() and (out[:TITLE_PX] > 200).any()


def test_learner_action_image_is_drawn_from_above_too() -> None:
    """TensorBoard's action image (learner.metrics) in the same orientation: row 0 (y_min) at the bottom."""
    from romannet.learner.metrics import action_image

    q = np.zeros((20, 20), np.float32)
    q[0, :] = 1.0  # the highest Q along row 0
    image = action_image(np.zeros((20, 20, 3), np.uint8), q, 0, 5, 0.0, scale=2)
    q_panel = image[:, 40:]
    assert q_panel[-1, 20].sum() > q_panel[0, 20].sum()  # bright (yellow) at the bottom, dark on top
    rows = np.nonzero(image[:, :40, 0] == 255)[0]  # the red ring of the action on the colour heightmap
    assert rows.min() >= 30


def test_colour_bar_ticks_tell_close_values_apart() -> None:
    """An untrained net's Q map spans a few thousandths of its values: every tick must still differ."""
    q = [0.00131 - i * 0.00002 for i in range(5)]
    assert tick_labels(q) == ["1.31e-03", "1.29e-03", "1.27e-03", "1.25e-03", "1.23e-03"]
    assert tick_labels([1.2345, 1.2355]) == ["1.23", "1.24"]
    assert tick_labels([0.3, 0.25, 0.2, 0.15, 0.1, 0.05, 0.0]) == ["0.3", "0.25", "0.2", "0.15", "0.1", "0.05", "0"]
