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
    """A manipulation environment: the PyBullet simulator now, real robots later."""

    primitives: tuple[str, ...]

    def reset(self, seed: int | None = None) -> Observation:
        """Start a new episode (a new scene from `seed`) and return the first observation."""
        ...

    def step(self, action: Action) -> StepResult:
        """Execute one primitive; a failure is a StepResult with success False, never an exception."""
        ...

    def close(self) -> None:
        """Release the simulator / disconnect the robot. Idempotent."""
        ...


@runtime_checkable
class ReplayClient(Protocol):
    """Access to the prioritized replay server (Zenoh or in-process)."""

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        """Insert; returns only after the server has written the transition durably (or raises)."""
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
