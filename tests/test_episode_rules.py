"""The episode rules (common/episode_rules.py) on hand-made heightmaps, and the same recorded steps run
through the simulator's and the real robot's step code with identical judgements."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from romannet.actor.real.env import RealEnv
from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.oracle import oracle_action
from romannet.common.action import Action
from romannet.common.config import Config, RewardConfig, TaskConfig, load_config
from romannet.common.config_sim import SimConfig
from romannet.common.episode_rules import (
    Measure,
    clutter_progress,
    done_reason,
    goal_reached,
    ideal_actions,
    judge_step,
    measure,
    occupied_fraction,
    occupied_pixels,
    refusal,
    stacking_progress,
    step_reward,
)
from romannet.common.interfaces import MotionResult, Observation, StepResult

pytestmark = pytest.mark.timeout(300)

REWARD = RewardConfig()


# ------------------------------------------------------------------------------------------ refusal
def test_refusal_rules():
    prims = ("push", "pick")
    assert refusal(Action("pick", 3, 4, 0.0, 0.0), prims, False, (8, 8)) == ""
    assert refusal(Action("place", 3, 4, 0.0, 0.0), prims, True, (8, 8)) == "primitive_not_allowed"
    assert refusal(Action("place", 3, 4, 0.0, 0.0), ("pick", "place"), False, (8, 8)) == "not_holding"
    assert refusal(Action("pick", 3, 4, 0.0, 0.0), prims, True, (8, 8)) == "holding_object"
    assert refusal(Action("pick", 8, 0, 0.0, 0.0), prims, False, (8, 8)) == "out_of_workspace"
    assert refusal(Action("pick", 0, -1, 0.0, 0.0), prims, False, (8, 8)) == "out_of_workspace"


# ----------------------------------------------------------------------------------------- occupied
def test_occupied_pixels_count_heights_above_the_threshold_and_never_missing_readings():
    hm = np.zeros((224, 224), np.float32)
    assert occupied_pixels(hm, 0.01) == 0 and occupied_fraction(hm, 0.01) == 0.0
    hm[:56, :] = 0.02  # a quarter of the rows
    hm[100, 100] = 0.005  # below the threshold
    assert occupied_pixels(hm, 0.01) == 56 * 224
    assert occupied_fraction(hm, 0.01) == pytest.approx(0.25)
    hm[:2, :2] = [[np.nan, np.inf], [-np.inf, 0.02]]  # missing readings are empty, not occupied
    assert occupied_pixels(hm, 0.01) == 56 * 224 - 3
    assert occupied_fraction(np.full((4, 4), 0.3, np.float32), 0.01) == 1.0
    with pytest.raises(ValueError, match="2-D"):
        occupied_pixels(np.zeros(5), 0.01)


# ------------------------------------------------------------------------------------- task progress
def test_clutter_progress_is_the_removed_fraction_of_the_start_footprint():
    start = np.zeros((10, 10))
    start[:4, :] = 0.05  # 40 occupied pixels
    now = np.zeros((10, 10))
    now[:1, :] = 0.05  # 10 left
    assert clutter_progress(now, start, 0.01) == pytest.approx(0.75)
    assert clutter_progress(start, start, 0.01) == 0.0
    assert clutter_progress(np.zeros((10, 10)), start, 0.01) == 1.0


def test_clutter_progress_edge_cases():
    empty = np.zeros((8, 8))
    assert clutter_progress(empty, empty, 0.01) == 1.0  # nothing to remove: done
    start = np.zeros((8, 8))
    start[0, 0] = 0.05
    spread = np.full((8, 8), 0.05)
    assert clutter_progress(spread, start, 0.01) == 0.0  # footprint grew: clipped, never negative
    below = np.full((8, 8), 0.005)  # thin things under the threshold are floor, not clutter
    assert clutter_progress(below, start, 0.01) == 1.0
    with_nan = start.copy()
    with_nan[1, 1] = np.nan  # a missing depth reading is not an object
    with_nan[2, 2] = np.inf
    assert clutter_progress(with_nan, start, 0.01) == 0.0
    with pytest.raises(ValueError, match="shapes differ"):
        clutter_progress(np.zeros((4, 4)), np.zeros((8, 8)), 0.01)


def test_stacking_progress():
    assert stacking_progress(0.10, 0.20) == pytest.approx(0.5)
    assert stacking_progress(3, 4) == pytest.approx(0.75)  # cube counts work too
    assert stacking_progress(0.3, 0.2) == 1.0
    assert stacking_progress(-0.01, 0.2) == 0.0
    with pytest.raises(ValueError):
        stacking_progress(0.1, 0.0)
    with pytest.raises(ValueError):
        stacking_progress(float("nan"), 0.2)


def _cubes(*heights_m: float) -> np.ndarray:
    """A 64x64 heightmap (2 mm/px) with one 5 cm wide column per height, side by side."""
    hm = np.zeros((64, 64), np.float32)
    for i, h in enumerate(heights_m):
        hm[5:30, 2 + 30 * i:27 + 30 * i] = h
    return hm


def test_measure_reads_stack_height_occupied_share_and_the_tasks_progress():
    start = _cubes(0.05, 0.05)
    stacking = TaskConfig(kind="stacking", goal_stack_height=4)
    m = measure(_cubes(0.10), start, stacking, REWARD)
    assert m == Measure(stack_height=2, occupied=pytest.approx(25 * 25 / 64**2), progress=0.5)
    clutter = measure(_cubes(0.05), start, TaskConfig(kind="clutter"), REWARD)
    assert clutter.stack_height == 1 and clutter.progress == pytest.approx(0.5)  # half the footprint gone


# ------------------------------------------------------------------------------------- judging a step
def test_a_place_counts_only_when_the_measured_stack_grew():
    one, two = Measure(1, 0.1, 0.25), Measure(2, 0.1, 0.5)
    grew = judge_step("place", True, "", one, two, 3, REWARD)
    assert (grew.success, grew.detail, grew.consecutive_failures) == (True, "", 0)
    assert grew.reward == pytest.approx(REWARD.place_weight * 0.5)
    flat = judge_step("place", True, "", one, Measure(1, 0.1, 0.25), 3, REWARD)
    assert (flat.success, flat.detail, flat.reward, flat.consecutive_failures) == (False, "stack_not_higher", 0.0, 4)
    pick = judge_step("pick", True, "", one, one, 3, REWARD)  # other primitives keep what they reported
    assert pick.success and pick.reward == pytest.approx(REWARD.pick_weight * 0.25)
    refused = judge_step("place", False, "not_holding", one, two, 0, REWARD)
    assert (refused.success, refused.detail, refused.reward) == (False, "not_holding", 0.0)


def test_progress_reversed_beyond_the_tolerance_earns_nothing():
    cfg = dataclasses.replace(REWARD, progress_tolerance=0.02)
    assert step_reward("push", True, 0.5, 0.49, cfg) == pytest.approx(cfg.push_weight * 0.49)
    assert step_reward("push", True, 0.5, 0.4, cfg) == 0.0
    dropped = judge_step("pick", True, "", Measure(0, 0.2, 0.5), Measure(0, 0.3, 0.4), 0, cfg)
    assert dropped.success and dropped.reward == 0.0 and dropped.consecutive_failures == 0


def test_done_reasons_in_their_order():
    limits = SimConfig(max_steps=10, max_consecutive_failures=3)
    assert done_reason(True, 3, 10, limits, unstable="object fell") == "unstable"
    assert done_reason(True, 3, 10, limits) == "done"
    assert done_reason(False, 3, 10, limits) == "consecutive_failures"
    assert done_reason(False, 2, 10, limits) == "step_limit"
    assert done_reason(False, 2, 9, limits) == ""
    stacking, clutter = TaskConfig(kind="stacking", goal_stack_height=3), TaskConfig(kind="clutter")
    assert goal_reached(stacking, 3, False) and not goal_reached(stacking, 2, True)
    assert goal_reached(clutter, 0, True) and not goal_reached(clutter, 5, False)


def test_ideal_actions_are_objects_for_removal_and_two_per_added_cube_for_stacking():
    assert ideal_actions("clutter", 30, 4) == 30
    assert ideal_actions("arrangement", 6, 4) == 6
    assert ideal_actions("clutter", 0, 4) == 0  # completed by pushing everything out: no pick was needed
    assert [ideal_actions("stacking", 0, h) for h in (2, 3, 4, 5)] == [2, 4, 6, 8]
    with pytest.raises(ValueError, match="at least 2"):
        ideal_actions("stacking", 10, 1)
    with pytest.raises(ValueError, match="negative"):
        ideal_actions("clutter", -1, 4)
    with pytest.raises(ValueError, match="unknown task"):
        ideal_actions("sorting", 3, 4)


# ------------------------------------------------------------------- the same steps, sim and real
SETS = ["workspace.resolution_m=0.007", 'sim.robot="gripper"', "sim.num_objects=4", "sim.max_steps=12",
        "sim.max_consecutive_failures=4", "camera.width_px=160", "camera.height_px=120",
        "camera.fx_px=154.655", "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0",
        "task.goal_stack_height=3"]


REFUSALS = ("primitive_not_allowed", "not_holding", "holding_object", "out_of_workspace")


@dataclasses.dataclass(frozen=True)
class RecordedStep:
    action: Action
    result: StepResult


def _random_action(env: SimEnv, rng: np.random.Generator) -> Action:
    """Any primitive of the task (some are refused) at a random pixel."""
    return Action(str(rng.choice(env.primitives)), int(rng.integers(env.ws.height_px)),
                  int(rng.integers(env.ws.width_px)), float(rng.uniform(-math.pi, math.pi)), 0.0, explored=True)


def record_sim(cfg: Config, seed: int, random_share: float) -> tuple[Observation, list[RecordedStep]]:
    """One simulated episode: the oracle, with a share of random actions so that some fail, and a second
    action off the heightmap (refused)."""
    rng = np.random.default_rng(seed)
    with SimEnv.from_config(cfg) as env:
        first = env.reset(seed)
        steps: list[RecordedStep] = []
        while not steps or not steps[-1].result.done:
            action = _random_action(env, rng) if rng.random() < random_share else oracle_action(env)
            if len(steps) == 1:
                action = dataclasses.replace(action, row=env.ws.height_px)
            steps.append(RecordedStep(action, env.step(action)))
    return first, steps


class ScriptedRobot:
    """A robot whose primitives report what the simulator's did (the outcome before the episode rules)."""

    stopped = ""

    def __init__(self, steps: list[RecordedStep]):
        self.outcomes = [s for s in steps if s.result.detail not in REFUSALS]
        self.calls: list[str] = []
        self.held = False

    def _next(self, primitive: str) -> MotionResult:
        step = self.outcomes[len(self.calls)]
        assert step.action.primitive == primitive
        self.calls.append(primitive)
        r = step.result
        self.held = r.observation.holding
        executed = r.success or r.detail == "stack_not_higher"  # a place the rules then judged
        return MotionResult(executed, "" if executed else r.detail)

    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def go_home(self) -> MotionResult: return MotionResult(True)
    def holding(self) -> bool: return self.held
    def resume(self) -> bool: return True
    def push(self, x_m, y_m, z_m, angle_rad) -> MotionResult: return self._next("push")  # noqa: ANN001
    def pick(self, x_m, y_m, z_m, angle_rad) -> MotionResult: return self._next("pick")  # noqa: ANN001
    def place(self, x_m, y_m, z_m, angle_rad) -> MotionResult: return self._next("place")  # noqa: ANN001
    def drop(self, x_m, y_m, z_m) -> MotionResult: return MotionResult(True)  # noqa: ANN001


