"""Symmetry augmentation of training windows (learner.augment = "d4").

A top-down scene transposed or mirrored is another scene the same physics plays out on: the action's pixel
and angle move with the image, and so do its label and support. Training each item under one of the 8
symmetries of the square (the dihedral group D4: transpose or not, then flip rows or not, flip columns or
not) shows the nets every orientation of what they saw, as BulletArm's D4 augmentation and equivariant nets
do. The symmetry of an item is drawn from its replay id and the update count, so a resumed learner trains
the same windows as one that never stopped.

Angles as in common.action: from the column (x) axis toward the row (y) axis. A direction (cos a, sin a)
becomes (sin a, cos a) under a transpose (a -> pi/2 - a), (cos a, -sin a) when the rows flip (a -> -a) and
(-cos a, sin a) when the columns flip (a -> pi - a); pick and place angles are taken modulo pi afterwards by
whoever reads them, push angles keep their direction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

D4_SIZE = 8
_MIX = 0x9E3779B97F4A7C15  # an odd 64-bit constant: consecutive ids and updates spread over the 8 symmetries


def d4_index(item_id: int, update: int) -> int:
    """The symmetry (0..7) an item is trained under at an update: bit 0 transpose, bit 1 flip rows, bit 2
    flip columns. Deterministic, so training is reproducible and a resume is exact."""
    x = ((int(item_id) * _MIX) ^ (int(update) * 0xBF58476D1CE4E5B9)) & 0xFFFFFFFFFFFFFFFF
    x ^= x >> 31
    x = (x * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (x >> 29) % D4_SIZE


def transform_angle(g: int, angle_rad: float) -> float:
    """The action's angle after symmetry g (radians, in (-pi, pi])."""
    a = float(angle_rad)
    if g & 1:
        a = math.pi / 2 - a
    if g & 2:
        a = -a
    if g & 4:
        a = math.pi - a
    return math.remainder(a, 2 * math.pi)


def transform_pixel(g: int, row: int, col: int, shape: tuple[int, int]) -> tuple[int, int]:
    """(row, col) after symmetry g of an image of this shape (h, w) (a transpose needs h == w)."""
    h, w = shape
    if g & 1:
        if h != w:
            raise ValueError(f"a transpose needs a square image, got {h}x{w}")
        row, col = col, row
    if g & 2:
        row = h - 1 - row
    if g & 4:
        col = w - 1 - col
    return row, col


def transform_image(g: int, image: np.ndarray) -> np.ndarray:
    """An (h, w, ...) array after symmetry g, contiguous."""
    if g & 1:
        if image.shape[0] != image.shape[1]:
            raise ValueError(f"a transpose needs a square image, got {image.shape[0]}x{image.shape[1]}")
        image = image.swapaxes(0, 1)
    if g & 2:
        image = image[::-1]
    if g & 4:
        image = image[:, ::-1]
    return np.ascontiguousarray(image)


def usable(g: int, shape: tuple[int, int]) -> int:
    """g, less its transpose where the image is not square (flips alone still apply)."""
    return g & ~1 if shape[0] != shape[1] else g


def transform_window(g: int, images: Sequence[np.ndarray], row: int, col: int,
                     angle_rad: float) -> tuple[list[np.ndarray], int, int, float]:
    """One item's window (label, support, colour, depth, ...; all (h, w, ...)) and its action under g."""
    shape = images[0].shape[:2]
    g = usable(g, shape)
    r, c = transform_pixel(g, row, col, shape)
    return [transform_image(g, im) for im in images], r, c, transform_angle(g, angle_rad)
