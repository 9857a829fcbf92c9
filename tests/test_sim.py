"""PyBullet simulator: camera -> heightmap geometry, primitives, stack measurement, determinism, episode ends.

Small scenes on purpose (one to five cubes, 1-4 objects per episode): the whole file must stay fast on a
busy two-core machine. Cubes are spawned directly with actor.sim.objects so each test controls its scene.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.objects import CUBE_SIZE_M, ObjectSpec, spawn_object
from romannet.actor.sim.oracle import oracle_action
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import TaskConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.errors import ConfigError

WS = WorkspaceConfig()
RED = (0.9, 0.1, 0.1, 1.0)


def _quat_yaw(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _env(kind: str = "stacking", **sim_kwargs) -> SimEnv:
    sim = SimConfig(**{"num_objects": 2, "num_stacking_cubes": 2, "settle_steps": 120, **sim_kwargs})
    return SimEnv(task=TaskConfig(kind=kind, goal_stack_height=5), sim=sim)


def _scene_with_cubes(env: SimEnv, cubes: list[tuple[float, float, float, float]], seed: int = 0) -> None:
    """Reset env to an empty table, then place 5 cm cubes at (x, y, z_centre, yaw) and settle."""
    env.task_def = dataclasses.replace(env.task_def, num_objects=0)
    env.reset(seed)
    for x, y, z, yaw in cubes:
        body = spawn_object(env.scene.client, ObjectSpec("cube", RED, (x, y, z), _quat_yaw(yaw)))
        env.scene.add_object(body)
    env.scene.settle(240)
    env.obs = env._observe()
    env.depth_start = env.obs.depth_hm
    env.progress = env._progress(env.obs.depth_hm)


@pytest.fixture(scope="module")
def env():
    e = _env()
    yield e
    e.close()


def test_sim_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="sim.push_distance_m"):
        SimConfig(push_distance_m=-1.0)
    with pytest.raises(ConfigError, match="sim.robot"):
        SimConfig(robot="hexapod")


def test_cube_reads_5cm_in_the_heightmap_at_its_pixels(env):
    x, y = 0.5631, -0.0717
    _scene_with_cubes(env, [(x, y, CUBE_SIZE_M / 2, 0.0)])
    row, col = position_to_pixel(x, y, WS)
    patch = env.obs.depth_hm[row - 8:row + 9, col - 8:col + 9]  # well inside the 25 x 25 px top face
    assert np.all(np.abs(patch - 0.050) <= 0.003), (patch.min(), patch.max())
    far = env.obs.depth_hm[row - 8:row + 9, col + 30:col + 47]  # 6 cm beside it: bare table
    assert np.all(far < 0.003)
    occupied = np.argwhere(env.obs.depth_hm > 0.025)
    assert abs(occupied[:, 0].mean() - row) <= 1.5 and abs(occupied[:, 1].mean() - col) <= 1.5
    assert env.stack_height_gt() == 1 and env.stack_height_hm(env.obs.depth_hm) == 1


@pytest.mark.parametrize("height", [1, 2, 3, 4, 5])
def test_stack_height_from_heightmap_agrees_with_poses(env, height):
    cubes = [(0.5, 0.02, CUBE_SIZE_M * (k + 0.5) + 0.001 * k, 0.1) for k in range(height)]
    _scene_with_cubes(env, cubes)
    assert env.stack_height_gt() == height
    assert env.stack_height_hm(env.obs.depth_hm) == height


def test_place_on_a_cube_raises_the_stack_to_two(env):
    _scene_with_cubes(env, [(0.45, -0.1, 0.025, 0.3), (0.6, 0.1, 0.025, -0.2)])
    pick = oracle_action(env)
    assert pick.primitive == "pick"
    result = env.step(pick)
    assert result.success, result.detail
    assert env.holding and result.observation.holding
    place = oracle_action(env)
    assert place.primitive == "place"
    result = env.step(place)
    assert result.success, result.detail
    assert env.stack_height_gt() == 2 and result.info["stack_height_hm"] == 2
    assert result.progress_after == pytest.approx(2 / 5) and result.reward == pytest.approx(2 / 5)


def test_push_moves_the_object_it_touches(env):
    x, y = 0.5, 0.0
    _scene_with_cubes(env, [(x, y, 0.025, 0.0)])
    start = env.scene.pose(env.scene.objects[0])[0]
    row, col = position_to_pixel(x - 0.06, y, WS)  # 6 cm behind the cube, pushing along +x
    result = env.step(Action("push", row, col, 0.0, 1.0))
    moved = env.scene.pose(env.scene.objects[0])[0] - start
    assert result.success, result.detail
    assert moved[0] > 0.02 and abs(moved[1]) < 0.02


def test_unreachable_and_refused_actions_fail_with_a_reason(env):
    _scene_with_cubes(env, [(0.5, 0.0, 0.025, 0.0)])
    result = env.step(Action("pick", -3, 500, 0.0, 1.0))
    assert not result.success and result.detail == "out_of_workspace" and not result.done
    result = env.step(Action("place", 100, 100, 0.0, 1.0))
    assert not result.success and result.detail == "not_holding"
    # The near corner at table height is beyond the Panda's top-down reach: a failed step, no exception.
    result = env.step(Action("pick", 0, 0, 0.0, 1.0))
    assert not result.success and result.detail in ("unreachable", "nothing_grasped")
    assert result.reward == 0.0


def test_episode_ends_after_max_consecutive_failures():
    with _env(max_consecutive_failures=2) as env:
        env.reset(3)
        first = env.step(Action("place", 10, 10, 0.0, 1.0))
        assert not first.done
        second = env.step(Action("place", 10, 10, 0.0, 1.0))
        assert second.done and second.done_reason == "consecutive_failures"
        with pytest.raises(RuntimeError):
            env.step(Action("place", 10, 10, 0.0, 1.0))


def test_episode_ends_at_the_step_limit():
    with _env(max_steps=1) as env:
        env.reset(4)
        result = env.step(Action("pick", -1, -1, 0.0, 1.0))
        assert result.done and result.done_reason == "step_limit"


def _poses_after(seed: int, actions: list[Action]) -> np.ndarray:
    with _env("clutter", object_set="cubes") as env:
        env.reset(seed)
        for a in actions:
            env.step(a)
        return np.concatenate([np.concatenate(env.scene.pose(b)) for b in env.scene.objects])


def test_same_seed_and_actions_give_the_same_outcome():
    actions = [Action("push", 112, 60, 0.3, 1.0), Action("pick", 100, 120, 1.0, 1.0)]
    a = _poses_after(7, actions)
    b = _poses_after(7, actions)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, _poses_after(8, []))


def test_oracle_picks_an_isolated_cube_in_at_least_9_of_10_seeds(env):
    successes = 0
    for seed in range(10):
        rng = np.random.default_rng(seed)
        x, y = rng.uniform(0.34, 0.67), rng.uniform(-0.17, 0.17)
        _scene_with_cubes(env, [(x, y, 0.025, rng.uniform(-math.pi, math.pi))], seed=seed)
        successes += env.step(oracle_action(env)).success
    assert successes >= 9
