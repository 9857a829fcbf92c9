"""Symmetry augmentation of training windows (learner.augment = "rotate").

A top-down scene turned about the vertical axis, or mirrored, is another scene the same physics plays out
on: the action's pixel and angle move with the image, and so do its label and support. Each item is trained
on a window centred on its executed pixel, turned by k pi / 16 (k = 0 .. 31, a full turn: pushes have a
direction) and mirrored or not. The 16 closing angles a pick net with a Q per angle has (model.pick_angle_bins)
are then trained from every pick at every angle, as VPG's and the paper's nets see each scene at 16 input
rotations, and BulletArm augments its data with the square's symmetries. The symmetry of an item is drawn
from its replay id and the update count, so a resumed learner trains the same windows as one that never
stopped.

Angles as in common.action: from the column (x) axis toward the row (y) axis; in (x, y) = (col, row) a turn
by phi maps a direction at angle a to a + phi, and a mirror of the columns maps it to pi - a. Pick and place
angles are taken modulo pi afterwards by whoever reads them; push angles keep their direction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

TURNS = 32  # steps of pi / 16 over a full turn
SYMMETRIES = 2 * TURNS  # each turn mirrored or not


def symmetry_index(item_id: int, update: int) -> tuple[int, bool]:
    """(turn k: the window is turned by k pi / 16, mirrored) an item is trained under at an update.
    Deterministic, so training is reproducible and a resume is exact."""
    x = ((int(item_id) * 0x9E3779B97F4A7C15) ^ (int(update) * 0xBF58476D1CE4E5B9)) & 0xFFFFFFFFFFFFFFFF
    x ^= x >> 31
    x = (x * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    s = (x >> 29) % SYMMETRIES
    return s % TURNS, s >= TURNS


def turn_rad(k: int) -> float:
    """A turn of k steps of pi / 16, in radians."""
    return k * math.pi / (TURNS // 2)


def moved_angle(angle_rad: float, k: int, mirrored: bool) -> float:
    """The action's angle after turning by k pi / 16, then mirroring the columns (radians, in (-pi, pi])."""
    a = float(angle_rad) + turn_rad(k)
    if mirrored:
        a = math.pi - a
    return math.remainder(a, 2 * math.pi)


def window_affine(row: int, col: int, k: int, size: int) -> np.ndarray:
    """2x3 affine from a window pixel (x = col, y = row) to the image pixel it shows, for cv2.warpAffine with
    WARP_INVERSE_MAP: the window is centred on (row, col) and turned by k pi / 16 (a direction at angle a in
    the image is at a + k pi / 16 in the window)."""
    phi = turn_rad(k)
    c, s = math.cos(phi), math.sin(phi)
    back = np.array([[c, s], [-s, c]])  # the turn by -phi
    centre = np.array([size // 2, size // 2], dtype=np.float64)
    offset = np.array([col, row], dtype=np.float64) - back @ centre
    return np.hstack([back, offset[:, None]])


def _warp(image: np.ndarray, affine: np.ndarray, size: int, fill: float | tuple[float, ...]) -> np.ndarray:
    flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    src = image.astype(np.uint8) if image.dtype == np.bool_ else image
    out = cv2.warpAffine(np.ascontiguousarray(src), affine, (size, size), flags=flags,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
    return out.astype(image.dtype, copy=False)


def moved_window(label: np.ndarray, support: np.ndarray, color: np.ndarray, depth: np.ndarray, row: int, col: int,
                 angle_rad: float, k: int, mirrored: bool, size: int) -> tuple[list[np.ndarray], int, int, float]:
    """An item's size x size training window (label, support, colour, depth) centred on its executed pixel
    (row, col) of the whole heightmaps, turned by k pi / 16 and mirrored or not, with the executed pixel and
    angle in it. Outside the heightmap: zero label, no support, the table (depth 0) in its median colour."""
    affine = window_affine(row, col, k, size)
    # The table's colour: the median of every 8th pixel each way (the table fills most of the workspace), cheap
    # enough for each item of each training step.
    table = tuple(float(v) for v in np.median(color[::8, ::8].reshape(-1, color.shape[-1]), axis=0))
    out = [_warp(label, affine, size, 0.0), _warp(support, affine, size, 0.0), _warp(color, affine, size, table),
           _warp(depth, affine, size, 0.0)]
    r, c = size // 2, size // 2
    if mirrored:
        out = [np.ascontiguousarray(im[:, ::-1]) for im in out]
        c = size - 1 - c
    return out, r, c, moved_angle(angle_rad, k, mirrored)


def window_size(shape: Sequence[int], crop: int) -> int:
    """The augmented window's side: the training crop, or the whole (square) heightmap's side without one."""
    h, w = shape[:2]
    if crop:
        return crop
    if h != w:
        raise ValueError(f"learner.augment = 'rotate' without a crop needs a square heightmap, got {h}x{w}")
    return h
