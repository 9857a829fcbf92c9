"""TPG reward: task progress, R_tp, the anisotropic Gaussian and the learner's label (map + support)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from romannet.common.config import RewardConfig
from romannet.common.errors import ConfigError
from romannet.common.reward import (
    gaussian_kernel,
    kernel_support,
    progress_reversed,
    task_progress_reward,
    tpg_label,
)

CFG = RewardConfig()
SHAPE = (224, 224)


def weighted_covariance(weights: np.ndarray) -> np.ndarray:
    """2x2 covariance of pixel offsets (d_col, d_row) weighted by `weights`, about the weighted mean."""
    rows, cols = np.indices(weights.shape, dtype=np.float64)
    total = weights.sum()
    mc, mr = (weights * cols).sum() / total, (weights * rows).sum() / total
    dc, dr = cols - mc, rows - mr
    return np.array([[(weights * dc * dc).sum(), (weights * dc * dr).sum()],
                     [(weights * dc * dr).sum(), (weights * dr * dr).sum()]]) / total


# ------------------------------------------------------------------------------------ progress
def test_progress_reversal_uses_the_tolerance():
    assert progress_reversed(0.5, 0.4, 0.02)
    assert not progress_reversed(0.5, 0.49, 0.02)  # depth noise
    assert not progress_reversed(0.5, 0.7, 0.02)


# ------------------------------------------------------------------------------------ R_tp
def test_default_weights_are_the_papers():
    assert (CFG.weight("push"), CFG.weight("pick"), CFG.weight("place")) == (0.2, 1.0, 1.0)
    assert task_progress_reward("push", True, 1.0, CFG, False) == pytest.approx(0.2)
    assert task_progress_reward("pick", True, 0.5, CFG, False) == pytest.approx(0.5)
    assert task_progress_reward("place", True, 0.75, CFG, False) == pytest.approx(0.75)


def test_failure_or_reversal_gives_zero_reward():
    assert task_progress_reward("pick", False, 0.9, CFG, False) == 0.0
    assert task_progress_reward("pick", True, 0.9, CFG, True) == 0.0
    assert task_progress_reward("place", True, 0.9, CFG, reversed=True) == 0.0


def test_without_progress_the_reward_is_w_times_x():
    cfg = replace(CFG, use_progress=False)
    assert task_progress_reward("push", True, 0.1, cfg, False) == pytest.approx(0.2)
    assert task_progress_reward("pick", True, 0.1, cfg, False) == 1.0


def test_task_progress_reward_rejects_bad_input():
    with pytest.raises(ValueError, match="primitive"):
        task_progress_reward("poke", True, 0.5, CFG, False)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        task_progress_reward("pick", True, 1.5, CFG, False)


# ------------------------------------------------------------------------------------ the Gaussian
@pytest.mark.parametrize("angle", [0.0, 0.3, 1.0, -2.2])
def test_kernel_rotates_by_quarter_turns_like_rot90(angle):
    k0 = gaussian_kernel(4.0, 2.0, angle)
    k90 = gaussian_kernel(4.0, 2.0, angle + math.pi / 2)
    np.testing.assert_allclose(np.rot90(k0), k90, atol=1e-12)
    np.testing.assert_allclose(gaussian_kernel(4.0, 2.0, angle + math.pi), k0, atol=1e-12)  # point symmetric


def test_kernel_axis_convention_and_anisotropy_from_second_moments():
    # theta from the column axis toward the row axis: the long axis is (d_col, d_row) = (cos, sin).
    theta = math.radians(30)
    kernel = gaussian_kernel(4.0, 2.0, theta, radius_sigmas=6.0)  # wide support: moments ~ untruncated
    eigvals, eigvecs = np.linalg.eigh(weighted_covariance(kernel))
    assert eigvals[1] / eigvals[0] == pytest.approx(4.0, rel=0.02)  # (sigma_x / sigma_y)^2
    assert eigvals[1] == pytest.approx(16.0, rel=0.02) and eigvals[0] == pytest.approx(4.0, rel=0.03)
    major = eigvecs[:, 1] * np.sign(eigvecs[0, 1])
    np.testing.assert_allclose(major, [math.cos(theta), math.sin(theta)], atol=1e-3)
    half = kernel.shape[0] // 2
    assert kernel[half, half + 4] > kernel[half + 4, half]  # at theta=30 deg the column axis is nearer x


def test_kernel_support_is_the_ellipse_and_zero_outside():
    kernel = gaussian_kernel(4.0, 2.0, 0.0, radius_sigmas=3.0)
    support = kernel_support(4.0, 2.0, 0.0, 3.0)
    assert kernel.shape == support.shape == (25, 25)
    assert np.all(kernel[~support] == 0) and np.all(kernel[support] > 0)
    assert support[12, 0] and support[12, 24]  # 12 px = 3 sigma_x along the column axis
    assert support[6, 12] and not support[5, 12]  # 6 px = 3 sigma_y along the row axis


def test_paper_normalization_integrates_to_one_and_peak_normalization_peaks_at_one():
    peak = gaussian_kernel(4.0, 2.0, 0.7, "peak", radius_sigmas=6.0)
    paper = gaussian_kernel(4.0, 2.0, 0.7, "paper", radius_sigmas=6.0)
    assert peak.max() == 1.0
    assert paper.sum() == pytest.approx(1.0, rel=1e-3)
    assert paper.max() == pytest.approx(1.0 / (2 * math.pi * 8.0))
    with pytest.raises(ValueError, match="normalization"):
        gaussian_kernel(4.0, 2.0, 0.0, "unit")  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ the label
@given(row=st.integers(0, 223), col=st.integers(0, 223), angle=st.floats(-4.0, 4.0),
       r_tp=st.floats(0.01, 1.0), normalization=st.sampled_from(["peak", "paper"]))
def test_label_peaks_at_the_executed_pixel_with_r_tp_and_is_zero_off_support(row, col, angle, r_tp, normalization):
    cfg = replace(CFG, kernel_normalization=normalization)
    reward, support = tpg_label(SHAPE, row, col, angle, r_tp, cfg)
    assert reward.dtype == np.float32 and support.dtype == bool and reward.shape == support.shape == SHAPE
    assert reward[row, col] == np.float32(r_tp) and reward.max() == np.float32(r_tp)
    assert support[row, col]
    assert np.all(reward[~support] == 0)
    assert np.all(reward[support] > 0)


def test_peak_normalization_gives_neighbours_nearly_the_same_reward():
    reward = tpg_label(SHAPE, 100, 100, 0.0, 1.0, CFG)[0]
    assert reward[100, 101] == pytest.approx(math.exp(-1 / 32), rel=1e-6)  # 1 px along x: sigma_x = 4
    assert reward[101, 100] == pytest.approx(math.exp(-1 / 8), rel=1e-6)  # 1 px across: sigma_y = 2
    assert reward[100, 101] > reward[101, 100]


def test_paper_normalization_leaves_r_tp_at_the_pixel_and_a_tiny_halo():
    reward = tpg_label(SHAPE, 100, 100, 0.0, 1.0, replace(CFG, kernel_normalization="paper"))[0]
    assert reward[100, 100] == 1.0
    halo = reward.copy()
    halo[100, 100] = 0
    assert 0 < halo.max() < 1.0 / (2 * math.pi * 8.0)


def test_label_at_the_border_is_the_clipped_kernel():
    full, full_support = tpg_label(SHAPE, 100, 100, 0.4, 0.8, CFG)
    corner, corner_support = tpg_label(SHAPE, 0, 223, 0.4, 0.8, CFG)
    # the corner label is the full label's lower-left quadrant (incl. the centre row/column), moved to the corner
    np.testing.assert_array_equal(corner[:13, 211:], full[100:113, 88:101])
    np.testing.assert_array_equal(corner_support[:13, 211:], full_support[100:113, 88:101])
    assert corner_support.sum() < full_support.sum() and corner[0, 223] == np.float32(0.8)
    assert corner_support[13:, :].sum() == 0 and corner_support[:, :211].sum() == 0


def test_zero_reward_still_has_a_support():
    reward, support = tpg_label(SHAPE, 50, 60, 1.0, 0.0, CFG)
    assert not reward.any()
    _, success_support = tpg_label(SHAPE, 50, 60, 1.0, 1.0, CFG)
    np.testing.assert_array_equal(support, success_support)
    assert support.sum() > 100


def test_zero_reward_support_pixel_learns_a_failure_at_its_pixel_only():
    """reward.zero_reward_support = "pixel": a failure's label is 0 at the executed pixel alone; a success
    keeps the Gaussian's whole support, and so does a failure under the default "kernel"."""
    pixel = replace(CFG, zero_reward_support="pixel")
    reward, support = tpg_label(SHAPE, 50, 60, 1.0, 0.0, pixel)
    assert support.sum() == 1 and support[50, 60] and not reward.any()
    success, success_support = tpg_label(SHAPE, 50, 60, 1.0, 0.7, pixel)
    expected, expected_support = tpg_label(SHAPE, 50, 60, 1.0, 0.7, CFG)
    np.testing.assert_array_equal(success_support, expected_support)
    np.testing.assert_array_equal(success, expected)
    assert tpg_label(SHAPE, 50, 60, 1.0, 0.0, CFG)[1].sum() > 100
    with pytest.raises(ConfigError, match="reward.zero_reward_support"):
        replace(CFG, zero_reward_support="everywhere")


