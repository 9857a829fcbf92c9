"""URRobot and RealSenseCamera on the fake drivers (tests/fakes: the real ur_rtde / pyrealsense2 names and
signatures, checked in test_real_fakes.py), and on the real drivers where no device is needed."""

from __future__ import annotations

import dataclasses
import importlib.util
import math

import numpy as np
import pytest
from _fake_drivers import fake_drivers, fakeworld

from romannet.actor.real.realsense import RealSenseCamera
from romannet.actor.real.ur import URRobot
from romannet.common.config_robot import RealSenseConfig, RobotConfig
from romannet.common.errors import ConfigError, RobotError

pytestmark = pytest.mark.timeout(60)

HOME = (0.5, -0.35, 0.35, math.pi, 0.0, 0.0)
LIMITS = {"limits_x_m": (0.3, 0.7), "limits_y_m": (-0.4, 0.2), "limits_z_m": (0.01, 0.4)}


def robot_cfg(**kw) -> RobotConfig:
    return RobotConfig(**{"host": "ur-fake", "home_pose": HOME, "vacuum_settle_s": 0.0, "max_speed_mps": 0.2,
                          "max_accel_mps2": 1.0, "move_speed_mps": 0.5, "accel_mps2": 2.0, **LIMITS, **kw})


def world(**kw):
    return fakeworld().World(host="ur-fake", home_pose=list(HOME), **kw)


@pytest.fixture
def cell():
    w = world()
    w.add_box("red", (0.5, 0.1, 0.025), (0.05, 0.05, 0.05))
    w.add_box("blue", (0.4, -0.1, 0.025), (0.05, 0.05, 0.05), rgb=(40, 40, 200))
    with fake_drivers(w):
        robot = URRobot(robot_cfg())
        robot.connect()
        yield w, robot
        robot.disconnect()


def test_connect_refuses_an_unready_controller_with_the_reason():
    with pytest.raises(RobotError, match="robot.host is empty"):
        URRobot(RobotConfig()).connect()
    with fake_drivers(world()):
        with pytest.raises(RobotError, match="cannot connect to the UR controller at elsewhere"):
            URRobot(robot_cfg(host="elsewhere")).connect()
    for attrs, why in (({"robot_mode": 5}, "robot mode is idle"), ({"protective_stopped": True}, "protective_stop"),
                       ({"emergency_stopped": True}, "emergency_stop"), ({"safety_mode": 9}, "fault")):
        w = world()
        for name, value in attrs.items():
            setattr(w, name, value)
        with fake_drivers(w), pytest.raises(RobotError, match=why):
            URRobot(robot_cfg()).connect()
        assert w.moves() == []  # connecting never moves the arm


def test_home_outside_the_safety_box_is_a_config_error():
    with pytest.raises(ConfigError, match="home_pose"):
        robot_cfg(home_pose=(0.5, 0.5, 0.3, math.pi, 0.0, 0.0))


def test_every_primitive_stays_in_the_box_at_capped_speeds(cell):
    w, robot = cell
    box_low, box_high = np.array([0.3, -0.4, 0.01]), np.array([0.7, 0.2, 0.4])
    results = [robot.push(0.68, 0.0, 0.02, 0.0),  # pushes 10 cm along +x: ends beyond x = 0.7
               robot.pick(0.5, 0.1, 0.05, 0.3),  # the red box
               robot.place(0.75, 0.25, 0.0, 0.0),  # outside the box in x and y
               robot.pick(0.65, 0.15, -0.05, 0.0),  # below the minimum height
               robot.drop(0.5, 0.0, 0.6),  # above the maximum height
               robot.move_to((0.0, 0.0, 1.0, math.pi, 0.0, 0.0))]
    assert [r.clamped for r in results] == [True, False, True, True, True, True]
    moves = w.moves()
    assert len(moves) > 15
    for m in moves:
        xyz = np.array(m["pose"][:3])
        assert np.all(xyz >= box_low - 1e-12) and np.all(xyz <= box_high + 1e-12), m
        assert m["speed"] <= 0.2 and m["acceleration"] <= 1.0
    assert {m["speed"] for m in moves} == {0.2, 0.05}  # free-space moves capped, contact moves slow
    assert robot.clamped_moves >= 5


def test_suction_pick_and_place_report_the_vacuum_sensor(cell):
    w, robot = cell
    picked = robot.pick(0.5, 0.1, 0.05, 0.0)
    assert picked.success and w.attached == "red" and robot.holding()
    placed = robot.place(0.4, -0.1, 0.05, 0.0)  # onto the blue box
    assert placed.success and w.attached is None and not robot.holding()
    assert w.box("red").center_m[2] == pytest.approx(0.075, abs=1e-6)  # resting on blue
    empty = robot.pick(0.6, -0.2, 0.0, 0.0)
    assert (empty.success, empty.reason) == (False, "nothing_grasped")
    assert w.tool_out[0] is False  # the vacuum was switched off again
    assert robot.place(0.5, 0.0, 0.0, 0.0).reason == "dropped"  # nothing held: no motion
    assert np.allclose(w.tcp_pose, HOME)


