"""The simulated Franka Panda: inverse kinematics + position control through physics steps.

Frames and conventions
- World = robot base frame; the Panda's base is at the origin facing +x, on the table top (z = 0).
- The controlled point is the *fingertip centre*: the middle between the two finger pads at their lowest
  point, `tip_offset_m` below the URDF's `panda_grasptarget` link. Heights given to the motions are
  fingertip heights above the table, so "fingers go 3 cm below the pose" is literal.
- `closing_angle_rad` is the direction of the finger-closing axis in the world x-y plane, measured from +x
  toward +y: the `Action.angle_rad` convention of common.action. The gripper is top-down; a half turn gives
  the same grasp, so the hand yaw is folded into (-pi/2, pi/2] to stay far from joint 7's limits.

Every motion is bounded by a StepBudget (simulated steps, not wall-clock time) and reports how far the
fingertips ended from their target instead of raising: an unreachable target is a failed primitive.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data

from romannet.common.config_sim import SimConfig

from .scene import StepBudget, wrap_half_pi

log = logging.getLogger(__name__)

ARM_JOINTS = tuple(range(7))
FINGER_JOINTS = (9, 10)
GRASP_TARGET_LINK = 11
# The Panda's "ready" pose: fingertips at about (0.31, 0, 0.47) m, hand top-down, closing axis along y.
# Seen from the default camera (0.75 m above the workspace centre) the arm and anything it holds then
# project outside the workspace, so the camera sees the scene unoccluded (VPG also moves home to capture).
HOME_Q = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
ARM_FORCE_N = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)  # the URDF's joint effort limits
FINGER_OPEN_M = 0.04  # per finger: the Panda URDF's travel, an 8 cm gap fully open (sim.finger_travel_m's default)
JOINT_SPEED_RADPS = 2.0  # joint-space moves (going home); the Panda's limits are 2.175-2.61 rad/s
YAW_SPEED_RADPS = 3.0  # wrist rotation during Cartesian moves
COUPLING_FORCE_FACTOR = 5.0  # the finger coupling's strength, in multiples of one finger's squeezing force
REACHED_TOL_M = 0.003  # a motion has arrived when the fingertips are this close to the target
SETTLE_STEPS = 60
# Solves of the twin per IK target (each up to 20 of PyBullet's iterations), stopping at IK_TOL_M. Six left the
# descent to a top-down grasp within 6 cm of the workspace's near edge unsolved for about half the yaws,
# though every one of those poses has a solution: the oracle's picks failed there (tests/test_sim.py).
IK_ITERATIONS = 50
IK_TOL_M = 5e-4  # IK residual at which the twin stops refining
IK_FAIL_M = 0.01  # a residual above this means the pose is out of the arm's reach
IK_WAYPOINT_M = 0.02  # spacing of the IK-solved points along a straight move
YAW_MARGIN_RAD = 0.3  # a hand yaw may pass +-pi/2 by this much (joint 7 stays 0.2 rad inside its limits)
POSITION_GAIN = 0.3  # stiffer than PyBullet's 0.1: the fingertips settle within ~3 mm under gravity


def hand_yaw(closing_angle_rad: float) -> float:
    """Hand yaw (Euler z of a top-down hand, rad) whose finger-closing axis lies along closing_angle_rad.

    With the hand at Euler (pi, 0, psi) its y axis (the axis the fingers slide on) points along
    (sin psi, -cos psi), i.e. along closing angle psi + pi/2 (or psi - pi/2: the same axis).
    """
    return wrap_half_pi(closing_angle_rad - math.pi / 2.0)


def hand_yaw_from(yaw_now_rad: float, closing_angle_rad: float) -> float:
    """The hand yaw for closing_angle_rad that is the shortest turn from yaw_now_rad (the hand's yaw as it
    is, not folded), among the two half-turn-equivalent yaws within +-(pi/2 + YAW_MARGIN_RAD).

    Folding both ends into (-pi/2, pi/2] is not enough: a hand standing at pi/2 + 1e-4 reads -pi/2 + 1e-4
    folded, and a move to closing angle 0 (yaw pi/2) then turned the wrist half round, through poses the
    IK could not reach mid-move (a push at angle 0 stopped short and never pushed: measured).
    """
    base = hand_yaw(closing_angle_rad)
    candidates = [c for c in (base - math.pi, base, base + math.pi) if abs(c) <= math.pi / 2.0 + YAW_MARGIN_RAD]
    return min(candidates, key=lambda c: abs(c - yaw_now_rad))


class Hand:
    """What every simulated gripper shares: the Panda's two force-limited fingers and the fingertip frame.

    Subclasses set body_id, finger_joints, grasp_link (the URDF's panda_grasptarget) and tip_offset_m,
    and implement reset, move_tips, go_home and close.
    """

    client: int
    sim: SimConfig
    body_id: int
    finger_joints: tuple[int, int]
    grasp_link: int
    tip_offset_m: float

    def _setup_fingers(self) -> None:
        for link in self.finger_joints:
            # High friction pads: a 5 cm cube must not slip out during the lift.
            p.changeDynamics(self.body_id, link, lateralFriction=self.sim.finger_friction, spinningFriction=0.01,
                             frictionAnchor=True, physicsClientId=self.client)
            if self.sim.finger_travel_m != FINGER_OPEN_M:  # the URDF's limit stops the finger at 0.04 m
                p.changeDynamics(self.body_id, link, jointLowerLimit=0.0, jointUpperLimit=self.sim.finger_travel_m,
                                 physicsClientId=self.client)
        if self.sim.coupled_fingers:  # one mechanism (sim.coupled_fingers): finger positions kept equal
            a, b = self.finger_joints
            gear = p.createConstraint(self.body_id, a, self.body_id, b, jointType=p.JOINT_GEAR, jointAxis=[1, 0, 0],
                                      parentFramePosition=[0, 0, 0], childFramePosition=[0, 0, 0],
                                      physicsClientId=self.client)
            # The fingers' joint axes point opposite ways, so equal positions is a ratio of -1; ERP 0.5 and a
            # force 5x a finger's hold them within 1 mm of each other while both squeeze.
            p.changeConstraint(gear, gearRatio=-1, erp=0.5, maxForce=COUPLING_FORCE_FACTOR * self.sim.finger_force_n,
                               physicsClientId=self.client)

    def _measure_tip_offset(self) -> float:
        """How far the finger pads reach below the grasp-target frame (m, ~0.011), with the hand top-down."""
        grasp_z = p.getLinkState(self.body_id, self.grasp_link, computeForwardKinematics=1,
                                 physicsClientId=self.client)[4][2]
        tip_z = min(p.getAABB(self.body_id, f, physicsClientId=self.client)[0][2] for f in self.finger_joints)
        return float(grasp_z - tip_z)

    def tip_position(self) -> np.ndarray:
        """World position (m) of the fingertip centre."""
        pos = p.getLinkState(self.body_id, self.grasp_link, computeForwardKinematics=1,
                             physicsClientId=self.client)[4]
        return np.array(pos) - np.array([0.0, 0.0, self.tip_offset_m])

    def current_hand_yaw(self) -> float:
        """The hand's yaw as it stands (rad, (-pi, pi], not folded: see hand_yaw_from)."""
        orn = p.getLinkState(self.body_id, self.grasp_link, computeForwardKinematics=1,
                             physicsClientId=self.client)[5]
        return float(p.getEulerFromQuaternion(orn)[2])

    def finger_gap_m(self) -> float:
        """Distance between the finger pads (m): 2 * sim.finger_travel_m fully open, ~0 closed on nothing."""
        states = p.getJointStates(self.body_id, self.finger_joints, physicsClientId=self.client)
        return float(states[0][0] + states[1][0])

    def fingers_touching(self, body_id: int) -> bool:
        """Do both fingers have a contact with body_id (simulator ground truth)?"""
        return all(p.getContactPoints(self.body_id, body_id, linkIndexA=f, physicsClientId=self.client)
                   for f in self.finger_joints)

    def set_fingers(self, closed: bool) -> None:
        """Command both fingers: position control, force-limited so a grasp squeezes instead of crushing,
        speed-limited so a finger landing on an object's edge pushes it instead of throwing it."""
        target = 0.0 if closed else self.sim.finger_travel_m
        for joint in self.finger_joints:  # (setJointMotorControlArray takes no speed limit)
            p.setJointMotorControl2(self.body_id, joint, p.POSITION_CONTROL, targetPosition=target,
                                    force=self.sim.finger_force_n, maxVelocity=self.sim.finger_speed_mps,
                                    physicsClientId=self.client)

    def actuate_fingers(self, closed: bool, budget: StepBudget) -> None:
        """Close or open and step until the fingers stop moving (or a full stroke's time / the budget run out)."""
        self.set_fingers(closed)
        max_steps = math.ceil(self.sim.finger_travel_m / self.sim.finger_speed_mps / self.sim.time_step_s) + 60
        previous = self.finger_gap_m()
        for i in range(max_steps):
            if not budget.step():
                return
            if i % 10 == 9:
                gap = self.finger_gap_m()
                if abs(gap - previous) < 2e-4:
                    return
                previous = gap

    def _hold(self) -> None:
        """Command the pose the hand is in now (a guarded move stops here)."""
        raise NotImplementedError

    def _guard(self, stop: Callable[[], bool] | None) -> bool:
        """Ask a guarded move's stop(); when it answers True, hold where the hand is."""
        if stop is not None and stop():
            self._hold()
            return True
        return False

    def _settle_at(self, target: np.ndarray, budget: StepBudget, tol_m: float,
                   stop: Callable[[], bool] | None) -> float:
        """After a move's path: step until the fingertips are within tol_m of target (at most SETTLE_STEPS,
        the budget and the guard allowing); returns the remaining distance (m)."""
        for _ in range(SETTLE_STEPS):
            err = float(np.linalg.norm(self.tip_position() - target))
            if err < tol_m or not budget.step() or self._guard(stop):
                break
        return float(np.linalg.norm(self.tip_position() - target))

    def reset(self) -> None:
        raise NotImplementedError

    def move_tips(self, target_m: np.ndarray, closing_angle_rad: float, budget: StepBudget,
                  speed_mps: float | None = None, tol_m: float = REACHED_TOL_M,
                  stop: Callable[[], bool] | None = None) -> float:
        """Straight line to target_m; stop(), asked after every step, ends the move where the hand is (a
        guarded move). Returns the remaining distance (m) to the target."""
        raise NotImplementedError

    def go_home(self, budget: StepBudget) -> bool:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class PandaArm(Hand):
    """The Panda on the table: Cartesian fingertip moves through IK, fingers with force-limited closing."""

    finger_joints = FINGER_JOINTS
    grasp_link = GRASP_TARGET_LINK

    def __init__(self, client: int, sim: SimConfig):
        self.client, self.sim = client, sim
        self.body_id = p.loadURDF("franka_panda/panda.urdf", [0, 0, 0], [0, 0, 0, 1], useFixedBase=True,
                                  physicsClientId=client)
        lo, hi = [], []
        for j in range(p.getNumJoints(self.body_id, physicsClientId=client)):
            info = p.getJointInfo(self.body_id, j, physicsClientId=client)
            if info[2] != p.JOINT_FIXED:
                lo.append(info[8])
                hi.append(info[9])
        self._lower, self._upper = lo, hi
        self._ranges = [u - low for low, u in zip(lo, hi, strict=True)]
        self._setup_fingers()
        self.reset()
        self.tip_offset_m = self._measure_tip_offset()
        # The kinematic twin for IK (see _ik): a second client holding only the arm, never stepped.
        self._kin_client = p.connect(p.DIRECT)
        self._kin_body = p.loadURDF(str(Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"),
                                    [0, 0, 0], [0, 0, 0, 1], useFixedBase=True, physicsClientId=self._kin_client)

    def close(self) -> None:
        """Disconnect the IK twin's client. Idempotent (the arm itself goes with its scene)."""
        if self._kin_client >= 0:
            p.disconnect(physicsClientId=self._kin_client)
            self._kin_client = -1

    # ------------------------------------------------------------------------------------------ state
    def reset(self) -> None:
        """Teleport to the home pose with the gripper open (no physics): episode start, and the way home of
        an empty hand that touches nothing (primitives.py says why)."""
        for j, q in zip(ARM_JOINTS, HOME_Q, strict=True):
            p.resetJointState(self.body_id, j, q, physicsClientId=self.client)
        for j in FINGER_JOINTS:
            p.resetJointState(self.body_id, j, self.sim.finger_travel_m, physicsClientId=self.client)
        self._command_arm(HOME_Q)
        self.set_fingers(closed=False)

    def joint_positions(self) -> np.ndarray:
        states = p.getJointStates(self.body_id, ARM_JOINTS, physicsClientId=self.client)
        return np.array([s[0] for s in states])

    # ---------------------------------------------------------------------------------------- control
    def _command_arm(self, q: tuple[float, ...] | np.ndarray) -> None:
        p.setJointMotorControlArray(self.body_id, ARM_JOINTS, p.POSITION_CONTROL, targetPositions=list(q),
                                    forces=ARM_FORCE_N, positionGains=[POSITION_GAIN] * 7, physicsClientId=self.client)

    def _ik(self, tip_target: np.ndarray, yaw: float, seed_q: np.ndarray) -> tuple[np.ndarray, float]:
        """Joint angles putting the fingertips at tip_target, hand top-down at `yaw`; and the residual (m).

        Solved on a kinematic twin of the arm in a private PyBullet client: PyBullet's IK starts from the
        body's current joint state and one call stops millimetres short, so the twin is set to each answer
        and the solve repeated, without disturbing the physics of the real arm. A null-space solve (rest
        pose: home, joint 7 turned to the yaw) picks the elbow-up branch; plain solves then refine it.
        """
        c, body = self._kin_client, self._kin_body
        for j, q in zip(ARM_JOINTS, seed_q, strict=True):
            p.resetJointState(body, j, q, physicsClientId=c)
        rest = list(HOME_Q)
        rest[6] = HOME_Q[6] - yaw  # joint 7 turns the top-down hand about -z
        pos = (tip_target + np.array([0.0, 0.0, self.tip_offset_m])).tolist()
        orn = p.getQuaternionFromEuler((math.pi, 0.0, yaw))
        q = np.array(seed_q)
        err = math.inf
        for i in range(IK_ITERATIONS):
            extra = {} if i else {"lowerLimits": self._lower, "upperLimits": self._upper,
                                  "jointRanges": self._ranges, "restPoses": rest + [FINGER_OPEN_M] * 2}
            sol = p.calculateInverseKinematics(body, GRASP_TARGET_LINK, pos, orn, maxNumIterations=20,
                                               residualThreshold=1e-5, physicsClientId=c, **extra)
            q = np.clip(np.array(sol[:7]), self._lower[:7], self._upper[:7])
            for j, qj in zip(ARM_JOINTS, q, strict=True):
                p.resetJointState(body, j, qj, physicsClientId=c)
            reached = p.getLinkState(body, GRASP_TARGET_LINK, computeForwardKinematics=1, physicsClientId=c)[4]
            err = float(np.linalg.norm(np.array(reached) - pos))
            if err < IK_TOL_M:
                break
        return q, err

    def move_tips(self, target_m: np.ndarray, closing_angle_rad: float, budget: StepBudget,
                  speed_mps: float | None = None, tol_m: float = REACHED_TOL_M,
                  stop: Callable[[], bool] | None = None) -> float:
        """Move the fingertips along a straight line to target_m with the gripper top-down.

        The line is cut into waypoints (IK_WAYPOINT_M apart) solved by IK, and the joint targets are
        interpolated between them at the commanded speed. Returns the remaining distance (m) to the target
        after the path and a settling phase that stops once within tol_m (or when the budget is spent); an
        IK failure (the target out of reach) returns at once with the IK residual, before the arm moves.
        stop: a guard asked after every step; when it answers True the arm holds where it is and returns.
        """
        target = np.asarray(target_m, dtype=np.float64)
        speed = speed_mps or self.sim.max_speed_mps
        start = self.tip_position()
        yaw0 = self.current_hand_yaw()
        yaw1 = hand_yaw_from(yaw0, closing_angle_rad)
        dt = self.sim.time_step_s
        length = float(np.linalg.norm(target - start))
        n_way = max(1, math.ceil(length / IK_WAYPOINT_M), math.ceil(abs(yaw1 - yaw0) / 0.2))
        qs = [self.joint_positions()]
        for k in range(1, n_way + 1):
            s = k / n_way
            q, err = self._ik(start + (target - start) * s, yaw0 + (yaw1 - yaw0) * s, qs[-1])
            if err > IK_FAIL_M:
                log.debug("IK failed for %s (residual %.3f m)", np.round(target, 3), err)
                return max(err, float(np.linalg.norm(self.tip_position() - target)))
            qs.append(q)
        n_steps = max(1, math.ceil(length / (speed * dt)), math.ceil(abs(yaw1 - yaw0) / (YAW_SPEED_RADPS * dt)))
        for i in range(1, n_steps + 1):
            f = i / n_steps * n_way
            k = min(int(f), n_way - 1)
            self._command_arm(qs[k] + (qs[k + 1] - qs[k]) * (f - k))
            if not budget.step() or self._guard(stop):
                return float(np.linalg.norm(self.tip_position() - target))
        return self._settle_at(target, budget, tol_m, stop)

    def _hold(self) -> None:
        self._command_arm(self.joint_positions())

    def go_home(self, budget: StepBudget) -> bool:
        """Joint-space move to HOME_Q at a bounded joint speed; True when there (within 0.01 rad)."""
        q0 = self.joint_positions()
        delta = np.array(HOME_Q) - q0
        n = max(1, math.ceil(np.max(np.abs(delta)) / (JOINT_SPEED_RADPS * self.sim.time_step_s)))
        for i in range(1, n + 1):
            self._command_arm(q0 + delta * (i / n))
            if not budget.step():
                break
        for _ in range(SETTLE_STEPS):
            if np.max(np.abs(self.joint_positions() - np.array(HOME_Q))) < 0.01:
                return True
            if not budget.step():
                return False
        return bool(np.max(np.abs(self.joint_positions() - np.array(HOME_Q))) < 0.01)
