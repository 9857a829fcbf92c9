"""One PyBullet world per environment: client lifecycle, table, objects, camera -> heightmaps, stability.

Resting objects are put to sleep explicitly once settled (`settle`): Bullet would wait 2 s of simulated
time before deactivating them, longer than a primitive, and a scene of ten awake objects costs ~10x the
physics time of a sleeping one. A sleeping object wakes on any contact with a moving body.

Frames: world = robot base frame (Panda base at the origin, facing +x); the table top is z = 0, the
workspace floor. Every PyBullet call passes `physicsClientId`, so several scenes live in one process
without touching PyBullet's global client.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import numpy as np
import pybullet as p
import pybullet_data

from romannet.common.config import CameraConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.heightmap import get_heightmaps

from .camera import Camera, Frame

log = logging.getLogger(__name__)

TABLE_THICKNESS_M = 0.05
TABLE_RGBA = (0.45, 0.45, 0.45, 1.0)
# Below this the object has fallen off the table (the table top is z = 0).
FELL_OFF_Z_M = -0.03
REST_SPEED_MPS = 0.005  # an object slower than this and REST_ANGULAR_SPEED_RADPS is at rest
REST_ANGULAR_SPEED_RADPS = 0.1
__all__ = ["Frame", "Scene", "StepBudget", "wrap_half_pi", "yaw_of"]


class StepBudget:
    """Counts physics steps of one primitive and refuses to step past its bound (bounded in sim time).

    watch: called every watch_every steps; a non-empty answer (why the simulation went unstable) stops the
    primitive at once, as a spent budget does, and is kept in `unstable`.
    """

    def __init__(self, client: int, max_steps: int, watch: Callable[[], str] | None = None,
                 watch_every: int = 24):
        self.client = client
        self.max_steps = max_steps
        self.used = 0
        self.watch, self.watch_every = watch, watch_every
        self.unstable = ""

    @property
    def exhausted(self) -> bool:
        return self.used >= self.max_steps or bool(self.unstable)

    def step(self) -> bool:
        """Advance the physics one time step; False (and no step) when the budget is spent or unstable."""
        if self.exhausted:
            return False
        p.stepSimulation(physicsClientId=self.client)
        self.used += 1
        if self.watch is not None and self.used % self.watch_every == 0:
            self.unstable = self.watch()
        return True


class Scene:
    """The physics world: a table, the task's objects and a statically mounted RGB-D camera."""

    def __init__(self, ws: WorkspaceConfig, cam: CameraConfig, sim: SimConfig):
        self.ws, self.cam, self.sim = ws, cam, sim
        self.client = p.connect(p.DIRECT)
        if self.client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")
        self.objects: list[int] = []  # body ids of the task's objects, in spawn order
        self.local_half_extents_m: dict[int, np.ndarray] = {}  # per body, in its own frame (for the oracle)
        self.steps_total = 0
        self.robot_id: int | None = None  # set by the environment: never put to sleep what it holds
        self._calm: dict[int, int] = {}
        self.camera = Camera(self.client, cam, sim)
        self.intrinsics, self.T_world_cam = self.camera.intrinsics, self.camera.T_world_cam
        self.reset_world()
        # The table is drawn once and composited under every frame (camera.py says why).
        self.camera.capture_table(self._table_extents, self._table_centre, TABLE_RGBA)

    # ------------------------------------------------------------------------------------- lifecycle
    def reset_world(self) -> None:
        """Empty the world and rebuild the table; the same calls in the same order give the same world."""
        c = self.client
        p.resetSimulation(physicsClientId=c)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=c)
        p.setGravity(0.0, 0.0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=self.sim.time_step_s, numSubSteps=self.sim.substeps,
                                    numSolverIterations=self.sim.solver_iterations,
                                    solverResidualThreshold=self.sim.solver_residual_threshold,
                                    deterministicOverlappingPairs=1, physicsClientId=c)
        half = self.sim.table_half_size_m
        centre_x = self.table_centre_x_m = (self.ws.x_min_m + self.ws.x_max_m) / 2.0
        # The table reaches back under the robot base, so the base stands on it.
        half_x = max(half, centre_x + 0.15)
        extents = self._table_extents = (half_x, half, TABLE_THICKNESS_M / 2.0)
        self._table_centre = (centre_x, 0.0, -TABLE_THICKNESS_M / 2.0)
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=extents, physicsClientId=c)
        self.table_id = p.createMultiBody(0.0, col, -1, list(self._table_centre), physicsClientId=c)
        # Invisible: the camera composites its pre-rendered table layer instead. (Without a visual shape
        # PyBullet would draw the collision box; a transparent one is skipped by the renderer.)
        p.changeVisualShape(self.table_id, -1, rgbaColor=(0.0, 0.0, 0.0, 0.0), physicsClientId=c)
        p.changeDynamics(self.table_id, -1, lateralFriction=0.8, physicsClientId=c)
        self.objects = []
        self.local_half_extents_m = {}
        self.steps_total = 0
        self.robot_id = None
        self._calm: dict[int, int] = {}  # per object: consecutive watch() checks found at rest

    def close(self) -> None:
        """Disconnect the client. Idempotent."""
        if self.client >= 0:
            try:
                p.disconnect(physicsClientId=self.client)
            except p.error:  # already gone (e.g. the process is shutting down)
                pass
            self.client = -1

    # --------------------------------------------------------------------------------------- objects
    def add_object(self, body_id: int) -> None:
        """Register a freshly spawned body (before any physics step: its extents are read at rest pose)."""
        c = self.client
        pos, orn = p.getBasePositionAndOrientation(body_id, physicsClientId=c)
        p.resetBasePositionAndOrientation(body_id, pos, (0, 0, 0, 1), physicsClientId=c)
        lo, hi = p.getAABB(body_id, -1, physicsClientId=c)
        p.resetBasePositionAndOrientation(body_id, pos, orn, physicsClientId=c)
        self.local_half_extents_m[body_id] = (np.array(hi) - np.array(lo)) / 2.0
        # Resting objects dominate the step cost (mesh contact manifolds): let Bullet put them to sleep.
        # They wake on any contact with a moving body; remove_object wakes the rest explicitly.
        p.changeDynamics(body_id, -1, activationState=p.ACTIVATION_STATE_ENABLE_SLEEPING,
                         physicsClientId=c)
        self.objects.append(body_id)

    def discard_object(self, body_id: int) -> None:
        """Delete a body from the world and the registry (no settling: the caller steps the world)."""
        p.removeBody(body_id, physicsClientId=self.client)
        self.objects.remove(body_id)
        self.local_half_extents_m.pop(body_id, None)
        self._calm.pop(body_id, None)

    def remove_object(self, body_id: int, settle_steps: int = 120) -> None:
        """Take a picked object out of the world (clutter removal) and let the rest settle (and sleep)."""
        self.discard_object(body_id)
        for other in self.objects:  # one may have rested on the removed body: it must fall, not float
            p.changeDynamics(other, -1, activationState=p.ACTIVATION_STATE_WAKE_UP, physicsClientId=self.client)
        self.settle(settle_steps)

    def pose(self, body_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(position m, quaternion xyzw) of a body's base in the world frame."""
        pos, orn = p.getBasePositionAndOrientation(body_id, physicsClientId=self.client)
        return np.array(pos), np.array(orn)

    def positions(self) -> np.ndarray:
        """(N, 3) world positions of the registered objects, spawn order."""
        return np.array([self.pose(b)[0] for b in self.objects]).reshape(-1, 3)

    def top_z(self, body_id: int) -> float:
        """Highest point of a body (world z, m)."""
        return float(p.getAABB(body_id, -1, physicsClientId=self.client)[1][2])

    def bottom_z(self, body_id: int) -> float:
        """Lowest point of a body (world z, m)."""
        return float(p.getAABB(body_id, -1, physicsClientId=self.client)[0][2])

    def in_workspace(self, body_id: int, margin_m: float = 0.0) -> bool:
        """Is the body's centre over the workspace square grown by margin_m on every side (and on or above
        the table)?"""
        x, y, z = self.pose(body_id)[0]
        ws, m = self.ws, margin_m
        return ws.x_min_m - m <= x <= ws.x_max_m + m and ws.y_min_m - m <= y <= ws.y_max_m + m and z > FELL_OFF_Z_M

    def step(self, n: int) -> None:
        """Advance the physics n time steps (settling, not robot motion)."""
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)
        self.steps_total += n

    def _touching_robot(self, body_id: int) -> bool:
        return self.robot_id is not None and bool(p.getContactPoints(body_id, self.robot_id,
                                                                     physicsClientId=self.client))

    def _slow(self, body_id: int, speed_mps: float) -> bool:
        lin, ang = p.getBaseVelocity(body_id, physicsClientId=self.client)
        return math.hypot(*lin) < speed_mps and math.hypot(*ang) < REST_ANGULAR_SPEED_RADPS

    def at_rest(self, speed_mps: float = REST_SPEED_MPS) -> bool:
        """Is every object slower than speed_mps (and REST_ANGULAR_SPEED_RADPS)? A held object (touching
        the robot) does not count: it may swing in the hand, and it is never put to sleep."""
        return all(self._touching_robot(b) or self._slow(b, speed_mps) for b in self.objects)

    def settle(self, max_steps: int, speed_mps: float = REST_SPEED_MPS, check_every: int = 10) -> int:
        """Step until every object is at rest at two checks check_every steps apart, then put them to sleep.

        Two checks, because a rocking object is momentarily still at each turn. Returns the steps used; at
        max_steps without rest the objects stay awake (Bullet's own sleeping then applies).
        """
        used, calm = 0, 0
        while True:
            calm = calm + 1 if self.at_rest(speed_mps) else 0
            if calm >= 2:
                self.sleep_objects()
                return used
            if used >= max_steps:
                return used
            n = min(check_every, max_steps - used)
            self.step(n)
            used += n

    def sleep_objects(self, exclude: Sequence[int] = ()) -> None:
        """Deactivate every object but those in exclude or touching the robot (a held object must follow it)."""
        c = self.client
        for b in self.objects:
            if b in exclude or self._touching_robot(b):
                continue
            p.changeDynamics(b, -1, activationState=p.ACTIVATION_STATE_SLEEP, physicsClientId=c)

    def watch(self) -> str:
        """Run every few steps during a primitive: instability(), and, while sane, put each object that was
        at rest at two checks in a row to sleep (Bullet itself waits 2 s; a primitive lasts ~1.5 s).

        Sleeping is per object but only takes where it cannot matter: Bullet wakes a whole island again as
        long as one member (the robot, a held or a sliding object) is active.
        """
        reason = self.instability()
        if reason:
            return reason
        for b in self.objects:
            if self._touching_robot(b) or not self._slow(b, REST_SPEED_MPS):
                self._calm[b] = 0
                continue
            self._calm[b] = self._calm.get(b, 0) + 1
            if self._calm[b] >= 2:
                p.changeDynamics(b, -1, activationState=p.ACTIVATION_STATE_SLEEP, physicsClientId=self.client)
        return ""

    def instability(self) -> str:
        """"" when the world is sane, else why not: an object fell off the table, flew away or went NaN."""
        limit = self.sim.table_half_size_m + 0.5
        for b in self.objects:
            pos, _ = self.pose(b)
            lin, ang = p.getBaseVelocity(b, physicsClientId=self.client)
            if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(lin)) and np.all(np.isfinite(ang))):
                return f"object {b} has a non-finite pose or velocity"
            if pos[2] < FELL_OFF_Z_M or abs(pos[1]) > limit or abs(pos[0] - self.table_centre_x_m) > limit:
                return f"object {b} left the table at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}) m"
            if np.linalg.norm(lin) > self.sim.unstable_speed_mps:
                return f"object {b} moves at {np.linalg.norm(lin):.1f} m/s (the simulation exploded)"
        return ""

    # ---------------------------------------------------------------------------------------- camera
    def render(self, rng: np.random.Generator | None = None, cull: Sequence[int] = ()) -> Frame:
        """Capture the camera (camera.Camera.render): cull = bodies hidden when outside the view (the robot)."""
        return self.camera.render(rng, cull)

    def heightmaps(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """(color_hm uint8 h x w x 3, depth_hm float32 h x w, metres above the table) via common.heightmap."""
        return get_heightmaps(frame.color, frame.depth_m, self.intrinsics, self.T_world_cam, self.ws)


def yaw_of(orn_xyzw: np.ndarray) -> float:
    """Rotation about world z (rad) of a quaternion, as PyBullet's Euler yaw."""
    return float(p.getEulerFromQuaternion(tuple(orn_xyzw))[2])


def wrap_half_pi(angle_rad: float) -> float:
    """Angle folded into (-pi/2, pi/2]: a parallel-jaw gripper is the same after a half turn."""
    a = math.fmod(angle_rad, math.pi)
    if a <= -math.pi / 2:
        a += math.pi
    elif a > math.pi / 2:
        a -= math.pi
    return a
