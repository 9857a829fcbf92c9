"""Configuration of a real robot actor: the UR arm (ur_rtde), its tool, safety limits, the RealSense camera.

Two frozen sections of the root Config, validated on construction (a bad value raises ConfigError naming
the field, the value and the fix):

[robot]      the arm's address, the safety box every commanded pose is clamped to, speed/acceleration caps,
             the home pose, the tool (suction cup with a vacuum sensor, or a gripper with width feedback)
             and its I/O pins, the primitives' distances, the calibration file, and the bins of the
             bin-picking task (source and destination swap when the source is empty).
[realsense]  which camera (serial number), the stream size and rate, frames dropped after start.

Frames: poses are in the robot base frame, metres, orientation as a rotation vector (UR's convention);
the heightmap workspace ([workspace]) is in the same frame. Simulation-only runs ignore both sections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from .configbase import require

# A UR controller refuses tool speeds above ~1 m/s in normal mode anyway; we cap far lower by default.
_HARD_MAX_SPEED_MPS = 1.0
_HARD_MAX_ACCEL_MPS2 = 5.0


def _finite(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


@dataclass(frozen=True)
class RobotConfig:
    """A UR arm through ur_rtde (`romannet actor --robot ur`), its tool and its safety limits."""

    kind: Literal["ur"] = "ur"
    host: str = ""  # the controller's IP address or host name (required for --robot ur)
    # Safety, enforced in the robot layer: every commanded TCP position is clamped into this box (base frame,
    # metres; z_m[0] is the minimum height), speeds and accelerations are capped.
    limits_x_m: tuple[float, float] = (0.25, 0.75)
    limits_y_m: tuple[float, float] = (-0.4, 0.4)  # wider than the workspace: home is beside it
    limits_z_m: tuple[float, float] = (0.0, 0.45)
    max_speed_mps: float = 0.25
    max_accel_mps2: float = 1.2
    move_speed_mps: float = 0.25  # free-space moves (capped by max_speed_mps)
    contact_speed_mps: float = 0.05  # the last approach_height_m down to a contact, and pushes
    accel_mps2: float = 0.8
    # TCP pose out of the camera's view, where every primitive starts and ends: x y z rx ry rz.
    home_pose: tuple[float, float, float, float, float, float] = (0.5, -0.35, 0.35, math.pi, 0.0, 0.0)
    # Orientation of the tool pointing straight down at primitive angle 0 (rotation vector); the primitive's
    # angle turns it about the base z axis.
    tool_down_rotvec: tuple[float, float, float] = (math.pi, 0.0, 0.0)
    # Primitives (paper: push 10 cm; pick goes below the surface the heightmap shows).
    approach_height_m: float = 0.1  # above the target, then straight down
    push_distance_m: float = 0.1
    push_clearance_m: float = 0.01  # the closed tool this far above the surface it pushes at
    pick_depth_m: float = 0.01  # suction: press this far below the surface; gripper: fingers this far down
    place_clearance_m: float = 0.02  # the held object's bottom this far above the surface before release
    lift_height_m: float = 0.15  # above the workspace floor after a pick
    held_object_height_m: float = 0.05  # stacking: the held cube's height (cube size)
    # Tool: "suction" (vacuum on a digital output, vacuum sensor on a digital input) or "gripper" (close on a
    # digital output, finger width from an analog input).
    tool: Literal["suction", "gripper"] = "suction"
    tool_output: Literal["tool", "standard"] = "tool"  # which digital outputs tool_output_pin numbers
    tool_output_pin: int = 0
    vacuum_input: int = 16  # getDigitalInState index: 0-7 standard, 8-15 configurable, 16-17 tool inputs
    vacuum_settle_s: float = 0.3  # wait after switching the vacuum before reading the sensor
    width_input: Literal["analog0", "analog1"] = "analog0"
    width_per_volt_m: float = 0.01  # finger width = width_per_volt_m * volts + width_offset_m
    width_offset_m: float = 0.0
    grasp_min_width_m: float = 0.004  # closed fingers wider than this hold something
    # Camera-to-robot calibration (`romannet calibrate`): our JSON file or VPG's camera_pose.txt.
    calibration_file: str = ""
    # Bin picking with bin swapping: the x/y of each bin's workspace corner (x_min, y_min); the heightmap
    # size is [workspace]'s. Empty: one workspace ([workspace]), picked objects dropped at drop_xy_m.
    bins_xy_m: tuple[tuple[float, float], ...] = ()
    drop_xy_m: tuple[float, float] = (0.5, -0.3)
    drop_height_m: float = 0.25
    empty_occupied_fraction: float = 0.005  # a bin with less of its area above reward.occupied_height_m is empty
    # Stacking: reset waits this long for the operator to clear the stack (0 = wait forever).
    reset_wait_s: float = 300.0

    def __post_init__(self) -> None:
        for name in ("limits_x_m", "limits_y_m", "limits_z_m"):
            lo, hi = getattr(self, name)
            require(_finite(lo, hi) and lo < hi, f"robot.{name}", (lo, hi),
                    "must be [low, high] metres in the robot base frame with low < high")
        require(_finite(self.max_speed_mps) and 0 < self.max_speed_mps <= _HARD_MAX_SPEED_MPS,
                "robot.max_speed_mps", self.max_speed_mps, f"must be in (0, {_HARD_MAX_SPEED_MPS}] m/s")
        require(_finite(self.max_accel_mps2) and 0 < self.max_accel_mps2 <= _HARD_MAX_ACCEL_MPS2,
                "robot.max_accel_mps2", self.max_accel_mps2, f"must be in (0, {_HARD_MAX_ACCEL_MPS2}] m/s^2")
        for name in ("move_speed_mps", "contact_speed_mps", "accel_mps2"):
            require(_finite(getattr(self, name)) and getattr(self, name) > 0, f"robot.{name}",
                    getattr(self, name), "must be positive (it is capped by max_speed_mps / max_accel_mps2)")
        require(len(self.home_pose) == 6 and _finite(*self.home_pose), "robot.home_pose", self.home_pose,
                "must be 6 finite numbers: x y z (m) rx ry rz (rotation vector)")
        if _finite(*self.home_pose):
            lows, highs = zip(self.limits_x_m, self.limits_y_m, self.limits_z_m, strict=True)
            require(all(lo <= v <= hi for v, lo, hi in zip(self.home_pose[:3], lows, highs, strict=True)),
                    "robot.home_pose", self.home_pose, f"its position must lie inside the safety box "
                    f"(limits_x_m {self.limits_x_m}, limits_y_m {self.limits_y_m}, limits_z_m {self.limits_z_m})")
        require(_finite(*self.tool_down_rotvec), "robot.tool_down_rotvec", self.tool_down_rotvec,
                "must be 3 finite numbers (a rotation vector)")
        for name in ("approach_height_m", "push_distance_m", "lift_height_m", "drop_height_m",
                     "held_object_height_m"):
            value = getattr(self, name)
            require(_finite(value) and 0 < value <= 1.0, f"robot.{name}", value, "must be in (0, 1] metres")
        for name in ("push_clearance_m", "pick_depth_m", "place_clearance_m"):
            value = getattr(self, name)
            require(_finite(value) and 0 <= value <= 0.1, f"robot.{name}", value, "must be in [0, 0.1] metres")
        require(0 <= self.tool_output_pin <= 7, "robot.tool_output_pin", self.tool_output_pin,
                "must be 0..7 (tool outputs are 0-1, standard outputs 0-7)")
        require(self.tool_output == "standard" or self.tool_output_pin <= 1, "robot.tool_output_pin",
                self.tool_output_pin, "tool digital outputs are 0 or 1; set robot.tool_output = \"standard\" "
                "for a standard output")
        require(0 <= self.vacuum_input <= 17, "robot.vacuum_input", self.vacuum_input,
                "must be 0..17 (0-7 standard, 8-15 configurable, 16-17 tool digital inputs)")
        require(_finite(self.vacuum_settle_s) and 0 <= self.vacuum_settle_s <= 5, "robot.vacuum_settle_s",
                self.vacuum_settle_s, "must be in [0, 5] seconds")
        require(_finite(self.width_per_volt_m, self.width_offset_m) and self.width_per_volt_m != 0,
                "robot.width_per_volt_m", self.width_per_volt_m, "must be a non-zero finite number (m per volt)")
        require(_finite(self.grasp_min_width_m) and 0 <= self.grasp_min_width_m < 0.2,
                "robot.grasp_min_width_m", self.grasp_min_width_m, "must be in [0, 0.2) metres")
        for i, xy in enumerate(self.bins_xy_m):
            require(len(xy) == 2 and _finite(*xy), f"robot.bins_xy_m[{i}]", xy, "must be [x_min, y_min] metres")
        require(len(self.bins_xy_m) in (0, 2), "robot.bins_xy_m", self.bins_xy_m,
                "must list no bin (one workspace) or exactly two bins (source and destination swap)")
        require(_finite(*self.drop_xy_m), "robot.drop_xy_m", self.drop_xy_m, "must be 2 finite numbers (m)")
        require(_finite(self.empty_occupied_fraction) and 0 <= self.empty_occupied_fraction < 1,
                "robot.empty_occupied_fraction", self.empty_occupied_fraction, "must be in [0, 1)")
        require(_finite(self.reset_wait_s) and self.reset_wait_s >= 0, "robot.reset_wait_s", self.reset_wait_s,
                "must be >= 0 seconds (0 = wait forever)")

    @property
    def speed_cap(self) -> tuple[float, float]:
        """(free-space speed, contact speed) after the cap, m/s."""
        return min(self.move_speed_mps, self.max_speed_mps), min(self.contact_speed_mps, self.max_speed_mps)


@dataclass(frozen=True)
class RealSenseConfig:
    """An Intel RealSense camera through pyrealsense2 (`romannet actor --camera realsense`)."""

    serial: str = ""  # "" = the only connected camera (an error if there are several)
    width_px: int = 640
    height_px: int = 480
    fps: int = 30
    warmup_frames: int = 30  # dropped after start, while auto-exposure settles
    timeout_s: float = 5.0  # one frame set

    def __post_init__(self) -> None:
        require(self.serial == "" or self.serial.isalnum(), "realsense.serial", self.serial,
                "must be the camera's serial number (letters and digits) or \"\" for the only camera")
        require((self.width_px, self.height_px) in ((640, 480), (848, 480), (1280, 720), (424, 240)),
                "realsense.width_px", (self.width_px, self.height_px),
                "width x height must be a RealSense D4xx mode: 640x480, 848x480, 1280x720 or 424x240")
        require(self.fps in (6, 15, 30, 60), "realsense.fps", self.fps, "must be 6, 15, 30 or 60")
        require(0 <= self.warmup_frames <= 300, "realsense.warmup_frames", self.warmup_frames, "must be 0..300")
        require(_finite(self.timeout_s) and 0 < self.timeout_s <= 60, "realsense.timeout_s", self.timeout_s,
                "must be in (0, 60] seconds")
