"""Task Progress based Gaussian (TPG) reward, as pure functions (paper Sec. "Task Progress based Gaussian Reward").

    R_tp  = W(phi) * X * P            X: primitive succeeded (bool, judged by the sim/robot)
                                      P: overall task progress in [0, 1], measured on the depth heightmap
                                         (common.episode_rules: clutter_progress, stacking_progress)
    R_tpg = max(R_tp, R_tp (*) G)     G: anisotropic Gaussian, sigma_x / sigma_y = 2, x along the gripper

Frames and the angle convention (the same as `common.action`): a heightmap is indexed [row, col]; the column
axis is the robot's x, the row axis the robot's y, and an angle theta is measured from the column axis toward
the row axis. The *gripper's x axis* at theta is the unit vector (d_col, d_row) = (cos theta, sin theta):
for a push it is the push direction, for pick/place the finger-closing axis. This is the direction the sim
executes for `Action.angle_rad` and the direction the learner's rotation label (cos/sin of theta for push,
of 2 theta for pick/place) encodes. The Gaussian is point symmetric, so theta and theta + pi give the same
kernel: pick/place's 180-degree symmetry and the learner's "opposite orientation" label agree with it.

The reward only depends on a depth heightmap and the sim/robot's success flag, so it works on a real robot.
"""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np

from .config import PRIMITIVES, RewardConfig

logger = logging.getLogger(__name__)

Normalization = Literal["peak", "paper"]


# ---------------------------------------------------------------------------------------------- R_tp
def progress_reversed(p_before: float, p_after: float, tolerance: float) -> bool:
    """True when progress dropped by more than `tolerance` (RewardConfig.progress_tolerance): reward 0.

    The tolerance absorbs depth noise (a real camera's heightmap flickers by a few occupied pixels).
    """
    if not (math.isfinite(p_before) and math.isfinite(p_after)):
        raise ValueError(f"progress must be finite, got before={p_before!r}, after={p_after!r}")
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance = {tolerance!r} must be >= 0")
    return p_after < p_before - tolerance


def task_progress_reward(primitive: str, X: bool, P: float, cfg: RewardConfig, reversed: bool = False) -> float:
    """R_tp = W(primitive) * X * P (cfg.use_progress False: W * X); 0 if the action reversed progress.

    Args:
        primitive: "push" | "pick" | "place" (selects W: cfg.push_weight, pick_weight, place_weight).
        X: sub-task indicator from the sim/robot (push moved an object, pick lifted one, place raised the stack).
        P: task progress in [0, 1] after the action (common.episode_rules.task_progress).
        reversed: progress_reversed(P_before, P_after, cfg.progress_tolerance).
    """
    if primitive not in PRIMITIVES:
        raise ValueError(f"primitive = {primitive!r} must be one of {PRIMITIVES}")
    if not (math.isfinite(P) and 0.0 <= P <= 1.0):
        raise ValueError(f"task progress P = {P!r} must be in [0, 1]")
    if reversed or not X:
        return 0.0
    weight = cfg.weight(primitive)
    return float(weight * P) if cfg.use_progress else float(weight)


# ------------------------------------------------------------------------------------ Gaussian smoothing
def _mahalanobis_sq(sigma_x_px: float, sigma_y_px: float, angle_rad: float, half_px: int) -> np.ndarray:
    """(u/sigma_x)^2 + (v/sigma_y)^2 on a (2 half + 1)^2 pixel grid centred on the middle pixel.

    u is the offset along the gripper x axis (cos theta, sin theta) in (col, row), v the offset across it.
    """
    offsets = np.arange(-half_px, half_px + 1, dtype=np.float64)
    d_row, d_col = offsets[:, None], offsets[None, :]
    cos_t, sin_t = math.cos(angle_rad), math.sin(angle_rad)
    u = d_col * cos_t + d_row * sin_t
    v = -d_col * sin_t + d_row * cos_t
    return (u / sigma_x_px) ** 2 + (v / sigma_y_px) ** 2


def _check_kernel_args(sigma_x_px: float, sigma_y_px: float, angle_rad: float, radius_sigmas: float) -> int:
    """Validate the kernel parameters; return the half-size in pixels of the square that holds the support."""
    for name, value in (("sigma_x_px", sigma_x_px), ("sigma_y_px", sigma_y_px), ("radius_sigmas", radius_sigmas)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r} must be a positive finite number")
    if not math.isfinite(angle_rad):
        raise ValueError(f"angle_rad = {angle_rad!r} must be finite")
    return int(math.ceil(radius_sigmas * max(sigma_x_px, sigma_y_px)))


def kernel_support(sigma_x_px: float, sigma_y_px: float, angle_rad: float, radius_sigmas: float) -> np.ndarray:
    """Boolean (2R+1)^2 mask of the kernel's support: the ellipse of Mahalanobis radius `radius_sigmas`.

    Semi-axes radius_sigmas * sigma_x (along the gripper) and radius_sigmas * sigma_y (across); R =
    ceil(radius_sigmas * max(sigma_x, sigma_y)). Computed from geometry, not from kernel > 0, so it is the same
    whatever the reward value (a failed action still has a support: its label is 0 there).
    """
    half = _check_kernel_args(sigma_x_px, sigma_y_px, angle_rad, radius_sigmas)
    return _mahalanobis_sq(sigma_x_px, sigma_y_px, angle_rad, half) <= radius_sigmas**2


