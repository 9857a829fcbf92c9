"""Not repeating a failed action on a scene it did not change: the greedy policy's loop breaker.

    memory = FailureMemory.for_task(cfg)      # one per episode: exploration.failure_memory_px, the task
    action = decide(..., avoid=memory)         # decide takes memory.masks(its nets, the heightmap shape)
    memory.record(action, success, p_before, p_after)  # a success clears it; memory.reset() at a new episode

A greedy policy that is not learning sees nearly the same heightmap after a pick that moved nothing, so it
chooses the same pixel again and again until the episode ends on consecutive failures. The paper's test
protocol escapes by training within the run (VPG's test-time learning); a robot running frozen weights
needs the rule at decision time: pixels within radius_px of an action of the same primitive that failed
since the last success are not chosen (masked_q sinks them below every other pixel, and exploration
draws among the rest). Any success changed the scene, so it clears the memory; on stacking, a pick that
took a cube off the stack counts as a failure, and putting it back clears nothing (FailureMemory.record).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from .action import Action
from .config import Config
from .reward import progress_reversed


def failure_masks(failed: Iterable[tuple[str, int, int]], primitives: Iterable[str], shape: tuple[int, int],
                  radius_px: int) -> dict[str, np.ndarray] | None:
    """{primitive: bool (h, w), False within radius_px of one of its failed (primitive, row, col)}; None
    when nothing is masked. A map that would lose every pixel keeps them all (the policy must act)."""
    failed = list(failed)
    if radius_px <= 0 or not failed:
        return None
    rows, cols = np.ogrid[0:shape[0], 0:shape[1]]
    out: dict[str, np.ndarray] = {}
    for prim in primitives:
        mask = np.ones(shape, dtype=bool)
        for p, r, c in failed:
            if p == prim:
                mask &= (rows - r) ** 2 + (cols - c) ** 2 > radius_px ** 2
        out[prim] = mask if mask.any() else np.ones(shape, dtype=bool)
    return out if any(not m.all() for m in out.values()) else None


def masked_q(q: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """q with the masked-out pixels set just below its smallest valid value (finite, so the argmax and the
    local-maximum search work unchanged)."""
    if mask.all():
        return q
    floor = float(q[mask].min()) - 1.0
    return np.where(mask, q, np.float32(floor)).astype(q.dtype, copy=False)


@dataclass
class FailureMemory:
    """The failed actions of the current episode since its last success (module docstring)."""

    radius_px: int
    # Stacking: P counts cubes on the stack, which a pick can take off again (the rule in record). Clutter's P
    # is an occupied share that a push can lower and a pick win back; kept there it lowered pick success at 30
    # blocks from 66.5 % to 62.2 % (models/clutter, 10 runs), so there a success clears the memory as before.
    track_progress: bool = False
    tolerance: float = 0.0  # a change of P within it is none (reward.progress_tolerance: depth noise)
    failed: list[tuple[str, int, int]] = field(default_factory=list)
    best_progress: float | None = None  # the highest task progress P seen in the episode

    @classmethod
    def for_task(cls, cfg: Config) -> FailureMemory:
        """The memory an episode under `cfg` uses: exploration.failure_memory_px, progress tracked on stacking
        alone (the field's comment), with the reward's reversal tolerance."""
        return cls(cfg.exploration.failure_memory_px, track_progress=cfg.task.kind == "stacking",
                   tolerance=cfg.reward.progress_tolerance)

    def reset(self) -> None:
        """A new episode: nothing failed yet."""
        self.failed.clear()
        self.best_progress = None

    def record(self, action: Action, success: bool, progress_before: float | None = None,
               progress_after: float | None = None) -> None:
        """Remember a failed action; a success changed the scene, so it clears what was remembered.

        With track_progress and the task progress P before and after the action (StepResult): an action that
        lowered P (a cube taken off the stack) is remembered as a failure, and a success that only won back P
        lost since (putting that cube back) clears nothing, so the greedy policy does not take the same cube
        off again and again. A reversal is the reward's (common.reward.progress_reversed, within `tolerance`)."""
        moved = self.track_progress and progress_before is not None and progress_after is not None
        reversed_ = moved and progress_reversed(progress_before, progress_after, self.tolerance)
        restored = (moved and self.best_progress is not None
                    and progress_before + self.tolerance < progress_after <= self.best_progress + self.tolerance)
        if moved:
            self.best_progress = max(progress_after, progress_before, self.best_progress or 0.0)
        if success and not reversed_:
            if not restored:
                self.failed.clear()
        elif self.radius_px > 0:
            self.failed.append((action.primitive, action.row, action.col))

    def masks(self, primitives: Iterable[str], shape: tuple[int, int]) -> dict[str, np.ndarray] | None:
        """The pixels the next decision may choose (failure_masks), None when all of them."""
        return failure_masks(self.failed, primitives, shape, self.radius_px)
