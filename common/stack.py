"""The stack height read off a depth heightmap (stacking; the rules that use it are common.episode_rules).

It takes `depth_hm`, float32 h x w in metres above the workspace floor (common.heightmap.get_heightmaps).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# cv2.medianBlur accepts float32 images only with these kernel sizes.
_FLOAT_MEDIAN_KSIZES = (3, 5)


def _as_heightmap(depth_hm: np.ndarray) -> np.ndarray:
    hm = np.asarray(depth_hm, dtype=np.float32)
    if hm.ndim != 2 or hm.size == 0:
        raise ValueError(f"depth_hm must be a non-empty h x w heightmap; got shape {hm.shape}")
    # A NaN would poison the median and the max; an unknown height is treated like an empty pixel (0 m).
    return np.nan_to_num(hm, nan=0.0, posinf=0.0, neginf=0.0)


def stack_height(depth_hm: np.ndarray, cube_size_m: float = 0.05, median_ksize: int = 5) -> int:
    """Number of cubes in the tallest stack: round(max filtered height / cube_size_m), 0 when empty.

    The median filter (median_ksize x median_ksize pixels) removes speckle: a cluster of outliers counts
    only if it covers more than half the kernel, far less than a cube's footprint (25 x 25 px for 5 cm cubes
    at 2 mm/px). There is no upper cap, unlike the authors' code (which reads anything above 0.21 m as 0 and
    so never sees a 5-cube stack); the workspace z_max bounds what the heightmap can hold instead.
    """
    if not cube_size_m > 0:
        raise ValueError(f"cube_size_m must be > 0; got {cube_size_m}")
    return max(0, int(np.rint(float(filtered_heightmap(depth_hm, median_ksize).max()) / cube_size_m)))


def filtered_heightmap(depth_hm: np.ndarray, median_ksize: int = 5) -> np.ndarray:
    """The heightmap stack_height reads: unknown heights as 0 m, speckle removed by a median filter."""
    if median_ksize not in _FLOAT_MEDIAN_KSIZES:
        raise ValueError(f"median_ksize must be one of {_FLOAT_MEDIAN_KSIZES} (cv2 on float32); got {median_ksize}")
    return cv2.medianBlur(_as_heightmap(depth_hm), median_ksize)



def top_face_offset(depth_hm: np.ndarray, row: int, col: int, resolution_m: float, cube_size_m: float,
                    patch_radius_m: float) -> tuple[float, float] | None:
    """(distance from pixel (row, col) to the centre of the top face under it, that face's half-width), in
    metres, read off the heightmap before a place; None when nothing a cube high is under the pixel.

    The top face is the connected region within cube_size_m * 0.4 of the highest point in the place patch
    (the patch of `patch_radius_m` the hand is lowered onto), inside a window of two cube sizes around the
    pixel; its half-width is half the side of a square of its area.
    """
    if not (resolution_m > 0 and cube_size_m > 0 and patch_radius_m >= 0):
        raise ValueError(f"resolution_m, cube_size_m must be > 0 and patch_radius_m >= 0; got {resolution_m}, "
                         f"{cube_size_m}, {patch_radius_m}")
    hm = filtered_heightmap(depth_hm)
    h, w = hm.shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel ({row}, {col}) is outside the {h} x {w} heightmap")
    win = max(1, int(np.ceil(2 * cube_size_m / resolution_m)))
    r0, r1, c0, c1 = max(0, row - win), min(h, row + win + 1), max(0, col - win), min(w, col + win + 1)
    window = hm[r0:r1, c0:c1]
    rows, cols = np.mgrid[r0:r1, c0:c1]
    patch = (rows - row) ** 2 + (cols - col) ** 2 <= (patch_radius_m / resolution_m) ** 2
    top = float(window[patch].max())
    if top < cube_size_m / 2:
        return None
    _, labels = cv2.connectedComponents((window >= top - 0.4 * cube_size_m).astype(np.uint8), connectivity=8)
    peak = np.flatnonzero(patch.ravel() & (window.ravel() == top))[0]
    face = labels == labels.ravel()[peak]
    area_px = int(face.sum())
    distance_px = float(np.hypot(rows[face].mean() - row, cols[face].mean() - col))
    return distance_px * resolution_m, np.sqrt(area_px) * resolution_m / 2


def centring_factor(distance_m: float, half_width_m: float) -> float:
    """1 at a face's centre falling to 0 at its half-width: 1 - (distance / half-width)^2, clipped to [0, 1]."""
    if not (math.isfinite(distance_m) and distance_m >= 0 and math.isfinite(half_width_m) and half_width_m > 0):
        raise ValueError(f"distance_m must be >= 0 and half_width_m > 0; got {distance_m}, {half_width_m}")
    return float(min(1.0, max(0.0, 1.0 - (distance_m / half_width_m) ** 2)))