def test_rotating_the_action_rotates_the_label():
    a, _ = tpg_label(SHAPE, 112, 112, 0.25, 1.0, CFG)
    b, _ = tpg_label(SHAPE, 112, 112, 0.25 + math.pi / 2, 1.0, CFG)
    # np.rot90 of a 224x224 map moves (112, 112) to (111, 112); the window around it rotates exactly
    np.testing.assert_allclose(np.rot90(a)[111 - 12:111 + 13, 112 - 12:112 + 13], b[100:125, 100:125])


def test_without_gaussian_the_label_is_one_pixel():
    reward, support = tpg_label(SHAPE, 5, 6, 0.0, 0.4, replace(CFG, use_gaussian=False))
    assert support.sum() == 1 and support[5, 6]
    assert np.count_nonzero(reward) == 1 and reward[5, 6] == np.float32(0.4)


def test_label_rejects_bad_input():
    with pytest.raises(ValueError, match="outside"):
        tpg_label(SHAPE, 224, 0, 0.0, 1.0, CFG)
    with pytest.raises(ValueError, match="r_tp"):
        tpg_label(SHAPE, 0, 0, 0.0, -0.1, CFG)
    with pytest.raises(ValueError, match="angle_rad"):
        tpg_label(SHAPE, 0, 0, float("nan"), 1.0, CFG)
