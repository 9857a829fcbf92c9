"""The paper's three motion primitives, built from robot motions and bounded in simulated steps.

All positions are world (= robot base) frame metres with the table top at z = 0; heights are fingertip
heights (see robot.py). `angle_rad` follows common.action: push direction for a push, finger-closing axis
for pick/place. A primitive never raises for an unreachable pose, a blocked path or an empty grasp: it
returns a PrimitiveResult with success False and a reason, and always ends with the arm back home (out of
the camera's view) when the step budget allows.

Going home: with an empty hand that touches no object the arm is put back at home directly (no physics
steps): that free-space move above the scene can change nothing and carries no information, and it was
about a third of every primitive's steps. While anything is held or touched, it drives home physically.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import pybullet as p

from romannet.common.config_sim import SimConfig

from .grasp_check import ClosedGrasp, closed_grasp
from .robot import Hand
from .scene import Scene, StepBudget

log = logging.getLogger(__name__)

APPROACH_TOL_M = 0.01  # farther than this from a pose in free space above the scene = unreachable
DESCENT_SPEED_MPS = 0.25  # the last SLOW_ZONE_M above a contact height: slow, so contacts stay gentle
SLOW_ZONE_M = 0.04
# A pick's way down is guarded. Where objects first push the hand up (CONTACT_FORCE_N: a finger landing on an
# object), it goes on at PRESS_SPEED_MPS, so an object touched on its edge is pushed aside at that speed and
# the finger slides down past it, and it stops where the push reaches PRESS_LIMIT_N (a finger on an
# object's flat top). Pressed on at full arm force and speed instead, an object squirted out from under a
# finger: a cube 30 cm across the table at 1.7 m/s (measured).
CONTACT_FORCE_N = 5.0
PRESS_SPEED_MPS = 0.02
PRESS_LIMIT_N = 25.0
LIFT_SPEED_MPS = 0.6
PUSH_SPEED_MPS = 0.25
PLACE_GAP_M = 0.008  # the held object's bottom stops this far above the pose before the fingers open
FINISH_SETTLE_STEPS = 120  # after going home: what the primitive disturbed comes to rest (and sleeps)


@dataclass(frozen=True)
class PrimitiveResult:
    """What a primitive did. reason is "" on success, else a short code ("unreachable", "nothing_grasped", ...)."""

    success: bool
    reason: str
    steps: int  # physics steps used
    held_body: int | None = None  # pick: the body held after the lift
    hang_m: float = 0.0  # pick: how far the held body's bottom hangs below the fingertips
    moved_m: float = 0.0  # push: largest displacement of any object
    unstable: str = ""  # why the simulation went unstable during the primitive ("" = it did not)
    grasp: ClosedGrasp | None = None  # pick: the grasp as the fingers closed (grasp_check.py)


class Primitives:
    """push / pick / place for one arm in one scene."""

    def __init__(self, scene: Scene, arm: Hand, sim: SimConfig):
        self.scene, self.arm, self.sim = scene, arm, sim

    def _budget(self) -> StepBudget:
        # Watched during the primitive: an exploding contact ends it at once; resting objects go to sleep.
        return StepBudget(self.scene.client, self.sim.max_primitive_steps, watch=self.scene.watch)

    def _finish(self, budget: StepBudget, success: bool, reason: str, **extra) -> PrimitiveResult:
        """Return home (the camera must see the scene unoccluded), let the scene come to rest, count steps."""
        if budget.unstable:
            pass  # leave everything as it is: the episode ends
        elif self._touching_objects():
            self.arm.go_home(budget)
        else:
            self.arm.reset()
        if budget.unstable:
            success, reason = False, "unstable"
        else:
            self.scene.settle(FINISH_SETTLE_STEPS)
        self.scene.steps_total += budget.used
        if reason:
            log.debug("primitive failed: %s", reason)
        return PrimitiveResult(success, reason, budget.used, unstable=budget.unstable, **extra)

    def _touching_objects(self) -> bool:
        """Does the robot touch any object (at the last physics step)?"""
        objects = set(self.scene.objects)
        return any(c[2] in objects for c in p.getContactPoints(bodyA=self.arm.body_id,
                                                               physicsClientId=self.scene.client))

    def _approach(self, x_m: float, y_m: float, z_m: float, angle_rad: float, budget: StepBudget) -> bool:
        err = self.arm.move_tips(np.array([x_m, y_m, z_m]), angle_rad, budget, tol_m=APPROACH_TOL_M / 2)
        return err <= APPROACH_TOL_M

    def _descend(self, x_m: float, y_m: float, z_m: float, z_contact_m: float, angle_rad: float,
                 budget: StepBudget, guarded: bool = False) -> None:
        """Straight down to z_m: at full speed to SLOW_ZONE_M above z_contact_m, then slowly; guarded: from the first
        contact that pushes the hand up on, slowly, and only as long as the push stays below PRESS_LIMIT_N."""
        touched = (lambda: self._pushed_up_n() > CONTACT_FORCE_N) if guarded else None
        target = np.array([x_m, y_m, z_m])
        z_slow = z_contact_m + SLOW_ZONE_M
        if self.arm.tip_position()[2] > z_slow:
            self.arm.move_tips(np.array([x_m, y_m, z_slow]), angle_rad, budget, stop=touched)
        if touched is None or not touched():
            self.arm.move_tips(target, angle_rad, budget, DESCENT_SPEED_MPS, stop=touched)
        if touched is not None and touched():
            self.arm.move_tips(target, angle_rad, budget, PRESS_SPEED_MPS,
                               stop=lambda: self._pushed_up_n() > PRESS_LIMIT_N)

    def _pushed_up_n(self) -> float:
        """How hard objects push the robot up (N, at the last physics step)."""
        return upward_force_n(self.scene.client, self.arm.body_id, self.scene.objects)

    # ------------------------------------------------------------------------------------------ push
    def push(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> PrimitiveResult:
        """Closed gripper at (x, y), fingertips at z_m (a safe height read from the heightmap by the
        caller), then push_distance_m along angle_rad, the end clipped to the workspace."""
        budget = self._budget()
        before = self.scene.positions()
        self.arm.set_fingers(closed=True)
        z_above = z_m + self.sim.safe_height_m
        if not self._approach(x_m, y_m, z_above, angle_rad, budget):
            return self._finish(budget, False, "unreachable")
        self.arm.actuate_fingers(closed=True, budget=budget)  # closed before going down (they close en route)
        self._descend(x_m, y_m, z_m, z_m, angle_rad, budget)
        ws = self.scene.ws
        end_x = float(np.clip(x_m + self.sim.push_distance_m * math.cos(angle_rad), ws.x_min_m, ws.x_max_m))
        end_y = float(np.clip(y_m + self.sim.push_distance_m * math.sin(angle_rad), ws.y_min_m, ws.y_max_m))
        self.arm.move_tips(np.array([end_x, end_y, z_m]), angle_rad, budget, PUSH_SPEED_MPS)
        self.arm.move_tips(np.array([end_x, end_y, z_above]), angle_rad, budget)
        self.arm.set_fingers(closed=False)
        self.scene.settle(120)
        after = self.scene.positions()
        moved = float(np.max(np.linalg.norm(after - before, axis=1))) if len(before) else 0.0
        ok = moved > self.sim.push_moved_threshold_m
        return self._finish(budget, ok, "" if ok else "nothing_moved", moved_m=moved)

    # ------------------------------------------------------------------------------------------ pick
    def pick(self, x_m: float, y_m: float, z_m: float, angle_rad: float, remove_held: bool = False,
             z_contact_m: float | None = None) -> PrimitiveResult:
        """Top-down grasp: fingertips pick_depth_m below the pose z (not below the table), close, lift.

        Success = after the lift the finger gap is not closed AND both fingers touch the same object.
        remove_held: take a successfully picked object out of the world right after the lift, before the
        way home (clutter removal; held_body then names the removed body).
        z_contact_m: the highest point the open fingers may meet on the way down (default z_m): the descent
        is slow from SLOW_ZONE_M above it.
        """
        budget = self._budget()
        self.arm.set_fingers(closed=False)
        if not self._approach(x_m, y_m, self.sim.lift_height_m, angle_rad, budget):
            return self._finish(budget, False, "unreachable")
        self.arm.actuate_fingers(closed=False, budget=budget)  # fully open before going down
        z_grasp = max(z_m - self.sim.pick_depth_m, self.sim.fingertip_clearance_m)
        z_contact = max(z_m if z_contact_m is None else z_contact_m, z_m, z_grasp)
        self._descend(x_m, y_m, z_grasp, z_contact, angle_rad, budget, guarded=True)
        self.arm.actuate_fingers(closed=True, budget=budget)
        closed = closed_grasp(self.scene.client, self.arm.body_id, self.arm.finger_joints, self.scene.objects,
                              self.arm.finger_gap_m(), (x_m, y_m), angle_rad)
        self.arm.move_tips(np.array([x_m, y_m, self.sim.lift_height_m]), angle_rad, budget, LIFT_SPEED_MPS)
        if budget.exhausted:
            return self._finish(budget, False, "step_budget")
        held = self.held_body()
        if held is None:
            self.arm.set_fingers(closed=False)
            return self._finish(budget, False, "nothing_grasped", grasp=closed)
        hang = float(self.arm.tip_position()[2] - self.scene.bottom_z(held))
        if remove_held:
            self.scene.remove_object(held)
            self.arm.set_fingers(closed=False)
        return self._finish(budget, True, "", held_body=held, hang_m=hang, grasp=closed)

    def held_body(self) -> int | None:
        """The object held between the fingers: gap not closed and both fingers in contact with it."""
        if self.arm.finger_gap_m() <= self.sim.grasp_min_gap_m:
            return None
        for body in self.scene.objects:
            if self.arm.fingers_touching(body):
                return body
        return None

    # ----------------------------------------------------------------------------------------- place
    def place(self, x_m: float, y_m: float, z_m: float, angle_rad: float, hang_m: float) -> PrimitiveResult:
        """Carry the held object over (x, y), lower it until its bottom is just above z_m, open, retreat.

        hang_m: how far the held object hangs below the fingertips (measured at the pick). Whether the
        stack got higher is judged by the caller from the next heightmap.
        """
        budget = self._budget()
        z_release = z_m + hang_m + PLACE_GAP_M
        z_above = max(self.sim.lift_height_m, z_release + 0.05)
        if not self._approach(x_m, y_m, z_above, angle_rad, budget):
            return self._finish(budget, False, "unreachable")
        self._descend(x_m, y_m, z_release, z_release, angle_rad, budget)
        self.arm.actuate_fingers(closed=False, budget=budget)
        self.arm.move_tips(np.array([x_m, y_m, z_above]), angle_rad, budget)
        self.scene.settle(120)
        return self._finish(budget, True, "")


def upward_force_n(client: int, robot_id: int, bodies: list[int]) -> float:
    """Total upward contact force (N) that `bodies` exert on the robot at the last physics step.

    A contact's normal on B points from B to A (the robot), so its z component times the normal force is
    the push up; side contacts (fingers sliding past a neighbour) add next to nothing.
    """
    others = set(bodies)
    return float(sum(c[9] * c[7][2] for c in p.getContactPoints(bodyA=robot_id, physicsClientId=client)
                     if c[2] in others))
