"""The stack height read off a depth heightmap (stacking; the rules that use it are common.episode_rules).

It takes `depth_hm`, float32 h x w in metres above the workspace floor (common.heightmap.get_heightmaps).
"""

from __future__ import annotations

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


def top_face_centre(depth_hm: np.ndarray, row: int, col: int, resolution_m: float, cube_size_m: float,
                    patch_radius_m: float) -> tuple[float, float] | None:
    """(row, col), in fractional pixels, of the centre of the top face a held cube lowered at pixel (row, col)
    comes to rest on; None when there is no single cube-sized face there (the floor, or tops that touch).

    The hand is lowered onto the highest point within `patch_radius_m` of the pixel (common.action.patch_max);
    the top face is the 8-connected region within 0.4 cube sizes of that height (above or below) around it, in a
    window of two cube sizes. Its centroid is the face's centre when the face is one cube's top: a region larger than
    1.6 cube faces (neighbouring tops at the same height) or under half of one (an edge seen at a slant) is no
    face to centre on.
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
    patch = (rows - row) ** 2 + (cols - col) ** 2 <= max(1.0, patch_radius_m / resolution_m) ** 2
    top = float(window[patch].max())
    if top < cube_size_m / 2:
        return None
    near_top = (np.abs(window - top) <= 0.4 * cube_size_m).astype(np.uint8)
    _, labels = cv2.connectedComponents(near_top, connectivity=8)
    peak = np.flatnonzero(patch.ravel() & (window.ravel() == top))[0]
    face = labels == labels.ravel()[peak]
    area_faces = float(face.sum()) * resolution_m ** 2 / cube_size_m ** 2
    if not 0.5 <= area_faces <= 1.6:
        return None
    return float(rows[face].mean()), float(cols[face].mean())
