"""The scripted clutter oracle on real PyBullet scenes: it grasps where the fingers come down on free floor,
pushes only when no object leaves them room, and after a failure tries another grasp instead of repeating."""

from __future__ import annotations

import pytest

from romannet.actor.sim.arrangements import default_cases
from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.oracle import oracle_action
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig

pytestmark = pytest.mark.timeout(120)


def _case_env(stem: str) -> SimEnv:
    case = next(p for p in default_cases() if p.stem == stem)
    # The Panda hand: these cases test pushing apart what its 8 cm opening cannot grasp.
    sim = SimConfig(hand="panda", case_file=str(case), settle_steps=120, case_jitter_m=0.0, case_jitter_deg=0.0,
                    max_steps=12)
    return SimEnv(task=TaskConfig(kind="arrangement"), sim=sim)


def test_a_row_of_touching_cubes_is_picked_across_the_row_without_a_push() -> None:
    # case_01: three 5 cm cubes side by side, and a lone cylinder. Closing across the row, both fingers come
    # down on free floor, so every object comes out at the first try: four picks, no push.
    with _case_env("case_01") as env:
        env.reset(0)
        primitives, successes = [], []
        for _ in range(6):
            action = oracle_action(env)
            result = env.step(action)
            primitives.append(action.primitive)
            successes.append(result.success)
            if result.done:
                break
        assert result.done_reason == "done"
        assert primitives == ["pick"] * 4 and all(successes)


def test_a_packed_block_is_pushed_apart_once_the_lone_object_is_gone() -> None:
    # case_02: a 2 x 2 block of touching cubes, and a lone prism. Every cube has a neighbour under one finger
    # whichever way it closes, so after the prism the oracle pushes, then clears the rest.
    with _case_env("case_02") as env:
        env.reset(0)
        primitives = []
        for _ in range(10):
            action = oracle_action(env)
            primitives.append(action.primitive)
            result = env.step(action)
            if result.done:
                break
        assert primitives[0] == "pick" and "push" in primitives[1:3]
        assert result.done_reason == "done"


def test_after_a_failure_the_oracle_tries_another_action() -> None:
    with SimEnv(task=TaskConfig(kind="clutter"), sim=SimConfig(num_objects=6, settle_steps=120)) as env:
        env.reset(4)
        first = oracle_action(env)
        env.consecutive_failures = 1  # as after a failed attempt in this very state
        second = oracle_action(env)
        assert (second.primitive, second.row, second.col, second.angle_rad) != \
            (first.primitive, first.row, first.col, first.angle_rad)