def gaussian_kernel(sigma_x_px: float, sigma_y_px: float, angle_rad: float,
                    normalization: Normalization = "peak", radius_sigmas: float = 3.0) -> np.ndarray:
    """Anisotropic Gaussian G on a (2R+1)^2 pixel grid (float64), centre pixel in the middle, 0 off the support.

    Args:
        sigma_x_px: standard deviation along the gripper's x axis (push direction / finger-closing axis), px.
        sigma_y_px: standard deviation across it, px.
        angle_rad: gripper yaw theta (from the column axis toward the row axis; see the module docstring).
        normalization: "peak" -> G(0, 0) = 1; "paper" -> the paper's 1 / (2 pi sigma_x sigma_y) (unit integral).
        radius_sigmas: the support is the ellipse of this Mahalanobis radius (see kernel_support).
    """
    half = _check_kernel_args(sigma_x_px, sigma_y_px, angle_rad, radius_sigmas)
    if normalization == "peak":
        scale = 1.0
    elif normalization == "paper":
        scale = 1.0 / (2.0 * math.pi * sigma_x_px * sigma_y_px)
    else:
        raise ValueError(f"normalization = {normalization!r} must be 'peak' or 'paper'")
    d2 = _mahalanobis_sq(sigma_x_px, sigma_y_px, angle_rad, half)
    return np.where(d2 <= radius_sigmas**2, scale * np.exp(-0.5 * d2), 0.0)


def tpg_label(shape: tuple[int, int], row: int, col: int, angle_rad: float, r_tp: float,
              cfg: RewardConfig) -> tuple[np.ndarray, np.ndarray]:
    """The learner's label for one executed action: (reward_map float32 (h, w), support_mask bool (h, w)).

    reward_map = max(R_tp at the executed pixel, R_tp (*) G) = R_tpg; support_mask is where the label is defined
    (the kernel's support, clipped at the image border), which is where the Huber loss runs. With r_tp = 0 (a
    failed or reversing action) the map is all zeros but the support is unchanged: the net learns 0 around the
    pixel. With cfg.use_gaussian False (the R_tp ablation) map and support are the single executed pixel, and so
    they are for r_tp = 0 with cfg.zero_reward_support = "pixel".

    Normalization (cfg.kernel_normalization): the default "peak" (G(0) = 1) gives neighbours almost the executed
    pixel's reward, the paper's stated intuition ("action poses in the local neighbourhood should yield similar
    reward"). The paper's literal 1 / (2 pi sigma_x sigma_y) is 1/(2 pi * 4 * 2) ~ 0.02 at the default sigmas,
    so max(R_tp, R_tp (*) G) is R_tp at the pixel and <= 2 % of it elsewhere: practically the un-smoothed R_tp,
    which would make the R_tp-vs-R_tpg ablation compare two nearly identical rewards. "paper" stays selectable.

    Args:
        shape: (h, w) of the Q map, pixels.
        row, col: executed pixel.
        angle_rad: executed gripper yaw (Action.angle_rad).
        r_tp: task_progress_reward(...) >= 0.
    """
    h, w = shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"executed pixel ({row}, {col}) is outside the {h}x{w} map")
    if not (math.isfinite(r_tp) and r_tp >= 0):
        raise ValueError(f"r_tp = {r_tp!r} must be a finite reward >= 0 (R_tp = W X P)")
    reward_map = np.zeros((h, w), dtype=np.float32)
    support = np.zeros((h, w), dtype=bool)
    if not cfg.use_gaussian or (r_tp == 0.0 and cfg.zero_reward_support == "pixel"):
        reward_map[row, col] = r_tp
        support[row, col] = True
        return reward_map, support

    sigma_x = cfg.sigma_x_px
    kernel = gaussian_kernel(sigma_x, cfg.sigma_y_px, angle_rad, cfg.kernel_normalization, cfg.kernel_radius_sigmas)
    kernel_mask = kernel_support(sigma_x, cfg.sigma_y_px, angle_rad, cfg.kernel_radius_sigmas)
    half = kernel.shape[0] // 2
    # Clip the kernel's window to the image: rows r0:r1 of the map take kernel rows k_r0:k_r1.
    r0, r1 = max(row - half, 0), min(row + half + 1, h)
    c0, c1 = max(col - half, 0), min(col + half + 1, w)
    k_r0, k_c0 = r0 - (row - half), c0 - (col - half)
    window = (slice(k_r0, k_r0 + (r1 - r0)), slice(k_c0, k_c0 + (c1 - c0)))
    # R_tp is one pixel, so R_tp (*) G is G shifted to that pixel and scaled (G is point symmetric: no flip).
    reward_map[r0:r1, c0:c1] = r_tp * kernel[window]
    support[r0:r1, c0:c1] = kernel_mask[window]
    reward_map[row, col] = max(float(reward_map[row, col]), r_tp)  # the max(R_tp, R_g) of the paper
    return reward_map, support
