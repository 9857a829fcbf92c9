"""`sim.robot = "gripper"`: a floating Panda hand moved by a fixed constraint (no arm, no IK).

The same hand, fingers, friction and fingertip frame as the arm (robot.Hand), and the same primitives, but
the hand's base is pulled along the commanded Cartesian path by a force-limited PyBullet constraint
instead of an arm's joints. Faster (no IK, no arm dynamics), reaches everywhere (no "unreachable"
failures inside the workspace), and a grasp still fails for physical reasons (finger contacts). Frames
and angles as in robot.py. The URDF is the Panda URDF's hand subtree, written once to a temporary file.
"""

from __future__ import annotations

import logging
import math
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data

from romannet.common.config_sim import SimConfig

from .robot import REACHED_TOL_M, YAW_SPEED_RADPS, Hand, hand_yaw_from
from .scene import StepBudget

log = logging.getLogger(__name__)

HOME_TIP_M = (0.307, 0.0, 0.474)  # where the arm's home pose puts the fingertips: outside the camera's view
CONSTRAINT_FORCE_N = 300.0  # enough to carry the hand and a block, low enough to stop at a collision
GRIPPER_FINGER_JOINTS = (0, 1)
GRIPPER_GRASP_LINK = 2


def hand_urdf_path() -> Path:
    """A URDF of the Panda hand alone (the panda.urdf subtree from panda_hand down, absolute mesh paths)."""
    src = Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"
    text = src.read_text()
    body = text[text.index('<link name="panda_hand">'):text.rindex("</robot>")]
    body = body.replace("package://meshes", str(src.parent / "meshes"))
    out = Path(tempfile.gettempdir()) / "romannet_panda_hand.urdf"
    urdf = f'<?xml version="1.0"?>\n<robot name="panda_hand">\n{body}</robot>\n'
    if not out.exists() or out.read_text() != urdf:
        tmp = out.with_suffix(f".{id(urdf)}.tmp")  # written then renamed: parallel actors never read half
        tmp.write_text(urdf)
        tmp.replace(out)
    return out


def _top_down(yaw: float) -> tuple[float, ...]:
    return p.getQuaternionFromEuler((math.pi, 0.0, yaw))


class FloatingGripper(Hand):
    """The Panda hand without the arm; see the module docstring."""

    finger_joints = GRIPPER_FINGER_JOINTS
    grasp_link = GRIPPER_GRASP_LINK

    def __init__(self, client: int, sim: SimConfig):
        self.client, self.sim = client, sim
        self.body_id = p.loadURDF(str(hand_urdf_path()), HOME_TIP_M, _top_down(0.0), useFixedBase=False,
                                  physicsClientId=client)
        self._setup_fingers()
        self.tip_offset_m = self._measure_tip_offset()
        base_z = p.getBasePositionAndOrientation(self.body_id, physicsClientId=client)[0][2]
        self._base_above_tip_m = float(base_z - self.tip_position()[2])  # the hand is top-down
        self._constraint = p.createConstraint(self.body_id, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                              HOME_TIP_M, physicsClientId=client)
        self.reset()

    def _base_target(self, tip_m: np.ndarray) -> list[float]:
        return [float(tip_m[0]), float(tip_m[1]), float(tip_m[2] + self._base_above_tip_m)]

    def _command(self, tip_m: np.ndarray, yaw: float) -> None:
        p.changeConstraint(self._constraint, self._base_target(tip_m), _top_down(yaw),
                           maxForce=CONSTRAINT_FORCE_N, physicsClientId=self.client)

    def reset(self) -> None:
        """Teleport home with the gripper open: episode start, and an empty hand's way home (primitives.py)."""
        home = np.array(HOME_TIP_M)
        p.resetBasePositionAndOrientation(self.body_id, self._base_target(home), _top_down(0.0),
                                          physicsClientId=self.client)
        for j in self.finger_joints:
            p.resetJointState(self.body_id, j, self.sim.finger_travel_m, physicsClientId=self.client)
        self._command(home, 0.0)
        self.set_fingers(closed=False)

    def move_tips(self, target_m: np.ndarray, closing_angle_rad: float, budget: StepBudget,
                  speed_mps: float | None = None, tol_m: float = REACHED_TOL_M,
                  stop: Callable[[], bool] | None = None) -> float:
        """Straight line to target_m (fingertips), top-down; returns the remaining distance (m). stop: a
        guard asked after every step; True holds the hand where it is and returns."""
        target = np.asarray(target_m, dtype=np.float64)
        speed = speed_mps or self.sim.max_speed_mps
        start = self.tip_position()
        yaw0 = self.current_hand_yaw()
        yaw1 = hand_yaw_from(yaw0, closing_angle_rad)
        dt = self.sim.time_step_s
        n = max(1, math.ceil(np.linalg.norm(target - start) / (speed * dt)),
                math.ceil(abs(yaw1 - yaw0) / (YAW_SPEED_RADPS * dt)))
        for i in range(1, n + 1):
            s = i / n
            self._command(start + (target - start) * s, yaw0 + (yaw1 - yaw0) * s)
            if not budget.step():
                break
            if self._guard(stop):
                return float(np.linalg.norm(self.tip_position() - target))
        return self._settle_at(target, budget, tol_m, stop)

    def _hold(self) -> None:
        self._command(self.tip_position(), self.current_hand_yaw())

    def go_home(self, budget: StepBudget) -> bool:
        """Up to the home height first (never sweep through the scene), then across to home."""
        tip = self.tip_position()
        yaw = self.current_hand_yaw() + math.pi / 2.0  # keep the current wrist yaw
        self.move_tips(np.array([tip[0], tip[1], HOME_TIP_M[2]]), yaw, budget)
        return self.move_tips(np.array(HOME_TIP_M), yaw, budget, tol_m=0.01) < 0.01

    def close(self) -> None:
        """Nothing to release: the hand goes with its scene."""
