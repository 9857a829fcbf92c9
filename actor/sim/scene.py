"""One PyBullet world per environment: client lifecycle, table, objects, camera -> heightmaps, stability.

Frames: world = robot base frame (Panda base at the origin, facing +x); the table top is z = 0, the
workspace floor. Every PyBullet call passes `physicsClientId`, so several scenes live in one process
without touching PyBullet's global client.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import pybullet as p
import pybullet_data

from romannet.common.config import CameraConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.heightmap import get_heightmaps, look_at, vertical_fov_deg, zbuffer_to_depth

log = logging.getLogger(__name__)

TABLE_THICKNESS_M = 0.05
TABLE_RGBA = (0.45, 0.45, 0.45, 1.0)
# Below this the object has fallen off the table (the table top is z = 0).
FELL_OFF_Z_M = -0.03


@dataclass(frozen=True)
class Frame:
    """One camera capture: RGB uint8 (H, W, 3), metric depth float32 (H, W) along the camera z axis."""

    color: np.ndarray
    depth_m: np.ndarray


class StepBudget:
    """Counts physics steps of one primitive and refuses to step past its bound (bounded in sim time)."""

    def __init__(self, client: int, max_steps: int):
        self.client = client
        self.max_steps = max_steps
        self.used = 0

    @property
    def exhausted(self) -> bool:
        return self.used >= self.max_steps

    def step(self) -> bool:
        """Advance the physics one time step; False (and no step) when the budget is spent."""
        if self.used >= self.max_steps:
            return False
        p.stepSimulation(physicsClientId=self.client)
        self.used += 1
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
        # Camera: a PyBullet render has its principal point at the image centre, ((W-1)/2, (H-1)/2).
        self.intrinsics = np.array([[cam.fy_px, 0.0, (cam.width_px - 1) / 2.0],
                                    [0.0, cam.fy_px, (cam.height_px - 1) / 2.0],
                                    [0.0, 0.0, 1.0]])
        self.T_world_cam = look_at(np.array(sim.camera_eye_m), np.array(sim.camera_target_m),
                                   np.array(sim.camera_up))
        self._view = p.computeViewMatrix(sim.camera_eye_m, sim.camera_target_m, sim.camera_up,
                                         physicsClientId=self.client)
        self._proj = p.computeProjectionMatrixFOV(vertical_fov_deg(cam.fy_px, cam.height_px),
                                                  cam.width_px / cam.height_px, cam.near_m, cam.far_m,
                                                  physicsClientId=self.client)
        self.reset_world()

    # ------------------------------------------------------------------------------------- lifecycle
    def reset_world(self) -> None:
        """Empty the world and rebuild the table; the same calls in the same order give the same world."""
        c = self.client
        p.resetSimulation(physicsClientId=c)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=c)
        p.setGravity(0.0, 0.0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=self.sim.time_step_s, numSubSteps=self.sim.substeps,
                                    numSolverIterations=self.sim.solver_iterations,
                                    deterministicOverlappingPairs=1, physicsClientId=c)
        half = self.sim.table_half_size_m
        centre_x = self.table_centre_x_m = (self.ws.x_min_m + self.ws.x_max_m) / 2.0
        # The table reaches back under the robot base, so the base stands on it.
        half_x = max(half, centre_x + 0.15)
        extents = (half_x, half, TABLE_THICKNESS_M / 2.0)
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=extents, physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=extents, rgbaColor=TABLE_RGBA, physicsClientId=c)
        self.table_id = p.createMultiBody(0.0, col, vis, [centre_x, 0.0, -TABLE_THICKNESS_M / 2.0],
                                          physicsClientId=c)
        p.changeDynamics(self.table_id, -1, lateralFriction=0.8, physicsClientId=c)
        self.objects = []
        self.local_half_extents_m = {}
        self.steps_total = 0

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

    def remove_object(self, body_id: int) -> None:
        """Take a picked object out of the world (clutter removal)."""
        p.removeBody(body_id, physicsClientId=self.client)
        self.objects.remove(body_id)
        self.local_half_extents_m.pop(body_id, None)
        for other in self.objects:  # one may have rested on the removed body: it must fall, not float
            p.changeDynamics(other, -1, activationState=p.ACTIVATION_STATE_WAKE_UP, physicsClientId=self.client)

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

    def in_workspace(self, body_id: int) -> bool:
        """Is the body's centre over the workspace square (and on or above the table)?"""
        x, y, z = self.pose(body_id)[0]
        ws = self.ws
        return ws.x_min_m <= x <= ws.x_max_m and ws.y_min_m <= y <= ws.y_max_m and z > FELL_OFF_Z_M

    def step(self, n: int) -> None:
        """Advance the physics n time steps (settling, not robot motion)."""
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)
        self.steps_total += n

    def settle(self, max_steps: int, speed_mps: float = 0.005, check_every: int = 20) -> int:
        """Step until every object is slower than speed_mps (checked every few steps); returns steps used."""
        used = 0
        while used < max_steps:
            n = min(check_every, max_steps - used)
            self.step(n)
            used += n
            if all(np.linalg.norm(p.getBaseVelocity(b, physicsClientId=self.client)[0]) < speed_mps
                   for b in self.objects):
                break
        return used

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
    def render(self, rng: np.random.Generator | None = None) -> Frame:
        """Capture the camera (ER_TINY_RENDERER, CPU); depth linearised from the z-buffer, noise if configured."""
        cam = self.cam
        _, _, rgba, zbuf, _ = p.getCameraImage(cam.width_px, cam.height_px, self._view, self._proj,
                                               shadow=0, renderer=p.ER_TINY_RENDERER,
                                               flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self.client)
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(cam.height_px, cam.width_px, 4)
        depth = zbuffer_to_depth(np.asarray(zbuf).reshape(cam.height_px, cam.width_px), cam.near_m, cam.far_m)
        if self.sim.depth_noise_std_m > 0.0:
            if rng is None:
                raise ValueError("depth noise is configured: render() needs the episode's rng")
            depth = depth + rng.normal(0.0, self.sim.depth_noise_std_m, depth.shape).astype(np.float32)
        return Frame(np.ascontiguousarray(rgba[:, :, :3]), depth)

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
