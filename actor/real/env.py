"""RealEnv: a real robot and camera behind common.interfaces.Env, for the paper's real-world tasks.

Tasks (cfg.task.kind):
- "clutter" / "arrangement": bin picking with bin swapping. A successful pick is dropped into the other bin
  (robot.bins_xy_m lists two bins) or at robot.drop_xy_m (one workspace). The episode is done when the source
  bin is empty on the depth heightmap; the next reset swaps source and destination (the paper's real setup).
- "stacking": picked cubes stay in the tool until placed; the stack height is measured on the depth
  heightmap (common.stack), done at task.goal_stack_height. Reset waits for the operator to un-stack.

Success X comes from the hardware (vacuum sensor or finger width) for picks, from the depth heightmap for
places (the stack grew), and from the motion for pushes; the step is judged by the simulator's rules
(common.episode_rules: P, R_tp, the failure streak, sim.max_steps, sim.max_consecutive_failures), the task
complete when the heightmap says so (a stack of the goal's height, or less than robot.empty_occupied_fraction
of the bin occupied).

A protective or emergency stop ends the episode as "robot_stopped" (the failed action is recorded with
reward 0 and no new camera frame: the arm may be in view) and sets `paused`; the actor then waits for an
operator, and `try_resume()` lets the robot move again only once the controller is ready.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from romannet.common.action import (
    PLACE_PATCH_RADIUS_M,
    PUSH_PATCH_RADIUS_M,
    Action,
    patch_max,
    pixel_to_position,
    place_position,
)
from romannet.common.config import Config, WorkspaceConfig
from romannet.common.episode_rules import (
    Measure,
    done_reason,
    goal_reached,
    judge_step,
    measure,
    occupied_fraction,
    refusal,
)
from romannet.common.errors import RobotError
from romannet.common.heightmap import get_heightmaps
from romannet.common.interfaces import Camera, MotionResult, Observation, Robot, StepResult
from romannet.common.stack import stack_height

log = logging.getLogger(__name__)

RESET_POLL_S = 2.0


def bin_workspaces(cfg: Config) -> list[WorkspaceConfig]:
    """The heightmap workspace of each bin ([workspace]'s size at each robot.bins_xy_m corner), or [workspace]."""
    ws = cfg.workspace
    if not cfg.robot.bins_xy_m:
        return [ws]
    dx, dy = ws.x_max_m - ws.x_min_m, ws.y_max_m - ws.y_min_m
    return [dataclasses.replace(ws, x_min_m=x, x_max_m=x + dx, y_min_m=y, y_max_m=y + dy)
            for x, y in cfg.robot.bins_xy_m]


class RealEnv:
    """See the module docstring. Owns the robot and the camera: connect() both, close() releases both."""

    def __init__(self, cfg: Config, robot: Robot, camera: Camera, T_base_cam: np.ndarray, depth_scale: float = 1.0):
        self.cfg, self.robot, self.camera = cfg, robot, camera
        self.T_base_cam = np.asarray(T_base_cam, dtype=np.float64)
        self.depth_scale = float(depth_scale)
        self.primitives: tuple[str, ...] = cfg.task.primitives
        self.workspaces = bin_workspaces(cfg)
        self.source = 0  # index of the bin picked from
        self.paused = ""
        self.stacking = cfg.task.kind == "stacking"
        self._episode_over = True
        self.seed = -1

    @property
    def ws(self) -> WorkspaceConfig:
        return self.workspaces[self.source]

    def connect(self) -> None:
        self.robot.connect()
        try:
            self.camera.connect()
        except BaseException:
            self.robot.disconnect()
            raise

    def close(self) -> None:
        """Disconnect the robot and the camera. Idempotent."""
        try:
            self.robot.disconnect()
        finally:
            self.camera.disconnect()

    # ----------------------------------------------------------------------------------- observing
    def observe(self, ws: WorkspaceConfig | None = None, holding: bool = False) -> Observation:
        frame = self.camera.capture()
        depth_m = frame.depth_m * np.float32(self.depth_scale)
        color_hm, depth_hm = get_heightmaps(frame.color, depth_m, frame.intrinsics, self.T_base_cam, ws or self.ws)
        return Observation(color_hm, depth_hm, holding, frame.color, depth_m)

    def _empty(self, obs: Observation) -> bool:
        return occupied_fraction(obs.depth_hm, self.cfg.reward.occupied_height_m) < self.cfg.robot.empty_occupied_fraction

    def _measure(self, obs: Observation) -> Measure:
        """Stack height (cubes), occupied share and P of a new observation, measured once."""
        return measure(obs.depth_hm, self.depth_start, self.cfg.task, self.cfg.reward)

    # ------------------------------------------------------------------------------------- episodes
    def reset(self, seed: int | None = None) -> Observation:
        """Home, then a first observation of a scene worth an episode (waiting for the operator if needed).

        seed only labels the episode (a real scene is what it is)."""
        if self.robot.stopped:
            raise RobotError(f"the robot is stopped ({self.robot.stopped}): clear it and resume first")
        self.seed = -1 if seed is None else int(seed)
        home = self.robot.go_home()
        if home.stopped:
            self.paused = (f"the robot stopped ({home.stopped}) moving home before an episode; the actor will not "
                           "move it until an operator has cleared the stop and resumed the actor")
            raise RobotError(self.paused)
        if not home.success:
            raise RobotError(f"cannot move the robot home before an episode: {home.reason}")
        if self.robot.holding():
            raise RobotError("the tool still holds an object at the start of an episode: remove it")
        obs = self._ready_observation()
        self.depth_start = obs.depth_hm
        self.measured = self._measure(obs)
        self.obs, self.holding, self.steps, self.consecutive_failures = obs, False, 0, 0
        self._episode_over = False
        return obs

    def _scene_problem(self, obs: Observation) -> str:
        if self.stacking:
            h = stack_height(obs.depth_hm, self.cfg.task.cube_size_m)
            return f"a stack of {h} cubes stands in the workspace: un-stack the cubes" if h >= 2 else ""
        return "the bin is empty: put objects in it" if self._empty(obs) else ""

    def _ready_observation(self) -> Observation:
        waited, deadline = False, self.cfg.robot.reset_wait_s
        started = time.monotonic()
        while True:
            obs = self.observe()
            problem = self._scene_problem(obs)
            if problem and not self.stacking and len(self.workspaces) == 2:
                other = self.observe(self.workspaces[1 - self.source])
                if not self._empty(other):  # swap: the full bin becomes the source
                    self.source = 1 - self.source
                    log.info("source bin empty: swapped bins, now picking from bin %d", self.source)
                    return other
                problem = "both bins are empty: put objects in one"
            if not problem:
                if waited:
                    log.info("scene ready after %.0f s", time.monotonic() - started)
                return obs
            if deadline and time.monotonic() - started > deadline:
                raise RobotError(f"waited {deadline:.0f} s at reset: {problem}")
            if not waited:
                log.warning("waiting for the operator before the next episode: %s", problem)
                waited = True
            time.sleep(RESET_POLL_S)

    # ---------------------------------------------------------------------------------------- steps
    def _execute(self, action: Action) -> MotionResult:
        hm, ws, rc = self.obs.depth_hm, self.ws, self.cfg.robot
        x, y, z = pixel_to_position(action.row, action.col, hm, ws)
        if action.primitive == "push":
            top = patch_max(hm, action.row, action.col, PUSH_PATCH_RADIUS_M, ws.resolution_m)
            return self.robot.push(x, y, ws.z_min_m + top + rc.push_clearance_m, action.angle_rad)
        if action.primitive == "pick":
            result = self.robot.pick(x, y, z, action.angle_rad)
            if result.success and not self.stacking:  # bin picking: into the destination bin
                dx, dy = self._drop_xy()
                dropped = self.robot.drop(dx, dy, ws.z_min_m + rc.drop_height_m)
                if dropped.stopped:
                    return dropped
            return result
        top = patch_max(hm, action.row, action.col, PLACE_PATCH_RADIUS_M, ws.resolution_m)
        x, y = place_position(hm, action.row, action.col, ws, self.cfg.task.cube_size_m,
                              self.cfg.task.place_on_top_centre)
        return self.robot.place(x, y, ws.z_min_m + top, action.angle_rad)

    def _drop_xy(self) -> tuple[float, float]:
        if len(self.workspaces) == 2:
            dest = self.workspaces[1 - self.source]
            return (dest.x_min_m + dest.x_max_m) / 2, (dest.y_min_m + dest.y_max_m) / 2
        return self.cfg.robot.drop_xy_m

    def step(self, action: Action) -> StepResult:
        """Execute one primitive; failures come back as success False, a stop as done "robot_stopped"."""
        if self._episode_over:
            raise RuntimeError("the episode is over (or never started): call reset() first")
        self.steps += 1
        before = self.measured
        reason = refusal(action, self.primitives, self.holding, self.obs.depth_hm.shape)
        result = MotionResult(False, reason) if reason else self._execute(action)
        if result.stopped:
            return self._stopped(action, result, before.progress)
        if action.primitive == "pick" and not reason:
            self.holding = self.stacking and result.success and self.robot.holding()
        if action.primitive == "place" and not reason:
            self.holding = self.robot.holding()
        self.obs = self.observe(holding=self.holding)
        self.measured = after = self._measure(self.obs)
        judged = judge_step(action.primitive, result.success, result.reason, before, after,
                            self.consecutive_failures, self.cfg.reward)
        self.consecutive_failures = judged.consecutive_failures
        empty = after.occupied < self.cfg.robot.empty_occupied_fraction
        ended = done_reason(goal_reached(self.cfg.task, after.stack_height, empty), self.consecutive_failures,
                            self.steps, self.cfg.sim)
        self._episode_over = bool(ended)
        info = {"episode_seed": self.seed, "step": self.steps, "bin": self.source, "clamped": result.clamped,
                "stack_height_hm": after.stack_height, "occupied_fraction": after.occupied,
                "consecutive_failures": self.consecutive_failures}
        return StepResult(self.obs, judged.success, judged.progress_before, judged.progress_after, judged.reward,
                          bool(ended), ended, judged.detail, info)

    def _stopped(self, action: Action, result: MotionResult, p_before: float) -> StepResult:
        self._episode_over = True
        self.paused = (f"the robot stopped ({result.stopped}) during a {action.primitive}; the actor will not move it "
                       "until an operator has cleared the stop on the teach pendant and resumed the actor")
        log.error(self.paused)
        info = {"episode_seed": self.seed, "step": self.steps, "bin": self.source, "stopped": result.stopped}
        return StepResult(self.obs, False, p_before, p_before, 0.0, True, "robot_stopped", result.stopped, info)

    def camera_pose(self) -> tuple[np.ndarray, None]:
        """Env: the calibrated camera-to-base pose; the device reports its intrinsics with each frame."""
        return self.T_base_cam, None

    def try_resume(self) -> bool:
        """After an operator's resume request: True (pause lifted) if the robot can move again."""
        if not self.paused:
            return True
        if not self.robot.resume():
            return False
        self.paused = ""
        return True
