"""The learning rate over training: a pure function of the update count, so a resumed learner (whose update
count comes back from its checkpoint) continues the same schedule without any saved scheduler state."""

from __future__ import annotations


def lr_at(base_lr: float, updates_done: int, halve_every: int) -> float:
    """The rate of the next update after `updates_done` updates: `base_lr` halved once per `halve_every`
    updates done (0 = constant)."""
    if updates_done < 0:
        raise ValueError(f"updates_done must be >= 0, got {updates_done}")
    if halve_every <= 0:
        return base_lr
    return base_lr * 0.5 ** (updates_done // halve_every)
