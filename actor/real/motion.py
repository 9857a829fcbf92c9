"""The paper's primitives as lists of Cartesian TCP waypoints (pure functions; the robot layer runs them).

Poses are UR-style (x y z rx ry rz): robot base frame, metres, rotation vector. Heights are of the TCP,
which the controller must have set to the suction cup's tip or the fingertips' centre. The tool points
straight down (`tool_down_rotvec`) turned about the base z axis by the primitive's angle; a two-finger
gripper and a suction cup are symmetric under a half turn, so the angle is folded into (-pi/2, pi/2] to
keep the wrist away from its joint limits (the push direction itself is not folded).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from romannet.common.config_robot import RobotConfig


@dataclass(frozen=True)
class Waypoint:
    """One linear move: the target pose and whether it is a contact move (slow) or free space (fast)."""

    pose: tuple[float, float, float, float, float, float]
    contact: bool = False


def fold_angle(angle_rad: float) -> float:
    """angle_rad folded into (-pi/2, pi/2] (a symmetric tool looks the same after a half turn)."""
    a = math.remainder(angle_rad, math.pi)  # in [-pi/2, pi/2]
    return math.pi / 2 if a <= -math.pi / 2 else a


def tool_rotvec(angle_rad: float, tool_down_rotvec: tuple[float, float, float]) -> tuple[float, float, float]:
    """Rotation vector of the tool pointing down, turned by angle_rad about the base z axis."""
    r_down, _ = cv2.Rodrigues(np.asarray(tool_down_rotvec, dtype=np.float64).reshape(3, 1))
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    r_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    rv, _ = cv2.Rodrigues(r_z @ r_down)
    return float(rv[0, 0]), float(rv[1, 0]), float(rv[2, 0])


def _pose(x: float, y: float, z: float, rv: tuple[float, float, float]):
    return (float(x), float(y), float(z), *rv)


def push_plan(x: float, y: float, z: float, angle_rad: float, cfg: RobotConfig) -> list[Waypoint]:
    """Above the start, down to z (the tool's height for the push), push_distance_m along angle_rad, up."""
    rv = tool_rotvec(fold_angle(angle_rad), cfg.tool_down_rotvec)
    ex = x + cfg.push_distance_m * math.cos(angle_rad)
    ey = y + cfg.push_distance_m * math.sin(angle_rad)
    return [Waypoint(_pose(x, y, z + cfg.approach_height_m, rv)), Waypoint(_pose(x, y, z, rv), True),
            Waypoint(_pose(ex, ey, z, rv), True), Waypoint(_pose(ex, ey, z + cfg.approach_height_m, rv))]


def descend_plan(x: float, y: float, z: float, angle_rad: float, cfg: RobotConfig) -> list[Waypoint]:
    """Above (x, y), then slowly straight down to z (pick and place both start this way)."""
    rv = tool_rotvec(fold_angle(angle_rad), cfg.tool_down_rotvec)
    return [Waypoint(_pose(x, y, z + cfg.approach_height_m, rv)), Waypoint(_pose(x, y, z, rv), True)]


def lift_plan(x: float, y: float, z_to: float, angle_rad: float, cfg: RobotConfig) -> list[Waypoint]:
    """Straight up to z_to (slowly: the tool may hold an object or still touch one)."""
    rv = tool_rotvec(fold_angle(angle_rad), cfg.tool_down_rotvec)
    return [Waypoint(_pose(x, y, z_to, rv), True)]


def pick_tool_z(surface_z_m: float, cfg: RobotConfig) -> float:
    """TCP height of a pick at a surface point: pick_depth_m below it (a suction cup's compliance, or the
    fingers reaching around the object)."""
    return surface_z_m - cfg.pick_depth_m


def place_tool_z(surface_z_m: float, cfg: RobotConfig) -> float:
    """TCP height at release: the held object's bottom place_clearance_m above the surface under it."""
    return surface_z_m + cfg.held_object_height_m + cfg.place_clearance_m