class RecordedHeightmaps(RealEnv):
    """RealEnv seeing the simulator's recorded heightmaps instead of a camera's."""

    def __init__(self, cfg: Config, first: Observation, steps: list[RecordedStep], robot: ScriptedRobot):
        super().__init__(cfg, robot, camera=None, T_base_cam=np.eye(4))  # type: ignore[arg-type]
        self.frames = iter([first] + [s.result.observation for s in steps])

    def observe(self, ws=None, holding: bool = False) -> Observation:  # noqa: ANN001
        obs = next(self.frames)
        return Observation(obs.color_hm, obs.depth_hm, holding)


def _verdict(r: StepResult) -> tuple:
    return (r.success, r.detail, r.progress_before, r.progress_after, r.reward, r.done, r.done_reason,
            r.info["consecutive_failures"], r.info["stack_height_hm"], r.observation.holding)


@pytest.mark.parametrize("task", ["clutter", "stacking"])
def test_the_same_recorded_steps_get_the_same_judgements_in_the_simulator_and_on_a_real_robot(task):
    cfg = load_config(None, [*SETS, f'task.kind="{task}"'])
    covered: set[str] = set()
    for seed in range(3):
        first, steps = record_sim(cfg, seed, random_share=0.4)
        robot = ScriptedRobot(steps)
        real = RecordedHeightmaps(cfg, first, steps, robot)
        real.reset(seed)
        for s in steps:
            got = real.step(s.action)
            assert _verdict(got) == _verdict(s.result), f"seed {seed}, step {s.result.info['step']}"
            covered |= {"success" if s.result.success else s.result.detail or "failed", s.result.done_reason}
            if s.result.reward > 0:
                covered.add("reward")
        assert len(robot.calls) == len(robot.outcomes)  # every executed primitive, no more
    # The comparison covered rewarded successes, failures, refusals and ends of episodes.
    assert {"success", "reward", "done"} <= covered
    assert covered & set(REFUSALS)
    assert covered - set(REFUSALS) - {"success", "reward", "done", "", "step_limit", "consecutive_failures"}
