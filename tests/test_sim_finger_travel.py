"""sim.finger_travel_m: how far each finger opens. The default is the Panda's 4 cm (an 8 cm opening); 0.055
opens 11 cm like the paper's RG2 gripper, and a 9 cm cube the Panda cannot take becomes graspable."""

from __future__ import annotations

import dataclasses

import pytest

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.objects import ObjectSpec, spawn_object
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import load_config
from romannet.common.config_sim import SimConfig
from romannet.common.configbase import ConfigError

pytestmark = pytest.mark.timeout(120)

SMALL = ["workspace.resolution_m=0.007", "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655",
         "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0", 'task.kind="clutter"']


def _env(robot: str, travel_m: float) -> SimEnv:
    cfg = load_config(None, [*SMALL, f'sim.robot="{robot}"', f"sim.finger_travel_m={travel_m}"])
    return SimEnv.from_config(cfg)


def _pick_wide_cube(env: SimEnv) -> bool:
    """A lone 9 cm cube at the workspace centre, picked top-down across two faces; did the pick hold it?"""
    env.task_def = dataclasses.replace(env.task_def, num_objects=0)
    env.reset(0)
    x, y = (env.ws.x_min_m + env.ws.x_max_m) / 2, (env.ws.y_min_m + env.ws.y_max_m) / 2
    body = spawn_object(env.scene.client, ObjectSpec("cube", (0.8, 0.2, 0.2, 1.0), (x, y, 0.046), scale=1.8))
    env.scene.add_object(body)
    env.scene.settle(240)
    env.obs = env._observe()
    env.depth_start = env.obs.depth_hm
    row, col = position_to_pixel(x + env.ws.resolution_m / 2, y + env.ws.resolution_m / 2, env.ws)
    return bool(env.step(Action("pick", row, col, 0.0, 1.0)).success)


@pytest.mark.parametrize("robot", ["arm", "gripper"])
def test_the_hand_opens_as_far_as_the_configured_travel(robot: str) -> None:
    for travel_m in (0.04, 0.055):
        with _env(robot, travel_m) as env:
            env.reset(1)
            assert env.arm is not None
            assert env.arm.finger_gap_m() == pytest.approx(2 * travel_m, abs=1e-4)


def test_a_9_cm_cube_needs_the_wider_opening() -> None:
    results = {}
    for travel_m in (0.04, 0.055):
        with _env("gripper", travel_m) as env:
            results[travel_m] = _pick_wide_cube(env)
    assert results == {0.04: False, 0.055: True}


def test_finger_travel_is_validated_with_the_field_named() -> None:
    assert SimConfig().finger_travel_m == 0.04  # the Panda's default is unchanged
    with pytest.raises(ConfigError, match="sim.finger_travel_m"):
        SimConfig(finger_travel_m=0.2)
