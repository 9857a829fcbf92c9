"""sim.hand: the Panda's fingers (4 cm travel each, an 8 cm opening) or the paper's RG2 (11 cm), each with its
own force and speed; sim.finger_* override the hand's values. A 9 cm cube the Panda cannot take, the RG2 can."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.objects import ObjectSpec, spawn_object
from romannet.actor.sim.tasks import stack_height_from_poses
from romannet.bench.place_geometry import pick_centre, place_on
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import as_saved, load_config
from romannet.common.config_sim import HANDS, SimConfig
from romannet.common.configbase import ConfigError

pytestmark = pytest.mark.timeout(120)

SMALL = ["workspace.resolution_m=0.007", "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655",
         "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0", 'task.kind="clutter"']


def _env(robot: str, hand: str, *overrides: str) -> SimEnv:
    cfg = load_config(None, [*SMALL, f'sim.robot="{robot}"', f'sim.hand="{hand}"', *overrides])
    return SimEnv.from_config(cfg)


def _pick_wide_cube(env: SimEnv) -> bool:
    """A lone 9 cm cube at the workspace centre, picked top-down across two faces; did the pick hold it?"""
    env.task_def = dataclasses.replace(env.task_def, num_objects=0)
    env.reset(0)
    x, y = (env.ws.x_min_m + env.ws.x_max_m) / 2, (env.ws.y_min_m + env.ws.y_max_m) / 2
    body = spawn_object(env.scene.client, ObjectSpec("cube", (0.8, 0.2, 0.2, 1.0), (x, y, 0.046), scale=1.8))
    env.scene.add_object(body)
    env.scene.settle(240)
    env.observe_start()
    row, col = position_to_pixel(x + env.ws.resolution_m / 2, y + env.ws.resolution_m / 2, env.ws)
    return bool(env.step(Action("pick", row, col, 0.0, 1.0)).success)


@pytest.mark.parametrize("robot", ["arm", "gripper"])
def test_each_hand_opens_as_far_as_its_travel(robot: str) -> None:
    for hand, gap_m in (("panda", 0.08), ("rg2", 0.11)):
        with _env(robot, hand) as env:
            env.reset(1)
            assert env.arm is not None
            assert env.arm.finger_gap_m() == pytest.approx(gap_m, abs=1e-4)


def test_a_set_finger_travel_overrides_the_hands() -> None:
    with _env("gripper", "panda", "sim.finger_travel_m=0.05") as env:
        env.reset(1)
        assert env.arm is not None
        assert env.arm.finger_gap_m() == pytest.approx(0.10, abs=1e-4)


def test_a_9_cm_cube_needs_the_rg2s_opening() -> None:
    results = {}
    for hand in ("panda", "rg2"):
        with _env("gripper", hand) as env:
            results[hand] = _pick_wide_cube(env)
    assert results == {"panda": False, "rg2": True}


def test_the_hands_values_fill_what_is_unset() -> None:
    panda, rg2 = SimConfig(hand="panda"), SimConfig()  # the RG2 is the default hand
    assert (panda.finger_travel_m, panda.finger_force_n, panda.finger_speed_mps) == (0.04, 40.0, 0.1)
    assert (rg2.finger_travel_m, rg2.finger_force_n, rg2.finger_speed_mps) == (
        HANDS["rg2"].travel_m, HANDS["rg2"].force_n, HANDS["rg2"].speed_mps)
    assert SimConfig(hand="rg2", finger_force_n=25.0).finger_force_n == 25.0
    # A resolved config written out and read back is the same hand (a run's config.toml, a model's).
    assert load_config(None, ['sim.hand="rg2"']).sim == rg2


def test_hand_and_finger_travel_are_validated_with_the_field_named() -> None:
    with pytest.raises(ConfigError, match="sim.finger_travel_m"):
        SimConfig(finger_travel_m=0.2)
    with pytest.raises(ConfigError, match="sim.hand"):
        SimConfig(hand="robotiq")  # type: ignore[arg-type]


def test_the_rg2_holds_picks_the_panda_misses() -> None:
    """romannet bench pick-geometry's measurement: a lone 5 cm cube picked 2 cm off its centre along the
    closing axis is held by the RG2 (3 cm of clearance each side) and not by the Panda (1.5 cm)."""
    from romannet.bench.pick_geometry import hand_table

    offsets = (0.0, 0.02)
    panda = hand_table("panda", 0.05, offsets_m=offsets, angles_deg=(0.0,))
    rg2 = hand_table("rg2", 0.05, offsets_m=offsets, angles_deg=(0.0,))
    assert panda["rows"] == [[0.0, [True]], [0.02, [False]]]
    assert rg2["rows"] == [[0.0, [True]], [0.02, [True]]]
    assert (panda["margin_m"]["0.0"], rg2["margin_m"]["0.0"]) == (0.0, 0.02)


def _stacking_env(hand: str, *overrides: str) -> SimEnv:
    cfg = load_config(None, [*SMALL[:-1], 'task.kind="stacking"', "task.cube_size_m=0.04", 'sim.robot="gripper"',
                             f'sim.hand="{hand}"', "sim.num_stacking_cubes=3", *overrides])
    return SimEnv.from_config(cfg)


@pytest.mark.parametrize("hand", ["panda", "rg2"])
def test_coupled_fingers_hold_a_cube_centred_and_place_it_where_asked(hand: str) -> None:
    with _stacking_env(hand) as env:
        env.reset(0)
        assert env.sim.coupled_fingers and env.prims is not None and env.arm is not None
        first, second, third = env.scene.objects[:3]
        hang = pick_centre(env, second)
        assert hang is not None
        held_xy, tip_xy = env.scene.pose(second)[0][:2], env.arm.tip_position()[:2]
        assert float(np.linalg.norm(held_xy - tip_xy)) < 0.003  # centred between the fingers
        # Built into a 2-stack, then a third cube placed 1 cm off its top's centre along a face: it stays.
        place_on(env, first, hang, 0.0, 0.0, 0.0)
        hang = pick_centre(env, third)
        assert hang is not None
        place_on(env, second, hang, 0.01, 0.0, 0.0)
        assert stack_height_from_poses(env.scene, 0.04) == 3


def test_a_saved_config_without_coupled_fingers_runs_as_it_was_trained() -> None:
    assert SimConfig().coupled_fingers and load_config(None, ['sim.hand="panda"']).sim.coupled_fingers  # recipes
    assert as_saved({"sim": {"hand": "panda"}})["sim"]["coupled_fingers"] is False  # a run saved before the field


def test_place_geometry_counts_the_places_that_hold_and_renders_a_table() -> None:
    """romannet bench place-geometry's measurement: with coupled fingers a cube placed 1 cm off the top's
    centre, along a face and along the diagonal, holds on a lone cube and on a 2-stack."""
    from romannet.bench.place_geometry import markdown, place_table

    table = place_table("panda", 0.04, coupled=True, seeds=(0,), offsets_m=(0.01,), turns_deg=(0.0,))
    assert table["rows"] == [[1, 0.01, [[2, 2]]], [2, 0.01, [[2, 2]]]]
    text = markdown({"tables": [table]})
    assert "| a 2-stack | 1 cm | 2/2 |" in text and "coupled fingers" in text
