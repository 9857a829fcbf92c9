"""The simulated tasks as Gymnasium environments (romannet.gym_env), on real PyBullet with small scenes:
Gymnasium's own env checker, an oracle episode on Stacking, seeding, and the action conversion."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import romannet.gym_env  # noqa: F401  (registers the ids)
from romannet.actor.sim.oracle import oracle_action
from romannet.common.action import Action

# A 64 x 64 heightmap (0.007 m/px), a 160 x 120 camera and the floating hand: ~0.1 s a step.
SMALL = ['sim.robot="gripper"', "sim.num_objects=3", "sim.num_stacking_cubes=3", "sim.max_steps=4",
         "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655", "camera.fy_px=154.655",
         "camera.cx_px=80.0", "camera.cy_px=60.0"]


def make(name: str, *extra: str, **kwargs) -> gymnasium.Env:
    return gymnasium.make(f"romannet/{name}-v0", overrides=[*SMALL, *extra], heightmap_px=64, **kwargs)


@pytest.mark.parametrize("name", ["Clutter", "Stacking", "Arrangement"])
def test_gymnasium_env_checker_passes_without_warnings(name):
    env = make(name, render_mode="rgb_array")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env.unwrapped)
        assert not [str(w.message) for w in caught if issubclass(w.category, UserWarning)]  # gymnasium's
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        assert obs["color"].shape == (64, 64, 3) and obs["depth"].shape == (64, 64) and obs["holding"] == 0
        assert env.render().shape == (120, 160, 3)
    finally:
        env.close()


def test_spaces_follow_the_task_and_the_sizes():
    with make("Stacking") as env:
        base = env.unwrapped
        assert base.primitives == ("push", "pick", "place")
        assert list(env.action_space.nvec) == [3, 64, 64, 16]
        assert env.observation_space["depth"].high.max() == pytest.approx(0.4)
    with make("Clutter", "task.use_push=false") as env:
        assert list(env.action_space.nvec) == [1, 64, 64, 16]


def test_oracle_episode_on_stacking_terminates_with_the_stack_built():
    with make("Stacking", "task.goal_stack_height=3", "sim.max_steps=10") as env:
        env.reset(seed=2)
        base = env.unwrapped
        total, rewards = 0.0, []
        for _ in range(10):
            obs, reward, terminated, truncated, info = env.step(base.encode(oracle_action(base.sim)))
            rewards.append(reward)
            total += reward
            if terminated or truncated:
                break
        assert terminated and not truncated, info
        assert info["done_reason"] == "done" and info["is_success"] and info["progress"] == 1.0
        assert total > 0 and all(r >= 0 for r in rewards)
        assert obs["holding"] == 0


def test_step_limit_truncates_and_a_refused_action_is_a_failed_step():
    with make("Stacking") as env:
        env.reset(seed=0)
        place = env.unwrapped.encode(Action("place", 10, 10, 0.0, 0.0))  # with an empty hand: refused
        for step in range(4):
            obs, reward, terminated, truncated, info = env.step(place)
            assert reward == 0.0 and not info["success"] and info["detail"] == "not_holding"
            assert (terminated, truncated) == (False, step == 3)
        assert info["done_reason"] == "step_limit" and not info["is_success"]


def test_the_same_seed_gives_the_same_first_observation():
    with make("Clutter") as a, make("Clutter") as b:
        first, _ = a.reset(seed=7)
        again, _ = b.reset(seed=7)
        other, _ = a.reset(seed=8)
        for key in ("color", "depth"):
            np.testing.assert_array_equal(first[key], again[key])
        assert not np.array_equal(first["depth"], other["depth"])
        # No seed: drawn from the env's np_random, so a seeded sequence of resets repeats as well.
        a.reset(seed=3)
        b.reset(seed=3)
        np.testing.assert_array_equal(a.reset()[0]["depth"], b.reset()[0]["depth"])


def test_encode_decode_round_trip_and_angle_bins():
    with make("Stacking") as env:
        base = env.unwrapped
        act = base.decode([2, 5, 6, 4])
        assert (act.primitive, act.row, act.col) == ("place", 5, 6)
        assert act.angle_rad == pytest.approx(math.pi / 2)
        assert list(base.encode(act)) == [2, 5, 6, 4]
        assert base.encode(Action("pick", 1, 2, -0.2, 1.0))[3] == 15  # -11.5 deg: the bin at -22.5 deg
        assert env.action_space.contains(base.encode(Action("pick", 1, 2, -math.pi, 1.0)))


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="task"):
        romannet.gym_env.RoManNetEnv("sorting")
    with pytest.raises(ValueError, match="render_mode"):
        romannet.gym_env.RoManNetEnv("clutter", render_mode="human")


def test_make_with_the_module_prefix_needs_no_import():
    code = ("import gymnasium; env = gymnasium.make('romannet.gym_env:romannet/Clutter-v0', heightmap_px=64, "
            "overrides=['sim.robot=\"gripper\"', 'sim.num_objects=2']); print(env.reset(seed=0)[0]['depth'].shape)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "(64, 64)" in out.stdout
