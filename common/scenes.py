"""Seeded synthetic heightmaps (rotated blocks on a textured floor): the inputs of the inference benchmark, its
agreement measurement and int8's error calibration (common/int8net.py)."""

from __future__ import annotations

import math

import numpy as np

SIZE_PX = 224


def synthetic_scene(rng: np.random.Generator, h: int = SIZE_PX, w: int = SIZE_PX) -> tuple[np.ndarray, np.ndarray]:
    """Heightmaps of 3–10 rotated rectangular blocks on a textured floor: (h,w,3) uint8, (h,w) float32 m."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = np.zeros((h, w), np.float32)
    floor = rng.integers(40, 90, size=3)
    color = np.clip(floor + rng.integers(-6, 7, size=(h, w, 3)), 0, 255).astype(np.uint8)
    for _ in range(int(rng.integers(3, 11))):
        cy, cx = rng.uniform(0.1, 0.9) * h, rng.uniform(0.1, 0.9) * w
        half_len, half_wid = rng.uniform(4, 15, size=2)
        a = rng.uniform(0, math.pi)
        u = (cols - cx) * math.cos(a) + (rows - cy) * math.sin(a)
        v = -(cols - cx) * math.sin(a) + (rows - cy) * math.cos(a)
        mask = (np.abs(u) <= half_len) & (np.abs(v) <= half_wid)
        top = np.float32(rng.uniform(0.02, 0.08))
        depth[mask] = np.maximum(depth[mask], top)
        color[mask] = rng.integers(0, 256, size=3)
    return color, depth
