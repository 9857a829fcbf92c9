"""Rotation augmentation of a training transition: the scene turned about the executed pixel, and the action
with it (learner.augment_rotation).

Picking, placing and pushing on a table are the same actions when the whole scene turns about a vertical
axis, and so are their outcome and reward. Turning the heightmaps about the executed pixel by a random angle
phi and adding phi to the action's angle gives the nets that transition at every orientation: the rotation
head, which otherwise sees each cube at the one yaw it had, learns the angle relative to the object; the Q
maps see the object at new yaws too. The pixel itself stays where it was, so its label's support stays in the
image; content that turns out of the frame is lost and the frame's new corners are empty table (depth 0,
the colour image's median colour). V(s_{t+1}) is a max over the next state's maps, unchanged by the turn,
so it is computed on the recorded next state.

Frames: heightmap (col, row) is world (x, y) (common.heightmap), and an action's angle is its yaw in that
frame, so a turn of +phi in (col, row) adds phi to the angle.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from romannet.common.action import PRIMITIVES
from romannet.common.wire_messages import TransitionMsg


def rotate_about(image: np.ndarray, row: int, col: int, phi_rad: float,
                 fill: float | tuple[float, ...]) -> np.ndarray:
    """image (h, w) or (h, w, c) turned by phi about pixel (row, col): a point at (col + dx, row + dy) moves to
    (col + dx cos phi - dy sin phi, row + dx sin phi + dy cos phi); uncovered pixels get `fill`. Bilinear;
    same dtype and shape."""
    h, w = image.shape[:2]
    # cv2's matrix turns by -angle in (x right, y down) pixel coordinates: pass -phi.
    m = cv2.getRotationMatrix2D((float(col), float(row)), -math.degrees(phi_rad), 1.0)
    return cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=fill)


def augment_yaws(seed: int, update: int, primitive: str, n: int) -> list[float]:
    """n yaws, uniform in [-pi, pi), for the items of one primitive in the update numbered `update`: drawn
    from (seed, update, primitive) alone, so a resumed learner turns its items as the uninterrupted one would."""
    rng = np.random.default_rng([seed, update, PRIMITIVES.index(primitive)])
    return [float(v) for v in rng.uniform(-math.pi, math.pi, n)]


def turned_angle(angle_rad: float, phi_rad: float) -> float:
    """angle + phi wrapped to (-pi, pi]."""
    a = math.remainder(angle_rad + phi_rad, 2 * math.pi)
    return math.pi if a == -math.pi else a


def rotated_transition(t: TransitionMsg, phi_rad: float) -> TransitionMsg:
    """The transition with its before-heightmaps and action turned by phi about the executed pixel (the
    after-heightmaps, reward and outcome unchanged: see the module docstring)."""
    row, col = t.action.row, t.action.col
    table = tuple(float(v) for v in np.median(t.color_before.reshape(-1, t.color_before.shape[-1]), axis=0))
    depth = np.nan_to_num(t.depth_before, nan=0.0)
    return dataclasses.replace(
        t, color_before=rotate_about(t.color_before, row, col, phi_rad, table),
        depth_before=rotate_about(depth, row, col, phi_rad, 0.0),
        action=dataclasses.replace(t.action, angle_rad=turned_angle(t.action.angle_rad, phi_rad)))
