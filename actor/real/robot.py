"""CartesianRobot: the paper's primitives and the safety layer over any arm that can do linear TCP moves.

A concrete arm (ur.py) supplies five low-level operations: `_move_linear` (a blocking linear move),
`_stop_reason` (is the controller in a protective / emergency stop?), `_set_tool` (vacuum or fingers),
`_grasp_sensed` (vacuum sensor / finger width), and the connection lifecycle. Everything else is here, so
every arm gets the same guarantees:

- every commanded pose is clamped into the safety box and every speed/acceleration capped (safety.py);
- every move is followed by a stop check; a protective or emergency stop ends the primitive as failed,
  sets `stopped`, and from then on every motion is refused until `resume()` finds the controller ready
  again after an operator has cleared the stop (nothing is retried by itself);
- a failed move (unreachable pose, ...) ends the primitive as failed and sends the arm home.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod

import numpy as np

from romannet.common.config_robot import RobotConfig
from romannet.common.interfaces import MotionResult

from .motion import (
    Waypoint,
    descend_plan,
    fold_angle,
    lift_plan,
    pick_tool_z,
    place_tool_z,
    push_plan,
    tool_rotvec,
)
from .safety import SafetyBox, cap_motion, clamp_pose

log = logging.getLogger(__name__)


class _Stopped(Exception):
    """Internal: the controller stopped during a move (or was stopped before it)."""


class _MoveFailed(Exception):
    """Internal: the controller refused or did not complete a move, without a stop."""


class CartesianRobot(ABC):
    """The Robot interface (common.interfaces.Robot) on top of linear TCP moves; see the module docstring."""

    def __init__(self, cfg: RobotConfig):
        self.cfg = cfg
        self.box = SafetyBox.from_config(cfg)
        self.stopped = ""
        self.clamped_moves = 0  # how many commanded poses the safety box changed (status, tests)

    # ------------------------------------------------------------------------------ for subclasses
    @abstractmethod
    def connect(self) -> None: ...

    @abstractmethod
    def disconnect(self) -> None: ...

    @abstractmethod
    def tool_pose(self) -> np.ndarray: ...

    @abstractmethod
    def _move_linear(self, pose: np.ndarray, speed_mps: float, accel_mps2: float) -> bool:
        """Blocking linear move; False if the controller refused or did not complete it."""

    @abstractmethod
    def _stop_reason(self) -> str:
        """"" if the controller may move, else why not ("protective_stop", "emergency_stop", ...)."""

    @abstractmethod
    def _set_tool(self, active: bool) -> None:
        """Vacuum on / fingers closed (True), or vacuum off / fingers open (False); waits for it to act."""

    @abstractmethod
    def _grasp_sensed(self) -> bool:
        """The hardware's grasp signal: vacuum sensor, or fingers stopped wider than empty."""

    @abstractmethod
    def _controller_ready(self) -> str:
        """"" if the controller can take motion commands again after a stop was cleared, else why not."""

    def __enter__(self) -> CartesianRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    # ------------------------------------------------------------------------------------ motions
    def _move(self, pose, contact: bool = False) -> bool:
        """Clamp, cap, move, check for a stop. Returns whether the pose was clamped."""
        if self.stopped:
            raise _Stopped(self.stopped)
        target, clamped = clamp_pose(pose, self.box)
        if clamped:
            self.clamped_moves += 1
            log.warning("commanded TCP position %s is outside the safety box %s..%s: clamped to %s",
                        np.round(np.asarray(pose)[:3], 4).tolist(), self.box.low, self.box.high,
                        np.round(target[:3], 4).tolist())
        free, slow = self.cfg.speed_cap
        speed, accel = cap_motion(slow if contact else free, self.cfg.accel_mps2, self.box)
        ok = self._move_linear(target, speed, accel)
        reason = self._stop_reason()
        if reason:
            self.stopped = reason
            log.error("robot stopped during a move to %s: %s. The actor pauses; no motion is retried. Clear the "
                      "stop on the teach pendant and make the cell safe before resuming.",
                      np.round(target[:3], 4).tolist(), reason)
            raise _Stopped(reason)
        if not ok:
            raise _MoveFailed(f"the controller did not complete the move to {np.round(target, 4).tolist()}")
        return clamped

    def _run(self, plan: list[Waypoint]) -> bool:
        clamped = False
        for wp in plan:
            clamped |= self._move(wp.pose, wp.contact)
        return clamped

    def _primitive(self, name: str, body) -> MotionResult:
        """Run body() (which returns (success, reason, clamped)); turn stops and failed moves into results."""
        try:
            success, reason, clamped = body()
        except _Stopped as stop:
            return MotionResult(False, str(stop), stopped=str(stop))
        except _MoveFailed as err:
            log.warning("%s failed: %s", name, err)
            try:
                self._release_and_home()
            except (_Stopped, _MoveFailed) as again:
                log.error("could not return home after a failed %s: %s", name, again)
                if self.stopped:
                    return MotionResult(False, self.stopped, stopped=self.stopped)
            return MotionResult(False, "motion_failed")
        return MotionResult(success, reason, clamped)

    def _release_and_home(self) -> None:
        if not self._grasp_sensed():
            self._set_tool(False)
        self._move(self.home)

    @property
    def home(self) -> tuple[float, ...]:
        return tuple(self.cfg.home_pose)

    def move_to(self, pose) -> MotionResult:
        """One linear free-space move of the TCP (clamped); used by calibration."""
        return self._primitive("move", lambda: (True, "", self._move(pose)))

    def go_home(self) -> MotionResult:
        return self._primitive("home", lambda: (True, "", self._move(self.home)))

    def push(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        def body():
            self._set_tool(self.cfg.tool == "gripper")  # fingers closed to push; the vacuum stays off
            clamped = self._run(push_plan(x_m, y_m, z_m, angle_rad, self.cfg))
            if self.cfg.tool == "gripper":
                self._set_tool(False)
            clamped |= self._move(self.home)
            return True, "", clamped
        return self._primitive("push", body)

    def pick(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        def body():
            if self.cfg.tool == "suction":
                self._set_tool(True)  # vacuum on before contact: the cup seals as it touches
            else:
                self._set_tool(False)
            clamped = self._run(descend_plan(x_m, y_m, pick_tool_z(z_m, self.cfg), angle_rad, self.cfg))
            if self.cfg.tool == "gripper":
                self._set_tool(True)
            lift_z = self.box.low[2] + self.cfg.lift_height_m
            clamped |= self._run(lift_plan(x_m, y_m, max(lift_z, z_m + self.cfg.approach_height_m),
                                           angle_rad, self.cfg))
            clamped |= self._move(self.home)
            held = self._grasp_sensed()
            if not held:
                self._set_tool(False)
            return held, "" if held else "nothing_grasped", clamped
        return self._primitive("pick", body)

    def place(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        def body():
            if not self._grasp_sensed():
                self._set_tool(False)
                return False, "dropped", False
            z_tool = place_tool_z(z_m, self.cfg)
            clamped = self._run(descend_plan(x_m, y_m, z_tool, angle_rad, self.cfg))
            self._set_tool(False)
            clamped |= self._run(lift_plan(x_m, y_m, z_tool + self.cfg.approach_height_m, angle_rad, self.cfg))
            clamped |= self._move(self.home)
            return True, "", clamped
        return self._primitive("place", body)

    def drop(self, x_m: float, y_m: float, z_m: float) -> MotionResult:
        def body():
            rv = tool_rotvec(fold_angle(0.0), self.cfg.tool_down_rotvec)
            clamped = self._move((x_m, y_m, z_m, *rv))
            self._set_tool(False)
            clamped |= self._move(self.home)
            return True, "", clamped
        return self._primitive("drop", body)

    def holding(self) -> bool:
        return self._grasp_sensed()

    def resume(self) -> bool:
        """After an operator cleared the stop: True (motion allowed again) if the controller is ready."""
        if not self.stopped:
            return True
        why = self._stop_reason() or self._controller_ready()
        if why:
            log.warning("robot still not ready (%s): stays paused", why)
            return False
        log.info("robot ready again after %s: resuming", self.stopped)
        self.stopped = ""
        return True
