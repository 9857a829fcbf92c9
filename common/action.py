"""The action a policy chooses, and the pixel <-> robot-frame conversion (VPG's convention).

Image frame: row r, column c of a heightmap. Robot frame: x = c*res + x_min, y = r*res + y_min,
z = depth_hm[r, c] + z_min. Because columns map to x and rows to y with the same orientation, an angle
in the image frame (from the column axis toward the row axis) equals the gripper's yaw in the robot frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import PRIMITIVES, WorkspaceConfig
from .stack import top_face_centre


@dataclass(frozen=True)
class Action:
    """One chosen manipulation action: primitive type and pixel-wise pose (x, y, theta, Q)."""

    primitive: str  # "push" | "pick" | "place"
    row: int
    col: int
    angle_rad: float  # gripper yaw; push: direction of the push; pick/place: finger-closing axis
    q_value: float
    explored: bool = False

    def __post_init__(self) -> None:
        if self.primitive not in PRIMITIVES:
            raise ValueError(f"Action.primitive = {self.primitive!r} is invalid: must be one of {PRIMITIVES}")
        if not math.isfinite(self.angle_rad):
            raise ValueError(f"Action.angle_rad = {self.angle_rad!r} is invalid: must be finite")


def pixel_to_position(row: int, col: int, depth_hm: np.ndarray, ws: WorkspaceConfig) -> tuple[float, float, float]:
    """Robot-frame (x, y, z) in metres of heightmap pixel (row, col), z read from the depth heightmap."""
    h, w = depth_hm.shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel ({row}, {col}) is outside the {h}x{w} heightmap")
    x = col * ws.resolution_m + ws.x_min_m
    y = row * ws.resolution_m + ws.y_min_m
    z = float(depth_hm[row, col]) + ws.z_min_m
    return x, y, z


def position_to_pixel(x_m: float, y_m: float, ws: WorkspaceConfig) -> tuple[int, int]:
    """Heightmap (row, col) of a robot-frame position; raises ValueError outside the workspace."""
    # Floor, as the heightmap binning does: a pixel covers [x_min + col*res, x_min + (col+1)*res).
    # The epsilon keeps pixel -> position -> pixel exact despite floating-point division.
    col = math.floor((x_m - ws.x_min_m) / ws.resolution_m + 1e-9)
    row = math.floor((y_m - ws.y_min_m) / ws.resolution_m + 1e-9)
    if not (0 <= row < ws.height_px and 0 <= col < ws.width_px):
        raise ValueError(f"position ({x_m:.4f}, {y_m:.4f}) m is outside the workspace")
    return row, col


# Where every environment (the simulator, a real robot) starts a push and lowers a held object: above the
# highest point within these radii of the action's pixel.
PUSH_PATCH_RADIUS_M = 0.012  # the closed fingers' footprint
PLACE_PATCH_RADIUS_M = 0.015  # the held object's footprint, roughly


def patch_max(depth_hm: np.ndarray, row: int, col: int, radius_m: float, resolution_m: float) -> float:
    """Highest depth_hm value (m above the floor) within radius_m of pixel (row, col): where a push starts
    above, or a held object is lowered onto."""
    r = max(1, round(radius_m / resolution_m))
    return float(depth_hm[max(0, row - r):row + r + 1, max(0, col - r):col + r + 1].max())


def place_position(depth_hm: np.ndarray, row: int, col: int, ws: WorkspaceConfig, cube_size_m: float,
                   on_top_centre: bool) -> tuple[float, float]:
    """Robot-frame (x, y) in metres a held object is placed at for a place at pixel (row, col): the pixel's, or
    with `on_top_centre` the centre of the top face under it (common.stack.top_face_centre) where there is one."""
    x, y, _ = pixel_to_position(row, col, depth_hm, ws)
    if not on_top_centre:
        return x, y
    centre = top_face_centre(depth_hm, row, col, ws.resolution_m, cube_size_m, PLACE_PATCH_RADIUS_M)
    if centre is None:
        return x, y
    # A face's pixels cover [x_min + col * res, x_min + (col + 1) * res): their centres lie half a pixel in.
    return (centre[1] + 0.5) * ws.resolution_m + ws.x_min_m, (centre[0] + 0.5) * ws.resolution_m + ws.y_min_m
