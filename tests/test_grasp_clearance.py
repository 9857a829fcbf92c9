"""Pick clearance: where a top-down pick's open fingers and hand come down, read from the depth heightmap."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from _learner_helpers import SMALL_MODEL

from romannet.actor.main import for_robot
from romannet.common.config import ExplorationConfig, load_config, load_config_text
from romannet.common.grasp_clearance import (
    GripperFootprint,
    PickClearance,
    angle_bin,
    clear_picks,
    footprint_height,
    landing_heights,
    nearest_clear_angle,
)
from romannet.common.model import RoManNet
from romannet.common.policy import decide
from romannet.common.scenes import synthetic_scene

STACKING = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "stacking.toml"
RG2 = GripperFootprint(travel_m=0.055, pick_depth_m=0.03, tip_floor_m=0.006)
RES = 0.002
BINS = 16


def _box(hm: np.ndarray, centre_m: tuple[float, float], half_m: tuple[float, float], top_m: float,
         res: float = RES) -> None:
    """An axis-aligned block: centre (x, y) from the map's corner, half sizes (x, y), its top height."""
    c0, c1 = round((centre_m[0] - half_m[0]) / res), round((centre_m[0] + half_m[0]) / res)
    r0, r1 = round((centre_m[1] - half_m[1]) / res), round((centre_m[1] + half_m[1]) / res)
    hm[r0:r1, c0:c1] = np.maximum(hm[r0:r1, c0:c1], top_m)


def _scene(res: float = RES, size_px: int = 224) -> tuple[np.ndarray, tuple[int, int]]:
    """A 5 cm block 4 cm tall in the middle, a 6 cm tall neighbour 8 cm along +x: (heightmap, block's pixel)."""
    hm = np.zeros((size_px, size_px), np.float32)
    mid = size_px * res / 2
    _box(hm, (mid, mid), (0.025, 0.025), 0.04, res)
    _box(hm, (mid + 0.08, mid), (0.015, 0.025), 0.06, res)
    return hm, (size_px // 2, size_px // 2)


def test_a_finger_over_a_taller_neighbour_blocks_that_closing_axis_and_not_the_other() -> None:
    hm, (row, col) = _scene()
    clear = clear_picks(hm, RES, RG2, BINS)
    assert not clear[0, row, col]  # closing along x: a finger comes down on the neighbour
    assert clear[BINS // 2, row, col]  # closing along y: both fingers reach the grasp height
    lone = hm.copy()
    lone[:, col + 30:] = 0.0  # the neighbour taken away
    assert clear_picks(lone, RES, RG2, BINS)[:, row, col].all()


def test_a_pick_centred_over_the_floor_is_never_clear() -> None:
    hm, (row, col) = _scene()
    assert not clear_picks(hm, RES, RG2, BINS)[:, row, col - 60].any()  # 12 cm from the block, on the table
    assert not clear_picks(hm, RES, RG2, BINS)[:, row, col - 16].any()  # 3 cm left of it: the floor between


def test_the_map_is_the_pointwise_rule_up_to_a_pixel() -> None:
    """landing_heights (rotated maps, box filters) against footprint_height (points along the rectangles)."""
    rng = np.random.default_rng(3)
    agree, total = 0, 0
    for _ in range(3):
        _, hm = synthetic_scene(rng)
        heights = landing_heights(hm, RES, RG2, BINS)
        grasp = RG2.grasp_height(hm)
        for _ in range(200):
            row, col, k = int(rng.integers(224)), int(rng.integers(224)), int(rng.integers(BINS))
            point = footprint_height(hm, RES, (col + 0.5, row + 0.5), k * math.pi / BINS, RG2)
            agree += (point <= grasp[row, col] + RG2.clear_m) == (heights[k, row, col] <= grasp[row, col] + RG2.clear_m)
            total += 1
    assert agree / total >= 0.97  # the rest lie where a rectangle's edge meets a block's edge within a pixel


def test_nearest_clear_angle_keeps_a_clear_own_angle_and_otherwise_takes_the_nearest_clear_axis() -> None:
    bins = 4  # 0, 45, 90, 135 degrees
    clear = np.zeros((bins, 1, 4), bool)
    clear[0, 0, 0] = True  # own bin clear: the net's exact angle stays
    clear[2, 0, 1] = True  # only 90 degrees
    clear[[1, 3], 0, 3] = True  # 45 and 135 degrees: 178 degrees is nearest 135 (modulo 180)
    own = np.array([[0.05, 0.1, 0.3, math.radians(178.0)]], np.float32)
    valid, angles = nearest_clear_angle(own, clear)
    assert valid.tolist() == [[True, True, False, True]]
    assert angles[0, 0] == pytest.approx(0.05)
    assert angles[0, 1] == pytest.approx(math.pi / 2)
    assert angles[0, 2] == pytest.approx(0.3)  # nothing clear: unchanged (the pixel is not chosen)
    assert angles[0, 3] == pytest.approx(3 * math.pi / 4)
    assert angle_bin(np.array([math.pi - 0.01, -0.01, math.pi / 4]), bins).tolist() == [0, 0, 1]


def test_decide_picks_only_where_a_pick_is_clear_at_the_angle_it_executes() -> None:
    res = 0.005  # 64 px of 5 mm: the whole hand fits on a small map
    hm, _ = _scene(res, 64)
    color = np.zeros((*hm.shape, 3), np.uint8)
    clearance = PickClearance(RG2, res)
    clear = clear_picks(hm, res, RG2, BINS)
    model = RoManNet(SMALL_MODEL, seed=0)
    cfg = ExplorationConfig(random_angle_prob=0.0)
    actions = [decide(model, color, hm, False, rate, np.random.default_rng(s), ("pick",), cfg, clearance=clearance)
               for rate in (0.0, 1.0) for s in range(10)]
    for a in actions:
        assert clear[angle_bin(np.array(a.angle_rad), BINS), a.row, a.col], a
    plain = decide(model, color, hm, False, 0.0, np.random.default_rng(0), ("pick",), cfg)
    assert not clear[angle_bin(np.array(plain.angle_rad), BINS), plain.row, plain.col]  # the rule changed it


def test_pick_clearance_follows_the_config_and_the_simulated_hand() -> None:
    assert PickClearance.for_config(load_config_text("[exploration]\npick_clearance = false\n")) is None
    cfg = load_config_text('[exploration]\npick_clearance = true\n[sim]\nhand = "panda"\n')
    rule = PickClearance.for_config(cfg)
    assert rule is not None and rule.footprint.travel_m == pytest.approx(0.04)
    assert rule.resolution_m == cfg.workspace.resolution_m
    assert load_config().exploration.pick_clearance  # the clutter recipe's, and so the default
    assert not load_config(STACKING).exploration.pick_clearance  # not measured on stacking
    # A config saved before the rule existed (a run's, a model package's) ran without it, and still does.
    assert not load_config_text("[exploration]\nfailure_memory_px = 10\n").exploration.pick_clearance


def test_a_real_robot_actor_runs_without_the_rule_and_says_so(caplog) -> None:
    cfg = load_config()
    with caplog.at_level(logging.WARNING):
        real = for_robot(cfg, "ur")
    assert not real.exploration.pick_clearance and "pick_clearance is off on a real robot" in caplog.text
    assert for_robot(cfg, "sim") is cfg
