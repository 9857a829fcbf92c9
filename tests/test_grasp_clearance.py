"""Pick clearance: where a top-down pick's open fingers and hand come down, read from the depth heightmap."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from _learner_helpers import SMALL_MODEL

from romannet.actor.main import for_robot
from romannet.common.config import ConfigError, ExplorationConfig, load_config, load_config_text
from romannet.common.grasp_clearance import (
    GripperFootprint,
    PickClearance,
    angle_bin,
    centred_pixel,
    clear_picks,
    closing_widths,
    footprint_height,
    landing_heights,
    narrowest_clear_bin,
    nearest_clear_angle,
    surface_run_middle,
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


def _turned_block(size_px: int, half_m: tuple[float, float], top_m: float, yaw_rad: float) -> np.ndarray:
    """A heightmap of one block at the map's centre, its sides turned yaw_rad from the map's axes."""
    idx = (np.arange(size_px) + 0.5) * RES - size_px * RES / 2
    y, x = np.meshgrid(idx, idx, indexing="ij")
    u = x * math.cos(yaw_rad) + y * math.sin(yaw_rad)
    v = -x * math.sin(yaw_rad) + y * math.cos(yaw_rad)
    return np.where((np.abs(u) <= half_m[0]) & (np.abs(v) <= half_m[1]), top_m, 0.0).astype(np.float32)


def closing_width(hm: np.ndarray, res: float, g: GripperFootprint, xy: tuple[int, int], angle: float) -> float:
    return float(closing_widths(hm, res, g, xy[1], xy[0], np.array([angle]))[0])


def test_the_closing_width_is_a_blocks_side_when_square_and_its_diagonal_across_corners() -> None:
    yaw = math.radians(20.0)
    hm = _turned_block(224, (0.025, 0.025), 0.05, yaw)
    centre = (111, 111)
    assert closing_width(hm, RES, RG2, centre, yaw) == pytest.approx(0.05, abs=2 * RES)
    assert closing_width(hm, RES, RG2, centre, yaw + math.pi / 2) == pytest.approx(0.05, abs=2 * RES)
    assert closing_width(hm, RES, RG2, centre, yaw + math.pi / 4) == pytest.approx(0.05 * math.sqrt(2), abs=2 * RES)
    assert closing_width(hm, RES, RG2, (20, 20), yaw) == math.inf  # the table: nothing to squeeze
    wide = _turned_block(224, (0.07, 0.07), 0.05, 0.0)  # 14 cm: wider than the RG2's 11 cm opening
    assert closing_width(wide, RES, RG2, centre, 0.0) == math.inf


@pytest.mark.parametrize("yaw_deg", [0.0, 20.0, 33.0, 71.0])
def test_the_narrowest_clear_angle_closes_square_to_a_blocks_faces(yaw_deg: float) -> None:
    yaw = math.radians(yaw_deg)
    hm = _turned_block(224, (0.025, 0.04), 0.05, yaw)  # 5 x 8 cm: the narrow side along yaw
    clear = clear_picks(hm, RES, RG2, BINS)
    k = narrowest_clear_bin(hm, RES, RG2, clear, 112, 112, yaw + math.pi / 2)  # the net says: the wide side
    assert k is not None and clear[k, 112, 112]
    off = abs((k * math.pi / BINS - yaw + math.pi / 2) % math.pi - math.pi / 2)
    assert off < math.pi / BINS  # one of the two bins either side of the narrow side's axis


def test_a_round_object_keeps_the_nets_own_angle_among_the_narrowest() -> None:
    idx = (np.arange(224) + 0.5) * RES - 224 * RES / 2
    y, x = np.meshgrid(idx, idx, indexing="ij")
    hm = np.where(np.hypot(x, y) <= 0.025, 0.05, 0.0).astype(np.float32)  # a standing cylinder
    clear = clear_picks(hm, RES, RG2, BINS)
    assert clear[:, 112, 112].all()
    widths = [closing_width(hm, RES, RG2, (112, 112), k * math.pi / BINS) for k in range(BINS)]
    assert max(widths) - min(widths) <= 2 * RES  # every axis as wide, up to the pixels of its edge
    for k_own in (0, 8):  # the narrowest two by the pixels: the net's own stays
        assert narrowest_clear_bin(hm, RES, RG2, clear, 112, 112, k_own * math.pi / BINS) == k_own
    k = narrowest_clear_bin(hm, RES, RG2, clear, 112, 112, 5 * math.pi / BINS)
    assert k is not None and widths[k] <= min(widths) + RES
    clear[:, 112, 112] = False
    assert narrowest_clear_bin(hm, RES, RG2, clear, 112, 112, 0.0) is None  # nothing clear: no choice


def test_decide_with_the_narrowest_rule_closes_across_the_blocks_narrow_side() -> None:
    yaw = math.radians(30.0)
    res = 0.005
    size = 64
    idx = (np.arange(size) + 0.5) * res - size * res / 2
    y, x = np.meshgrid(idx, idx, indexing="ij")
    u, v = x * math.cos(yaw) + y * math.sin(yaw), -x * math.sin(yaw) + y * math.cos(yaw)
    hm = np.where((np.abs(u) <= 0.025) & (np.abs(v) <= 0.045), 0.05, 0.0).astype(np.float32)
    color = np.zeros((size, size, 3), np.uint8)
    model = RoManNet(SMALL_MODEL, seed=0)
    cfg = ExplorationConfig(random_angle_prob=0.0)
    rule = PickClearance(RG2, res, BINS, narrowest=True)
    clear = clear_picks(hm, res, RG2, BINS)
    for s in range(5):
        a = decide(model, color, hm, False, 0.0, np.random.default_rng(s), ("pick",), cfg, clearance=rule)
        assert clear[angle_bin(np.array(a.angle_rad), BINS), a.row, a.col]
        k = narrowest_clear_bin(hm, res, RG2, clear, a.row, a.col, 0.0)
        assert k is not None and abs(closing_width(hm, res, RG2, (a.col, a.row), a.angle_rad)
                                     - closing_width(hm, res, RG2, (a.col, a.row), k * math.pi / BINS)) <= res


def test_the_pick_angle_rule_follows_the_config_and_refuses_a_q_per_angle() -> None:
    assert PickClearance.for_config(load_config()).narrowest  # the default
    rule = PickClearance.for_config(load_config_text('[exploration]\npick_clearance = true\npick_angle = "net"\n'))
    assert rule is not None and not rule.narrowest
    with pytest.raises(ConfigError, match="pick_angle"):
        load_config_text('[exploration]\npick_angle = "widest"\n')
    with pytest.raises(ConfigError, match="pick_angle_bins"):
        load_config_text('[exploration]\npick_angle = "narrowest"\n[model]\npick_angle_bins = 16\n')


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 90.0])
def test_a_pick_off_a_blocks_middle_moves_along_its_closing_axis_to_the_middle(yaw_deg: float) -> None:
    yaw = math.radians(yaw_deg)
    hm = _turned_block(224, (0.025, 0.04), 0.05, yaw)  # 5 x 8 cm, its middle at pixel (111.5, 111.5)
    clear = clear_picks(hm, RES, RG2, BINS)
    k = angle_bin(np.array(yaw), BINS)
    angle = float(k) * math.pi / BINS  # closing across the 5 cm side
    for along, across in ((8, 0), (-9, 0), (6, 7)):  # pixels off the middle along / across the closing axis
        col = round(111.5 + along * math.cos(angle) - across * math.sin(angle))
        row = round(111.5 + along * math.sin(angle) + across * math.cos(angle))
        assert clear[k, row, col]
        r, c = centred_pixel(hm, RES, RG2, clear, row, col, angle)
        off = np.array([c - 111.5, r - 111.5])
        assert abs(off @ [math.cos(angle), math.sin(angle)]) <= 1.5  # in the middle between the fingers
        assert abs(off @ [-math.sin(angle), math.cos(angle)] - across) <= 1.5  # not moved across the axis


def test_a_pick_stays_where_its_middle_is_not_clear_or_nothing_fits() -> None:
    hm = _turned_block(224, (0.025, 0.025), 0.05, 0.0)
    clear = clear_picks(hm, RES, RG2, BINS)
    r, c = centred_pixel(hm, RES, RG2, clear, 111, 118, 0.0)
    assert r == 111 and abs(c - 111.5) <= 1  # the middle of pixels 99-124
    blocked = clear.copy()
    blocked[0, 105:118, 105:118] = False  # the middle not clear along that angle: the chosen pixel stays
    assert centred_pixel(hm, RES, RG2, blocked, 111, 118, 0.0) == (111, 118)
    wide = _turned_block(224, (0.07, 0.07), 0.05, 0.0)  # wider than the opening: nothing to centre on
    assert centred_pixel(wide, RES, RG2, np.ones_like(clear), 111, 130, 0.0) == (111, 130)
    assert centred_pixel(hm, RES, RG2, clear, 20, 20, 0.0) == (20, 20)  # the table


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 90.0])
def test_with_across_a_pick_also_moves_across_its_closing_axis_to_the_blocks_middle(yaw_deg: float) -> None:
    yaw = math.radians(yaw_deg)
    hm = _turned_block(224, (0.025, 0.04), 0.05, yaw)  # 5 x 8 cm: across the 5 cm side the block is 8 cm long
    clear = clear_picks(hm, RES, RG2, BINS)
    k = angle_bin(np.array(yaw), BINS)
    angle = float(k) * math.pi / BINS
    for along, across in ((6, 7), (-4, -12), (0, 15)):
        col = round(111.5 + along * math.cos(angle) - across * math.sin(angle))
        row = round(111.5 + along * math.sin(angle) + across * math.cos(angle))
        r, c = centred_pixel(hm, RES, RG2, clear, row, col, angle, across=True)
        off = np.array([c - 111.5, r - 111.5])
        assert np.hypot(*off) <= 2.0, (along, across, off)  # the block's middle both ways


def test_the_surface_run_stops_at_a_step_so_a_neighbour_lying_against_it_is_not_its_middle() -> None:
    hm = np.zeros((64, 64), np.float32)
    hm[30:34, 10:30] = 0.04  # a block 20 px long, its top 4 cm high
    hm[30:34, 30:50] = 0.05  # a taller one against it: 1 cm up, an edge, not the same surface
    assert surface_run_middle(hm, 0.01, 32, 15, 0.0, max_px=40) == pytest.approx(4.5)  # middle of 10..29
    hm[30:34, 30:50] = 0.043  # a tilted top rises 3 mm over one pixel: the same surface
    assert surface_run_middle(hm, 0.01, 32, 15, 0.0, max_px=40) == pytest.approx(14.5)
    assert surface_run_middle(hm, 0.01, 32, 15, 0.0, max_px=5) == pytest.approx(0.0)  # at most max_px each way


def test_the_across_rule_needs_the_centre_rule_and_is_off_by_default() -> None:
    assert not PickClearance.for_config(load_config()).across
    on = load_config_text("[exploration]\npick_clearance = true\npick_centre = true\npick_centre_across = true\n")
    assert PickClearance.for_config(on).across
    off = load_config_text("[exploration]\npick_clearance = true\npick_centre = false\npick_centre_across = true\n")
    assert not PickClearance.for_config(off).across


def _with_low_neighbour() -> np.ndarray:
    """A 3 x 5 cm block 4 cm tall in the middle (grasp height 1 cm), and 1.5 cm past its +x face, between the
    open fingers' 5.5 cm and the face, a low neighbour 2 cm tall: above the fingertips, under the pads' top."""
    hm = np.zeros((224, 224), np.float32)
    mid = 224 * RES / 2
    _box(hm, (mid, mid), (0.015, 0.025), 0.04)
    _box(hm, (mid + 0.04, mid), (0.01, 0.03), 0.02)
    return hm


def test_the_sweep_rules_out_an_angle_whose_closing_finger_meets_another_object_first() -> None:
    hm = _with_low_neighbour()
    row = col = 112
    clear = clear_picks(hm, RES, RG2, BINS)
    assert clear[0, row, col] and clear[BINS // 2, row, col]  # the fingers land clear either way
    along_x, along_y = closing_widths(hm, RES, RG2, row, col, np.array([0.0, math.pi / 2]))
    assert along_x == pytest.approx(0.03, abs=2 * RES) and along_y == pytest.approx(0.05, abs=2 * RES)
    swept_x, swept_y = closing_widths(hm, RES, RG2, row, col, np.array([0.0, math.pi / 2]), sweep=True)
    assert swept_x == math.inf  # the +x finger pushes the neighbour into the block
    assert swept_y == pytest.approx(0.05, abs=2 * RES)
    before = PickClearance(RG2, RES, BINS, narrowest=True, centre=True)
    after = PickClearance(RG2, RES, BINS, narrowest=True, centre=True, sweep=True)
    assert abs(before.executed(hm, clear, row, col, 0.3)[2]) < math.pi / BINS  # across the 3 cm side, into it
    _, _, angle = after.executed(hm, clear, row, col, 0.3)
    assert abs(angle - math.pi / 2) < math.pi / BINS  # across the 5 cm side, clear of the neighbour


def test_the_sweep_counts_a_ledge_under_the_pads_top_and_the_middle_stays_the_pads() -> None:
    hm = np.zeros((224, 224), np.float32)
    hm[90:135, 105:119] = 0.04  # a block 14 px (2.8 cm) across x, 9 cm along y, 4 cm tall: grasp height 1 cm
    hm[90:135, 119:132] = 0.015  # a 1.5 cm ledge on its +x side (above the fingertips, under the pads' top)
    clear = clear_picks(hm, RES, RG2, BINS)
    assert closing_widths(hm, RES, RG2, 112, 112, np.array([0.0]))[0] == pytest.approx(14 * RES)
    assert closing_widths(hm, RES, RG2, 112, 112, np.array([0.0]), sweep=True)[0] == pytest.approx(27 * RES)
    rule = PickClearance(RG2, RES, BINS, narrowest=True, centre=True, sweep=True)
    assert rule.executed(hm, clear, 112, 116, 0.0) == (112, 112, 0.0)  # the middle of 105..118


def test_where_no_angle_passes_the_sweep_the_pose_is_todays() -> None:
    hm = _with_low_neighbour()
    mid = 224 * RES / 2
    for dx, dy in ((-0.04, 0.0), (0.0, 0.045), (0.0, -0.045), (0.03, 0.04), (-0.03, 0.04), (0.03, -0.04),
                   (-0.03, -0.04)):
        _box(hm, (mid + dx, mid + dy), (0.008, 0.008), 0.02)  # low neighbours all round
    clear = clear_picks(hm, RES, RG2, BINS)
    assert not np.isfinite(closing_widths(hm, RES, RG2, 112, 112, np.arange(BINS) * math.pi / BINS, sweep=True)).any()
    before = PickClearance(RG2, RES, BINS, narrowest=True, centre=True)
    after = PickClearance(RG2, RES, BINS, narrowest=True, centre=True, sweep=True)
    for angle in (0.0, 0.7, 1.6):  # today's rule: across the 3 cm side, whatever the net's angle
        assert after.executed(hm, clear, 112, 112, angle) == before.executed(hm, clear, 112, 112, angle) \
            == (112, 112, 0.0)


def test_the_sweep_rule_follows_the_config_and_is_off_by_default() -> None:
    assert not PickClearance.for_config(load_config()).sweep
    rule = PickClearance.for_config(load_config_text(
        '[exploration]\npick_clearance = true\npick_angle = "narrowest"\npick_sweep = true\n'))
    assert rule is not None and rule.sweep
    with pytest.raises(ConfigError, match="pick_sweep.*narrowest"):
        load_config_text('[exploration]\npick_angle = "net"\npick_sweep = true\n')


SMALL_RES = 0.005  # the decisions' small scene: 64 x 64 px, a 5 x 8 cm block 5 cm tall in the middle


def _small_block_decisions() -> tuple[np.ndarray, np.ndarray, RoManNet, ExplorationConfig, PickClearance]:
    """(heightmap, colour, untrained net, exploration, centre rule) for decide() on the small scene."""
    idx = (np.arange(64) + 0.5) * SMALL_RES - 64 * SMALL_RES / 2
    y, x = np.meshgrid(idx, idx, indexing="ij")
    hm = np.where((np.abs(x) <= 0.025) & (np.abs(y) <= 0.04), 0.05, 0.0).astype(np.float32)
    return (hm, np.zeros((64, 64, 3), np.uint8), RoManNet(SMALL_MODEL, seed=0),
            ExplorationConfig(random_angle_prob=0.0), PickClearance(RG2, SMALL_RES, BINS, centre=True))


def test_decide_with_the_centre_rule_picks_in_the_middle_between_the_fingers() -> None:
    hm, color, model, cfg, rule = _small_block_decisions()
    clear = clear_picks(hm, SMALL_RES, RG2, BINS)
    for s in range(5):
        a = decide(model, color, hm, False, 1.0, np.random.default_rng(s), ("pick",), cfg, clearance=rule)
        assert clear[angle_bin(np.array(a.angle_rad), BINS), a.row, a.col]
        off = np.array([a.col - 31.5, a.row - 31.5]) @ [math.cos(a.angle_rad), math.sin(a.angle_rad)]
        assert abs(off) <= 1.5


def test_the_centre_rule_follows_the_config_and_goes_with_the_clearance_rule() -> None:
    assert PickClearance.for_config(load_config()).centre  # the default
    rule = PickClearance.for_config(load_config_text("[exploration]\npick_clearance = true\npick_centre = false\n"))
    assert rule is not None and not rule.centre
    assert PickClearance.for_config(load_config_text("[exploration]\npick_clearance = false\n")) is None


def test_the_centre_rule_does_not_move_a_pick_back_onto_a_failed_one() -> None:
    from romannet.common.failure_memory import FailureMemory

    hm, color, model, cfg, rule = _small_block_decisions()
    first = decide(model, color, hm, False, 0.0, np.random.default_rng(0), ("pick",), cfg, clearance=rule)
    memory = FailureMemory(radius_px=3)
    memory.record(first, False, 0.0, 0.0)  # the middle failed
    for s in range(5):
        a = decide(model, color, hm, False, 1.0, np.random.default_rng(s), ("pick",), cfg, avoid=memory,
                   clearance=rule)
        assert (a.row - first.row) ** 2 + (a.col - first.col) ** 2 > 3 ** 2