def test_the_tool_settle_wait_is_spent_only_when_the_tool_changes(cell, monkeypatch):
    import romannet.actor.real.ur as ur

    w, robot = cell
    waits: list[float] = []
    monkeypatch.setattr(ur.time, "sleep", waits.append)
    robot.cfg = dataclasses.replace(robot.cfg, vacuum_settle_s=0.3)
    io_before = sum(c["call"] == "setToolDigitalOut" for c in w.calls)
    assert robot.push(0.5, 0.0, 0.02, 0.0).success  # suction: the vacuum is off and stays off
    assert waits == []
    assert sum(c["call"] == "setToolDigitalOut" for c in w.calls) > io_before  # still written, not skipped
    assert robot.pick(0.5, 0.1, 0.05, 0.0).success and waits == [0.3]  # vacuum on
    assert robot.place(0.4, -0.1, 0.05, 0.0).success and waits == [0.3, 0.3]  # and off again


def test_gripper_success_from_the_finger_width():
    w = world(tool="gripper", width_per_volt_m=0.01)
    w.add_box("cube", (0.5, 0.0, 0.025), (0.04, 0.04, 0.05))
    with fake_drivers(w):
        with URRobot(robot_cfg(tool="gripper", width_per_volt_m=0.01, grasp_min_width_m=0.005)) as robot:
            assert not robot.holding()  # open fingers are wide, but hold nothing
            assert robot.pick(0.5, 0.0, 0.05, 0.0).success
            assert robot.gripper_width_m() == pytest.approx(0.04, abs=1e-3) and robot.holding()
            assert robot.place(0.45, 0.1, 0.0, 0.0).success and not robot.holding()
            assert robot.pick(0.6, -0.2, 0.0, 0.0).reason == "nothing_grasped"


@pytest.mark.parametrize("stop", ["protective", "emergency"])
def test_a_stop_fails_the_primitive_and_nothing_moves_until_cleared(cell, stop):
    w, robot = cell
    getattr(w, f"inject_{stop}_stop")(when_z_below=0.06)
    result = robot.pick(0.5, 0.1, 0.05, 0.0)
    assert (result.success, result.stopped) == (False, f"{stop}_stop") and robot.stopped == f"{stop}_stop"
    n = len(w.moves())
    assert robot.go_home().stopped and robot.push(0.5, 0.0, 0.02, 0.0).stopped
    assert len(w.moves()) == n  # refused without a command to the controller: nothing is retried
    assert not robot.resume()  # still stopped on the pendant
    w.clear_stop()
    assert robot.resume() and robot.stopped == ""  # a new control connection restarted ur_rtde's script
    assert len(w.moves()) == n  # resuming moved nothing
    assert robot.go_home().success and np.allclose(w.tcp_pose, HOME)


def test_an_unreachable_pose_fails_the_primitive_and_returns_home():
    w = world(reach_m=0.62)
    with fake_drivers(w), URRobot(robot_cfg()) as robot:
        result = robot.push(0.65, -0.3, 0.02, 0.0)
        assert (result.success, result.reason, result.stopped) == (False, "motion_failed", "")
        assert np.allclose(w.tcp_pose, HOME) and robot.stopped == ""


def test_realsense_frames_in_metres_with_the_device_intrinsics():
    w = world()
    w.add_box("red", (0.5, 0.0, 0.05), (0.1, 0.1, 0.1))
    with fake_drivers(w):
        with RealSenseCamera(RealSenseConfig(warmup_frames=2)) as cam:
            frame = cam.capture()
            assert cam.depth_scale_m == pytest.approx(0.001)
            np.testing.assert_allclose(frame.intrinsics, [[615, 0, 320], [0, 615, 240], [0, 0, 1]])
            assert frame.color.shape == (480, 640, 3) and frame.color.dtype == np.uint8
            # The camera looks straight down from 0.9 m: the box top (0.1 m) is 0.8 m away, the table 0.9 m.
            assert frame.depth_m[240, 320] == pytest.approx(0.8, abs=0.001)
            assert frame.depth_m[20, 20] == pytest.approx(0.9, abs=0.001)
        with pytest.raises(RobotError, match="no RealSense camera with serial 'abc123'"):
            RealSenseCamera(RealSenseConfig(serial="abc123")).connect()
        w.camera.timeout = True
        with pytest.raises(RobotError, match="no frames"):
            RealSenseCamera(RealSenseConfig(warmup_frames=1, timeout_s=0.1)).connect()
        w.camera.connected = False
        with pytest.raises(RobotError, match="no RealSense camera is connected"):
            RealSenseCamera(RealSenseConfig()).connect()


# ------------------------------------------------------------------------- the real drivers, no device
@pytest.mark.skipif(importlib.util.find_spec("rtde_receive") is None, reason="ur_rtde is not installed")
def test_real_ur_rtde_reports_an_absent_controller_clearly():
    with pytest.raises(RobotError, match=r"cannot connect to the UR controller at 127\.0\.0\.1: .*30004"):
        URRobot(robot_cfg(host="127.0.0.1")).connect()


def test_real_pyrealsense2_reports_no_camera_clearly():
    try:
        from romannet.actor.real.realsense import import_pyrealsense2

        import_pyrealsense2()
    except RobotError as err:
        pytest.skip(f"the real pyrealsense2 does not import here: {err}")
    with pytest.raises(RobotError, match="no RealSense camera is connected"):
        RealSenseCamera(RealSenseConfig()).connect()
