"""Configuration of camera-to-robot calibration (`romannet calibrate`): the grid of poses and the checkerboard.

One frozen dataclass, the `[calibration]` section of the root Config, validated on construction (a bad value
raises ConfigError naming the field, the value and the fix).

The procedure (actor/real/calibrate.py) moves the TCP, holding `tool_rotvec`, over a grid of positions;
a checkerboard fixed to the tool is seen by the camera at each. Frames: grid positions and `tool_rotvec` are
in the robot base frame (metres, UR rotation vector), `board_offset_m` is the board centre in the TCP frame.
The board's plane is the TCP x-y plane through that centre; the pattern's columns run along TCP x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .configbase import require

_MAX_GRID_COUNT = 20  # per axis: 20^3 poses is already hours of robot time


def _finite(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


@dataclass(frozen=True)
class CalibrationConfig:
    """Camera-to-robot calibration with a checkerboard on the tool (`romannet calibrate`)."""

    # Grid of TCP positions, base frame: (start, stop, count) per axis, start..stop inclusive (np.linspace).
    # The default 3x3x3 = 27 poses sits inside robot.limits_* and the default camera's view of the workspace.
    grid_x_m: tuple[float, float, int] = (0.42, 0.58, 3)
    grid_y_m: tuple[float, float, int] = (-0.08, 0.08, 3)
    grid_z_m: tuple[float, float, int] = (0.08, 0.24, 3)
    # Tool orientation held at every pose (rotation vector, base frame) so the board faces the camera; the
    # default points the tool straight down, which a camera above the table sees at a slant.
    tool_rotvec: tuple[float, float, float] = (math.pi, 0.0, 0.0)
    # The board centre (the middle of the pattern's inner corners) in the TCP frame, metres. Measure it on
    # your mount: an error here shifts the fitted camera position by the same amount (the tool orientation
    # is constant, so the fit cannot see it).
    board_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # The checkerboard: inner corners (columns along TCP x, rows along TCP y) and the square's side.
    pattern_corners: tuple[int, int] = (5, 4)
    square_m: float = 0.02
    min_valid_depth_px: int = 200  # depth readings on the board needed to accept a pose
    min_poses: int = 10  # poses with a detected board and depth needed for a fit
    max_rms_error_m: float = 0.005  # above this RMS residual `romannet calibrate` warns and exits 2
    settle_s: float = 0.5  # wait after each move before capturing, so the frame is not from the motion

    def __post_init__(self) -> None:
        for name in ("grid_x_m", "grid_y_m", "grid_z_m"):
            value = getattr(self, name)
            ok = (len(value) == 3 and _finite(value[0], value[1]) and value[0] <= value[1]
                  and isinstance(value[2], int) and 1 <= value[2] <= _MAX_GRID_COUNT)
            require(ok, f"calibration.{name}", value,
                    f"must be [start, stop, count] with start <= stop (metres, base frame) and count in "
                    f"1..{_MAX_GRID_COUNT}")
        require(len(self.tool_rotvec) == 3 and _finite(*self.tool_rotvec), "calibration.tool_rotvec",
                self.tool_rotvec, "must be 3 finite numbers (a rotation vector, base frame)")
        require(len(self.board_offset_m) == 3 and _finite(*self.board_offset_m)
                and math.hypot(*self.board_offset_m) <= 0.5, "calibration.board_offset_m", self.board_offset_m,
                "must be 3 finite numbers (metres, TCP frame) within 0.5 m of the TCP")
        require(len(self.pattern_corners) == 2 and all(isinstance(c, int) and 3 <= c <= 30
                                                       for c in self.pattern_corners),
                "calibration.pattern_corners", self.pattern_corners,
                "must be [columns, rows] of inner corners, each 3..30 (OpenCV needs more than 2)")
        require(_finite(self.square_m) and 0.002 <= self.square_m <= 0.2, "calibration.square_m", self.square_m,
                "must be the square's side in metres, in [0.002, 0.2]")
        require(isinstance(self.min_valid_depth_px, int) and self.min_valid_depth_px >= 10,
                "calibration.min_valid_depth_px", self.min_valid_depth_px, "must be an integer >= 10")
        require(isinstance(self.min_poses, int) and 4 <= self.min_poses <= 10000, "calibration.min_poses",
                self.min_poses, "must be 4..10000 (a similarity fit needs at least 3 poses not on a line)")
        require(self.pose_count >= self.min_poses, "calibration.grid_x_m", self.pose_count,
                f"the grid has {self.pose_count} poses, fewer than calibration.min_poses = {self.min_poses}; "
                "raise the counts of grid_x_m / grid_y_m / grid_z_m or lower min_poses")
        require(_finite(self.max_rms_error_m) and 0 < self.max_rms_error_m <= 0.1, "calibration.max_rms_error_m",
                self.max_rms_error_m, "must be in (0, 0.1] metres")
        require(_finite(self.settle_s) and 0 <= self.settle_s <= 10, "calibration.settle_s", self.settle_s,
                "must be in [0, 10] seconds")

    @property
    def pose_count(self) -> int:
        """How many poses the grid has."""
        return self.grid_x_m[2] * self.grid_y_m[2] * self.grid_z_m[2]
