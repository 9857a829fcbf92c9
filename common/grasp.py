"""Where along its closing axis a pick closes: the middle of the object under the chosen pixel, read off the
depth heightmap (the same on a simulated and a real robot)."""

from __future__ import annotations

import math

import numpy as np

from .stack import filtered_heightmap

# A pixel lower than this above the table is floor: a pick aimed there is left where it was aimed.
OBJECT_MIN_HEIGHT_M = 0.01
# The longest run of object along the closing axis worth centring on: a 5 cm block's diagonal (7.1 cm) fits,
# two blocks side by side do not, and the fingers need room either side within the hand's opening.
PICK_CENTRE_MAX_SPAN_M = 0.08


def closing_axis_run(depth_hm: np.ndarray, row: int, col: int, angle_rad: float, resolution_m: float,
                     max_span_m: float = PICK_CENTRE_MAX_SPAN_M) -> tuple[float, float] | None:
    """(near, far): signed distances in metres along the closing axis (angle_rad from the column axis toward
    the row axis) from pixel (row, col) to the outer edges of the object run under it, near <= 0 <= far;
    None where there is nothing to grasp across.

    The run is the contiguous line of pixels through (row, col), along the closing axis, at least half as high
    as the pixel itself (and above OBJECT_MIN_HEIGHT_M); each pixel covers resolution_m. None when the pixel is
    floor, or the run is longer than max_span_m or reaches the heightmap's edge (objects that touch, or one too
    long to grasp across).
    """
    if not (resolution_m > 0 and max_span_m > 0 and math.isfinite(angle_rad)):
        raise ValueError(f"resolution_m and max_span_m must be > 0 and angle_rad finite; got {resolution_m}, "
                         f"{max_span_m}, {angle_rad}")
    hm = filtered_heightmap(depth_hm)
    h, w = hm.shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel ({row}, {col}) is outside the {h} x {w} heightmap")
    here = float(hm[row, col])
    if here < OBJECT_MIN_HEIGHT_M:
        return None
    threshold = max(OBJECT_MIN_HEIGHT_M, here / 2)
    reach = int(math.ceil(max_span_m / resolution_m))
    dr, dc = math.sin(angle_rad), math.cos(angle_rad)

    def run_end(sign: int) -> int | None:
        """Last step t (pixels) from the pixel in direction sign still on the object; None past reach/edge."""
        for t in range(1, reach + 1):
            r, c = round(row + sign * t * dr), round(col + sign * t * dc)
            if not (0 <= r < h and 0 <= c < w):
                return None
            if hm[r, c] < threshold:
                return t - 1
        return None

    ahead, behind = run_end(1), run_end(-1)
    if ahead is None or behind is None or (ahead + behind + 1) * resolution_m > max_span_m:
        return None
    return -(behind + 0.5) * resolution_m, (ahead + 0.5) * resolution_m


def closing_axis_offset(depth_hm: np.ndarray, row: int, col: int, angle_rad: float, resolution_m: float,
                        max_span_m: float = PICK_CENTRE_MAX_SPAN_M) -> float | None:
    """Signed distance in metres along the closing axis from pixel (row, col) to the middle of the object run
    under it (closing_axis_run); None where there is nothing to centre on."""
    run = closing_axis_run(depth_hm, row, col, angle_rad, resolution_m, max_span_m)
    return None if run is None else (run[0] + run[1]) / 2
