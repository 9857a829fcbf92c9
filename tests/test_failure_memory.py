"""The failure memory: a policy that does not repeat a failed action on a scene the failure did not change."""

from __future__ import annotations

import numpy as np
import pytest
from _learner_helpers import SMALL_MODEL

from romannet.common.action import Action
from romannet.common.config import Config, ExplorationConfig, RewardConfig, TaskConfig
from romannet.common.configbase import ConfigError
from romannet.common.failure_memory import FailureMemory, failure_masks, masked_q
from romannet.common.model import RoManNet
from romannet.common.policy import decide

SHAPE = (32, 32)


def _pick(row: int, col: int) -> Action:
    return Action("pick", row, col, 0.0, 0.5)


def test_failure_masks_exclude_a_disc_around_each_failure_of_the_same_primitive() -> None:
    masks = failure_masks([("pick", 10, 10), ("push", 20, 20)], ("push", "pick"), SHAPE, radius_px=3)
    assert masks is not None
    pick, push = masks["pick"], masks["push"]
    assert not pick[10, 10] and not pick[13, 10] and pick[14, 10]  # within 3 px: out; 4 px: in
    assert not pick[12, 12] and pick[13, 13]  # the disc is round: 2.83 px in, 4.24 px out
    assert pick[20, 20] and not push[20, 20] and push[10, 10]  # each primitive avoids only its own failures
    assert (~pick).sum() == (~push).sum() == 29  # pixels within a radius of 3


def test_nothing_to_avoid_gives_none_and_a_map_never_loses_every_pixel() -> None:
    assert failure_masks([], ("pick",), SHAPE, 5) is None
    assert failure_masks([("pick", 1, 1)], ("pick",), SHAPE, 0) is None  # off
    assert failure_masks([("place", 1, 1)], ("pick",), SHAPE, 5) is None  # no failure of a net that runs
    everything = failure_masks([("pick", 16, 16)], ("pick",), SHAPE, 100)
    assert everything is None  # the disc covers the map: the policy must still act, so nothing is avoided


def test_masked_q_sinks_the_masked_pixels_below_every_other_and_stays_finite() -> None:
    q = np.random.default_rng(0).random(SHAPE).astype(np.float32)
    q[0, 0] = 5.0  # the raw argmax lies in the masked region
    mask = np.ones(SHAPE, bool)
    mask[:4, :4] = False
    mq = masked_q(q, mask)
    assert mq.dtype == q.dtype and np.isfinite(mq).all()
    assert mq.max() == q[mask].max() and (mq[~mask] < q[mask].min()).all()
    assert np.array_equal(mq[mask], q[mask])
    assert masked_q(q, np.ones(SHAPE, bool)) is q  # nothing masked: the map itself


def test_the_memory_holds_the_failures_since_the_last_success_of_an_episode() -> None:
    memory = FailureMemory(radius_px=2)
    memory.record(_pick(5, 5), False)
    memory.record(_pick(9, 9), False)
    masks = memory.masks(("pick",), SHAPE)
    assert masks is not None and not masks["pick"][5, 5] and not masks["pick"][9, 9]
    memory.record(_pick(20, 20), True)  # a success changed the scene: what failed before may work now
    assert memory.masks(("pick",), SHAPE) is None
    memory.record(_pick(5, 5), False)
    memory.reset()  # a new episode
    assert memory.masks(("pick",), SHAPE) is None
    off = FailureMemory(radius_px=0)
    off.record(_pick(5, 5), False)
    assert off.failed == [] and off.masks(("pick",), SHAPE) is None


def _place(row: int, col: int) -> Action:
    return Action("place", row, col, 0.0, 1.0)


def test_taking_a_cube_off_the_stack_is_remembered_and_putting_it_back_clears_nothing() -> None:
    memory = FailureMemory(radius_px=2, track_progress=True)
    memory.record(_pick(30, 30), True, 0.25, 0.25)  # a cube off the table: P unchanged, a plain success
    memory.record(_place(10, 10), True, 0.25, 0.5)  # the stack grows: a new best
    memory.record(_pick(10, 10), True, 0.5, 0.25)  # the stack's top cube off again: P falls
    masks = memory.masks(("pick",), SHAPE)
    assert masks is not None and not masks["pick"][10, 10]
    memory.record(_place(10, 10), True, 0.25, 0.5)  # back on: only what was lost, so the pick stays avoided
    assert memory.masks(("pick",), SHAPE) is not None
    memory.record(_pick(30, 30), True, 0.5, 0.5)  # another cube off the table clears it, as any success
    assert memory.masks(("pick",), SHAPE) is None
    memory.record(_place(10, 10), True, 0.5, 0.75)  # past the best: a new stack height
    assert memory.best_progress == 0.75 and memory.failed == []


def test_progress_changes_within_the_tolerance_are_none_and_untracked_progress_is_ignored() -> None:
    stacking = FailureMemory.for_task(Config(task=TaskConfig(kind="stacking")))
    assert stacking.track_progress and stacking.tolerance == RewardConfig().progress_tolerance
    untracked = FailureMemory.for_task(Config(task=TaskConfig(kind="clutter")))  # any success clears
    untracked.record(_pick(5, 5), True, 0.50, 0.10)
    assert untracked.masks(("pick",), SHAPE) is None and untracked.best_progress is None
    memory = FailureMemory(radius_px=2, track_progress=True, tolerance=0.02)
    memory.record(_pick(5, 5), True, 0.50, 0.49)  # depth noise, not a reversal
    assert memory.masks(("pick",), SHAPE) is None
    memory.record(_pick(5, 5), True, 0.50, 0.40)
    assert memory.masks(("pick",), SHAPE) is not None
    memory.reset()
    assert memory.best_progress is None and memory.masks(("pick",), SHAPE) is None


def test_decide_does_not_choose_a_failed_pixel_again_and_its_maps_are_the_states() -> None:
    model = RoManNet(SMALL_MODEL, seed=0)
    depth = np.zeros(SHAPE, np.float32)
    color = np.zeros((*SHAPE, 3), np.uint8)
    cfg = ExplorationConfig(failure_memory_px=4)
    memory = FailureMemory(cfg.failure_memory_px)
    first, maps = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("pick",), cfg,
                         return_maps=True, avoid=memory)
    memory.record(first, False)
    second, maps2 = decide(model, color, depth, False, 0.0, np.random.default_rng(0), ("pick",), cfg,
                           return_maps=True, avoid=memory)
    # The same scene and weights: without the memory the greedy choice would be the same pixel.
    assert (second.row - first.row) ** 2 + (second.col - first.col) ** 2 > 4 ** 2
    assert np.array_equal(maps.q["pick"], maps2.q["pick"])  # V(s) still sees every pixel
    assert second.q_value < first.q_value  # the next best, outside the disc
    # Exploring draws outside the disc too.
    explored = [decide(model, color, depth, False, 1.0, np.random.default_rng(s), ("pick",), cfg, avoid=memory)
                for s in range(30)]
    assert all((a.row - first.row) ** 2 + (a.col - first.col) ** 2 > 4 ** 2 for a in explored)


def test_failure_memory_px_is_validated() -> None:
    with pytest.raises(ConfigError, match="failure_memory_px"):
        ExplorationConfig(failure_memory_px=-1)
    with pytest.raises(ConfigError, match="failure_memory_px"):
        ExplorationConfig(failure_memory_px=500)
