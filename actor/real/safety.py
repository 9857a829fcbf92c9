"""Safety limits of a real arm, as small pure functions: the robot layer applies them to every command.

The policy never sees these limits: whatever pixel it picks, the robot layer clamps the commanded TCP
position into the configured box (x, y, and z between the minimum and maximum height) and caps speed and
acceleration. Orientation is not clamped: primitives only ever command the top-down tool orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from romannet.common.config_robot import RobotConfig


@dataclass(frozen=True)
class SafetyBox:
    """The box every commanded TCP position must lie in (robot base frame, metres), and the motion caps."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]
    max_speed_mps: float
    max_accel_mps2: float

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> SafetyBox:
        return cls((cfg.limits_x_m[0], cfg.limits_y_m[0], cfg.limits_z_m[0]),
                   (cfg.limits_x_m[1], cfg.limits_y_m[1], cfg.limits_z_m[1]),
                   cfg.max_speed_mps, cfg.max_accel_mps2)


def clamp_pose(pose: np.ndarray | list[float], box: SafetyBox) -> tuple[np.ndarray, bool]:
    """The pose (x y z rx ry rz) with its position clamped into the box; True if anything moved.

    A non-finite pose is refused (ValueError): clamping NaN would pass NaN to the controller.
    """
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a TCP pose must be 6 finite numbers (x y z rx ry rz); got {p.tolist()}")
    out = p.copy()
    out[:3] = np.clip(p[:3], box.low, box.high)
    return out, bool(np.any(out[:3] != p[:3]))


def cap_motion(speed_mps: float, accel_mps2: float, box: SafetyBox) -> tuple[float, float]:
    """Speed and acceleration capped to the box's limits (and refused if not positive and finite)."""
    if not (np.isfinite(speed_mps) and speed_mps > 0 and np.isfinite(accel_mps2) and accel_mps2 > 0):
        raise ValueError(f"speed and acceleration must be positive and finite; got {speed_mps}, {accel_mps2}")
    return min(speed_mps, box.max_speed_mps), min(accel_mps2, box.max_accel_mps2)


def inside(position: np.ndarray | list[float], box: SafetyBox, tol_m: float = 1e-9) -> bool:
    """Is the position inside the box (within tol_m)?"""
    q = np.asarray(position, dtype=np.float64)[:3]
    return bool(np.all(q >= np.asarray(box.low) - tol_m) and np.all(q <= np.asarray(box.high) + tol_m))
