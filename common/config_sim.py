"""Configuration of the PyBullet simulator actors run (actor/sim): scene, robot, camera, primitives, episodes.

Frames: the robot base frame is the world frame; the Panda's base sits at the origin facing +x, the table
top is the plane z = 0 (the workspace floor, WorkspaceConfig.z_min_m). Lengths in metres, times in seconds.
The workspace square, camera intrinsics and task kind live in common.config (WorkspaceConfig, CameraConfig,
TaskConfig); this section only holds what is specific to the simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from .configbase import require

OBJECT_SETS = ("blocks", "cubes", "novel")


@dataclass(frozen=True)
class HandSpec:
    """What a simulated parallel gripper's fingers can do; the finger links and pads are the Panda's."""

    travel_m: float  # per finger, closed to fully open
    force_n: float  # squeezing force of each finger
    speed_mps: float  # top speed of each finger


# "panda": the Panda URDF's travel (an 8 cm opening). Without a speed limit the position-controlled fingers
# closed at up to 0.96 m/s and threw an object hit with an edge; a real gripper's fingers move at cm/s.
# "rg2": the paper's and VPG's simulated gripper, by the OnRobot RG2 data sheet: 0-110 mm stroke, up to
# 40 N gripping force, up to 127 mm/s closing speed (both fingers together).
HANDS = {
    "panda": HandSpec(travel_m=0.04, force_n=40.0, speed_mps=0.1),
    "rg2": HandSpec(travel_m=0.055, force_n=40.0, speed_mps=0.0635),
}


@dataclass(frozen=True)
class SimConfig:
    """The simulated scene, robot and primitives (PyBullet, DIRECT mode, one client per environment)."""

    # --- scene
    object_set: Literal["blocks", "cubes", "novel"] = "blocks"  # stacking always uses cubes
    num_objects: int = 10  # clutter: objects dropped per episode (paper: 10 training, 30 testing)
    num_stacking_cubes: int = 10  # stacking: cubes dropped per episode (the paper's 10)
    case_file: str = ""  # arrangement: a test-case file; "" = the seed picks one of the shipped cases
    # arrangement: each episode moves the whole case rigidly by up to this much (uniform in x and y) and turns
    # it by up to case_jitter_deg about its centre, drawn from the episode seed. Without it a deterministic
    # simulator and a greedy policy repeat the very same run for every seed of a case. 0 and 0 = as written.
    case_jitter_m: float = 0.005
    case_jitter_deg: float = 3.0
    drop_height_m: float = 0.15  # clutter/stacking: objects are dropped from this height above the table
    settle_steps: int = 240  # physics steps after spawning, so the scene is at rest before the first image
    # --- robot
    robot: Literal["arm", "gripper"] = "arm"  # "gripper": a floating Panda hand moved by a constraint (faster)
    # The fingers' travel, force and speed (HANDS): "panda" (8 cm opening) or "rg2" (11 cm, the paper's).
    hand: Literal["panda", "rg2"] = "rg2"
    finger_friction: float = 1.5  # lateral friction of the finger pads (a 5 cm cube must not slip)
    # Unset (None): the hand's own value (HANDS); set, it overrides the hand's.
    finger_force_n: float | None = None  # squeezing force of each finger (N)
    finger_speed_mps: float | None = None  # top speed of each finger (m/s)
    finger_travel_m: float | None = None  # travel of each finger from closed to fully open (m)
    # Both fingers one mechanism, as on the real Panda hand and RG2: a gear constraint keeps their positions
    # equal, so a held object sits centred in the hand. Independent fingers let it shift ~1 cm (the pair
    # drifts under inertia while both squeeze), and most places of a 4 cm cube onto a stack fell off.
    coupled_fingers: bool = True
    # --- physics
    time_step_s: float = 1.0 / 240.0
    substeps: int = 0  # PyBullet numSubSteps (0 = none); raise for stiffer contacts at a cost in speed
    solver_iterations: int = 50
    # The solver stops iterating once every constraint's velocity error is below this (m/s). PyBullet's
    # 1e-7 runs all 50 iterations every step; 1e-4 (0.4 um of drift per step) made a step ~3x cheaper with
    # the same oracle outcomes (bench/sim.py; docs/benchmarks.md).
    solver_residual_threshold: float = 1e-4
    # --- camera (intrinsics in CameraConfig); pose as PyBullet's computeViewMatrix(eye, target, up)
    camera_eye_m: tuple[float, float, float] = (0.5, 0.0, 0.75)
    camera_target_m: tuple[float, float, float] = (0.5, 0.0, 0.0)
    camera_up: tuple[float, float, float] = (-1.0, 0.0, 0.0)  # robot base at the top of the image
    depth_noise_std_m: float = 0.0  # Gaussian noise added to the camera depth (0 = a perfect sensor)
    # --- primitives (the paper's "Manipulation Action Space")
    push_distance_m: float = 0.10
    pick_depth_m: float = 0.03  # fingers go this far below the pose z before closing
    safe_height_m: float = 0.15  # approach/retreat height of the fingertips above the local heightmap
    lift_height_m: float = 0.25  # fingertip height above the table after a pick
    fingertip_clearance_m: float = 0.006  # fingertips never go lower than this above the table
    max_speed_mps: float = 1.0  # Cartesian speed of the fingertips along a straight segment
    max_primitive_steps: int = 1500  # hard bound on physics steps per primitive (incl. return home)
    push_moved_threshold_m: float = 0.01  # push success: some object moved farther than this
    grasp_min_gap_m: float = 0.002  # pick success needs the finger gap above this (not closed on air)
    # --- episodes
    max_steps: int = 100  # actions per episode before "step_limit"
    max_consecutive_failures: int = 10  # the paper's completion criterion
    unstable_speed_mps: float = 3.0  # an object faster than this (at rest checks) means the sim exploded
    table_half_size_m: float = 0.6  # the table is a square of this half size around the workspace centre

    def __post_init__(self) -> None:
        require(self.object_set in OBJECT_SETS, "sim.object_set", self.object_set,
                f"must be one of {', '.join(OBJECT_SETS)}")
        require(1 <= self.num_objects <= 60, "sim.num_objects", self.num_objects, "must be 1..60")
        require(1 <= self.num_stacking_cubes <= 20, "sim.num_stacking_cubes", self.num_stacking_cubes,
                "must be 1..20")
        require(0.0 <= self.case_jitter_m <= 0.05, "sim.case_jitter_m", self.case_jitter_m,
                "must be 0..0.05 m (a shift of the whole case; 0 = as written)")
        require(0.0 <= self.case_jitter_deg <= 30.0, "sim.case_jitter_deg", self.case_jitter_deg,
                "must be 0..30 degrees (a turn of the whole case; 0 = as written)")
        require(0.0 <= self.drop_height_m <= 0.5, "sim.drop_height_m", self.drop_height_m, "must be 0..0.5 m")
        require(0 <= self.settle_steps <= 5000, "sim.settle_steps", self.settle_steps, "must be 0..5000")
        require(self.robot in ("arm", "gripper"), "sim.robot", self.robot, "must be 'arm' or 'gripper'")
        require(self.hand in HANDS, "sim.hand", self.hand, f"must be one of {', '.join(HANDS)}")
        spec = HANDS[self.hand]
        for name, own in (("finger_force_n", spec.force_n), ("finger_speed_mps", spec.speed_mps),
                          ("finger_travel_m", spec.travel_m)):
            if getattr(self, name) is None:  # resolved once, so every reader sees a number
                object.__setattr__(self, name, own)
        require(0.1 <= self.finger_friction <= 10.0, "sim.finger_friction", self.finger_friction,
                "must be 0.1..10")
        require(1.0 <= self.finger_force_n <= 200.0, "sim.finger_force_n", self.finger_force_n,
                "must be 1..200 N")
        require(0.01 <= self.finger_speed_mps <= 1.0, "sim.finger_speed_mps", self.finger_speed_mps,
                "must be 0.01..1 m/s per finger")
        require(0.02 <= self.finger_travel_m <= 0.06, "sim.finger_travel_m", self.finger_travel_m,
                "must be 0.02..0.06 m per finger (the Panda: 0.04, an 8 cm opening; the RG2: 0.055, 11 cm)")
        require(1e-4 <= self.time_step_s <= 0.02, "sim.time_step_s", self.time_step_s,
                "must be 1e-4..0.02 s (PyBullet's default is 1/240)")
        require(0 <= self.substeps <= 20, "sim.substeps", self.substeps, "must be 0..20")
        require(1 <= self.solver_iterations <= 1000, "sim.solver_iterations", self.solver_iterations,
                "must be 1..1000")
        require(0.0 < self.solver_residual_threshold <= 1e-2, "sim.solver_residual_threshold",
                self.solver_residual_threshold, "must be in (0, 0.01] m/s (PyBullet's default: 1e-7)")
        require(all(math.isfinite(v) for v in (*self.camera_eye_m, *self.camera_target_m, *self.camera_up)),
                "sim.camera_eye_m", self.camera_eye_m, "camera eye, target and up must be finite")
        require(self.camera_eye_m[2] > 0.3, "sim.camera_eye_m", self.camera_eye_m,
                "the camera must be more than 0.3 m above the table to see the whole workspace")
        require(0.0 <= self.depth_noise_std_m <= 0.02, "sim.depth_noise_std_m", self.depth_noise_std_m,
                "must be 0..0.02 m")
        require(0.01 <= self.push_distance_m <= 0.3, "sim.push_distance_m", self.push_distance_m,
                "must be 0.01..0.3 m (the paper: 0.10)")
        require(0.0 <= self.pick_depth_m <= 0.08, "sim.pick_depth_m", self.pick_depth_m,
                "must be 0..0.08 m (the paper: 0.03)")
        require(0.05 <= self.safe_height_m <= 0.4, "sim.safe_height_m", self.safe_height_m, "must be 0.05..0.4 m")
        require(0.1 <= self.lift_height_m <= 0.5, "sim.lift_height_m", self.lift_height_m, "must be 0.1..0.5 m")
        require(0.0 <= self.fingertip_clearance_m <= 0.03, "sim.fingertip_clearance_m",
                self.fingertip_clearance_m, "must be 0..0.03 m")
        require(0.05 <= self.max_speed_mps <= 3.0, "sim.max_speed_mps", self.max_speed_mps,
                "must be 0.05..3 m/s")
        require(100 <= self.max_primitive_steps <= 20000, "sim.max_primitive_steps", self.max_primitive_steps,
                "must be 100..20000 physics steps")
        require(0.0 < self.push_moved_threshold_m <= 0.1, "sim.push_moved_threshold_m",
                self.push_moved_threshold_m, "must be in (0, 0.1] m")
        require(0.0 <= self.grasp_min_gap_m < 0.04, "sim.grasp_min_gap_m", self.grasp_min_gap_m,
                "must be in [0, 0.04) m")
        require(1 <= self.max_steps <= 10000, "sim.max_steps", self.max_steps, "must be 1..10000 actions")
        require(1 <= self.max_consecutive_failures <= 1000, "sim.max_consecutive_failures",
                self.max_consecutive_failures, "must be 1..1000 (the paper: 10)")
        require(0.1 <= self.unstable_speed_mps <= 100.0, "sim.unstable_speed_mps", self.unstable_speed_mps,
                "must be 0.1..100 m/s")
        require(0.35 <= self.table_half_size_m <= 3.0, "sim.table_half_size_m", self.table_half_size_m,
                "must be 0.35..3 m (the table must hold the 0.448 m workspace)")

