"""The real robot's safety math and primitive plans (pure functions; no driver needed)."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from romannet.actor.real.motion import (
    descend_plan,
    fold_angle,
    pick_tool_z,
    place_tool_z,
    push_plan,
    tool_rotvec,
)
from romannet.actor.real.safety import SafetyBox, cap_motion, clamp_pose, inside
from romannet.common.config import load_config_text
from romannet.common.config_robot import RealSenseConfig, RobotConfig
from romannet.common.errors import ConfigError

BOX = SafetyBox((0.3, -0.2, 0.02), (0.7, 0.2, 0.4), max_speed_mps=0.2, max_accel_mps2=1.0)


def test_positions_outside_the_box_are_clamped_onto_it_and_reported():
    pose, clamped = clamp_pose([0.9, -0.5, -0.1, math.pi, 0.0, 0.0], BOX)
    assert clamped
    np.testing.assert_allclose(pose, [0.7, -0.2, 0.02, math.pi, 0.0, 0.0])
    pose, clamped = clamp_pose([0.5, 0.0, 0.1, 1.0, 2.0, 3.0], BOX)
    assert not clamped and pose.tolist() == [0.5, 0.0, 0.1, 1.0, 2.0, 3.0]


@pytest.mark.parametrize("bad", [[0.5, 0.0, float("nan"), 0, 0, 0], [0.5, 0.0, 0.1], [0.5, float("inf"), 0, 0, 0, 0]])
def test_a_non_finite_or_short_pose_is_refused_not_clamped(bad):
    with pytest.raises(ValueError, match="6 finite numbers"):
        clamp_pose(bad, BOX)


def test_speed_and_acceleration_are_capped():
    assert cap_motion(1.5, 3.0, BOX) == (0.2, 1.0)
    assert cap_motion(0.05, 0.5, BOX) == (0.05, 0.5)
    with pytest.raises(ValueError):
        cap_motion(0.0, 1.0, BOX)
    with pytest.raises(ValueError):
        cap_motion(float("nan"), 1.0, BOX)


def test_inside():
    assert inside([0.3, 0.2, 0.4], BOX) and not inside([0.29, 0.0, 0.1], BOX)


@pytest.mark.parametrize("angle, folded", [(0.0, 0.0), (math.pi, 0.0), (-math.pi / 2, math.pi / 2),
                                           (3 * math.pi / 4, -math.pi / 4), (math.pi / 2, math.pi / 2),
                                           (-3 * math.pi / 4, math.pi / 4)])
def test_tool_angles_fold_into_a_half_turn(angle, folded):
    assert fold_angle(angle) == pytest.approx(folded)


def test_tool_orientation_points_down_and_turns_about_base_z():
    for angle in (0.0, 0.4, -1.2):
        r, _ = cv2.Rodrigues(np.array(tool_rotvec(angle, (math.pi, 0.0, 0.0))))
        np.testing.assert_allclose(r[:, 2], [0, 0, -1], atol=1e-9)  # tool z axis points down
        np.testing.assert_allclose(math.atan2(r[1, 0], r[0, 0]), angle, atol=1e-9)  # tool x turned by angle


def test_push_plan_goes_down_pushes_along_the_angle_and_comes_up():
    cfg = RobotConfig(push_distance_m=0.1, approach_height_m=0.08)
    plan = push_plan(0.5, 0.0, 0.03, math.pi / 2, cfg)
    xyz = np.array([wp.pose[:3] for wp in plan])
    np.testing.assert_allclose(xyz, [[0.5, 0.0, 0.11], [0.5, 0.0, 0.03], [0.5, 0.1, 0.03], [0.5, 0.1, 0.11]],
                               atol=1e-12)
    assert [wp.contact for wp in plan] == [False, True, True, False]


def test_pick_and_place_heights():
    cfg = RobotConfig(pick_depth_m=0.01, held_object_height_m=0.05, place_clearance_m=0.02)
    assert pick_tool_z(0.05, cfg) == pytest.approx(0.04)
    assert place_tool_z(0.05, cfg) == pytest.approx(0.12)
    plan = descend_plan(0.4, 0.1, 0.04, 0.0, cfg)
    assert plan[0].pose[2] == pytest.approx(0.04 + cfg.approach_height_m) and plan[1].contact


@pytest.mark.parametrize("text, field", [
    ("[robot]\nlimits_z_m = [0.3, 0.1]", "robot.limits_z_m"),
    ("[robot]\nmax_speed_mps = 3.0", "robot.max_speed_mps"),
    ("[robot]\ntool_output_pin = 4", "robot.tool_output_pin"),
    ("[robot]\nbins_xy_m = [[0.3, -0.2]]", "robot.bins_xy_m"),
    ("[robot]\nhome_pose = [0.5, 0.0, 0.3]", "robot.home_pose"),
    ("[robot]\ntool = \"magnet\"", "robot.tool"),
    ("[realsense]\nwidth_px = 641", "realsense.width_px"),
    ("[realsense]\nserial = \"12 34\"", "realsense.serial"),
])
def test_robot_config_errors_name_the_field(text, field):
    with pytest.raises(ConfigError) as err:
        load_config_text(text)
    assert err.value.field == field


def test_robot_config_defaults_are_valid_and_capped():
    cfg = load_config_text("[robot]\nhost = \"10.0.0.2\"\nmove_speed_mps = 0.9\nmax_speed_mps = 0.3")
    assert cfg.robot.speed_cap == (0.3, 0.05)
    assert dataclasses.replace(RealSenseConfig(), serial="f1230450").serial == "f1230450"


def test_shipped_real_robot_configs_load_and_keep_every_commanded_position_in_the_box():
    from pathlib import Path

    from romannet.actor.real.calibration import grid_positions
    from romannet.actor.real.env import bin_workspaces
    from romannet.common.config import load_config

    files = sorted((Path(__file__).resolve().parents[1] / "configs" / "real").glob("*.toml"))
    assert len(files) >= 2
    for path in files:
        cfg = load_config(path)
        box = SafetyBox.from_config(cfg.robot)
        assert inside(cfg.robot.home_pose, box), path
        for p in grid_positions(cfg.calibration.grid_x_m, cfg.calibration.grid_y_m, cfg.calibration.grid_z_m):
            assert inside(p, box), (path, p)
        for ws in bin_workspaces(cfg):  # the heightmap of every bin lies inside the box in x and y
            assert inside((ws.x_min_m, ws.y_min_m, box.low[2]), box) and \
                inside((ws.x_max_m, ws.y_max_m, box.low[2]), box), (path, ws)
