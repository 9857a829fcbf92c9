"""The shared interfaces of the fleet, in one small module (as Acme keeps its core in one file).

Actors talk to an `Env` (a simulator or a real robot behind the same interface), learners and actors talk
to a `ReplayClient` (over Zenoh or in-process), actors get weights and exploration rates from a
`WeightsSource`. Each has a Zenoh implementation and an in-process one behind the same methods.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from .action import Action
from .wire_messages import (
    ExplorationRateMsg,
    InsertAckMsg,
    PriorityUpdateMsg,
    SampleBatchMsg,
    TransitionMsg,
)

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True, eq=False)
class Observation:
    """What the policy sees: orthographic heightmaps of the workspace plus the gripper state.

    color_hm: uint8 (h, w, 3) RGB; depth_hm: float32 (h, w), metres above the workspace floor;
    camera_color / camera_depth_m: the raw camera frame (kept for recording; may be None).
    """

    color_hm: np.ndarray
    depth_hm: np.ndarray
    holding: bool
    camera_color: np.ndarray | None = None
    camera_depth_m: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class StepResult:
    """The outcome of executing one action.

    success is the paper's sub-task indicator X; progress_* are P before/after the action in [0, 1];
    reward is R_tp = W X P (0 on progress reversal), computed with common.reward; the learner builds the
    TPG label map from it. detail says why a primitive failed (IK failure, nothing grasped, ...).
    """

    observation: Observation
    success: bool
    progress_before: float
    progress_after: float
    reward: float
    done: bool
    done_reason: str = ""
    detail: str = ""
    info: dict[str, float | int | str | bool] = field(default_factory=dict)


@runtime_checkable
class Env(Protocol):
    """A manipulation environment: the PyBullet simulator or a real robot."""

    primitives: tuple[str, ...]
    # "" while the environment may act, else why it stopped (a real robot's protective stop): the actor then
    # waits for an operator and try_resume(). The simulator never pauses.
    paused: str

    def reset(self, seed: int | None = None) -> Observation:
        """Start a new episode (a new scene from `seed`) and return the first observation."""
        ...

    def step(self, action: Action) -> StepResult:
        """Execute one primitive; a failure is a StepResult with success False, never an exception."""
        ...

    def close(self) -> None:
        """Release the simulator / disconnect the robot. Idempotent."""
        ...

    def try_resume(self) -> bool:
        """After an operator's resume request: True (and `paused` cleared) if the environment can act again."""
        ...

    def camera_pose(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(T_world_cam 4x4, intrinsics 3x3) of the camera over the workspace, None where unknown; episodes
        record them so a player can place the camera (a real camera's intrinsics come with each frame)."""
        ...


@runtime_checkable
class ReplayClient(Protocol):
    """Access to the prioritized replay server (Zenoh or in-process)."""

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        """Insert; returns only after the server has written the transition durably (or raises)."""
        ...

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        """insert() of a transition already encoded with common.wire.encode_transition: the actor's spool
        holds the bytes, and a Zenoh client sends them without decoding and re-encoding the PNG heightmaps."""
        ...

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> SampleBatchMsg:
        """Draw a prioritized batch; raises TimeoutError if the rate limiter or the server holds it back."""
        ...

    def update_priorities(self, update: PriorityUpdateMsg) -> None:
        """Set new priorities by item id; ids of evicted items are ignored."""
        ...

    def stats(self, timeout_s: float = 10.0) -> dict:
        """Size, bytes, rates, per-actor counts, policy lag."""
        ...


@runtime_checkable
class WeightsSource(Protocol):
    """Where an actor gets new weights and exploration rates between actions."""

    def poll_weights(self) -> tuple[int, dict[str, torch.Tensor]] | None:
        """The newest (version, state tensors) not yet returned, or None; never blocks for long."""
        ...

    def poll_exploration(self) -> ExplorationRateMsg | None:
        """The newest exploration rate not yet returned, or None."""
        ...


# ------------------------------------------------------------------------------------------ real robots
@dataclass(frozen=True, eq=False)
class CameraFrame:
    """One aligned RGB-D frame: color uint8 (H, W, 3) RGB; depth_m float32 (H, W), metres along the camera
    z axis as the device reports them (0 = no reading); intrinsics 3x3 of the color stream (depth is aligned
    to it); timestamp_s from the device clock."""

    color: np.ndarray
    depth_m: np.ndarray
    intrinsics: np.ndarray
    timestamp_s: float = 0.0


@runtime_checkable
class Camera(Protocol):
    """An RGB-D camera with an explicit lifecycle (connect / disconnect, or `with camera:`)."""

    def connect(self) -> None:
        """Open the device and start streaming; raises RobotError with the reason (no device, busy, ...)."""
        ...

    def disconnect(self) -> None:
        """Stop streaming and release the device. Idempotent."""
        ...

    def capture(self) -> CameraFrame:
        """The newest aligned color + depth frame; raises RobotError if none arrives in time."""
        ...


@dataclass(frozen=True)
class MotionResult:
    """What a robot primitive or move did.

    success: the motion completed and (pick) the hardware reports a grasp / (place, push) nothing failed;
    reason: "" on success, else a short code ("nothing_grasped", "protective_stop", ...); clamped: a commanded
    pose was moved into the safety box; stopped: "" or why the robot stopped (protective / emergency stop):
    the robot then refuses every motion until `resume()`.
    """

    success: bool
    reason: str = ""
    clamped: bool = False
    stopped: str = ""


@runtime_checkable
class Robot(Protocol):
    """A real arm: explicit lifecycle, pose queries, the paper's three primitives as Cartesian motions,
    grasp feedback. Implementations clamp every commanded pose to their safety box and cap speeds; a
    protective or emergency stop ends the motion as failed and the robot stays stopped (no motion is
    retried) until `resume()` is called after an operator has cleared it."""

    stopped: str  # "" while the robot may move, else why it stopped

    def connect(self) -> None:
        """Connect and check the controller is ready (running, normal safety mode); raises RobotError."""
        ...

    def disconnect(self) -> None:
        """Stop any motion and close the connections. Idempotent."""
        ...

    def tool_pose(self) -> np.ndarray:
        """The TCP pose (6,): x y z in metres and a rotation vector, robot base frame."""
        ...

    def move_to(self, pose: np.ndarray) -> MotionResult:
        """A linear move of the TCP to `pose` (clamped), at the free-space speed."""
        ...

    def go_home(self) -> MotionResult:
        """Move to the home pose (out of the camera's view)."""
        ...

    def push(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        """Closed tool down to (x, y, z), then push_distance_m along angle_rad, up, and home."""
        ...

    def pick(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        """Top-down grasp at the surface point (x, y, z), lift, home; success from the grasp sensor."""
        ...

    def place(self, x_m: float, y_m: float, z_m: float, angle_rad: float) -> MotionResult:
        """Lower the held object onto the surface point (x, y, z), release, home."""
        ...

    def drop(self, x_m: float, y_m: float, z_m: float) -> MotionResult:
        """Release the held object from above (x, y, z) (bin picking: into the destination bin), home."""
        ...

    def holding(self) -> bool:
        """Grasp feedback now: vacuum sensor on / fingers stopped wider than empty."""
        ...

    def resume(self) -> bool:
        """After an operator cleared a stop: True (and motion allowed again) if the controller is ready."""
        ...
