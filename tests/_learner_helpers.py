"""Helpers for the learner tests: small configs and synthetic transitions with controlled fields."""

from __future__ import annotations

from typing import Any

import numpy as np

from romannet.common.action import Action
from romannet.common.config import ModelConfig, RewardConfig, TaskConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.wire_messages import TransitionMsg
from romannet.learner.trainer import Trainer

# PyTorch's Q-head init: the exact-value tests need Q maps well away from 0 (the default "small" head starts
# within a few hundredths of it); the paper's rotation head (cos, sin), which their targets and learning rates
# were set for.
SMALL_MODEL = ModelConfig(channels=8, residual_blocks=1, q_head_init="default", rotation_harmonics=1)


def transition(size: int = 32, seed: int = 0, primitive: str = "pick", row: int = 10, col: int = 12,
               angle_rad: float = 0.3, success: bool = True, reward: float = 1.0, done: bool = False,
               holding_before: bool = False, holding_after: bool = False, **kw: Any) -> TransitionMsg:
    """A valid transition on random size x size heightmaps (before and after differ)."""
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8)
    depths = rng.uniform(0.0, 0.05, (2, size, size)).astype(np.float32)
    fields: dict[str, Any] = dict(
        actor_id="sim-0", episode_id=f"ep-{seed}", step=0, start_ns=0, end_ns=1, task="clutter",
        color_before=colors[0], depth_before=depths[0], color_after=colors[1], depth_after=depths[1],
        action=Action(primitive, row, col, angle_rad, 0.0), success=success, progress_before=0.0,
        progress_after=1.0 if success else 0.0, reward=reward, done=done, done_reason="cleared" if done else "",
        holding_before=holding_before, holding_after=holding_after, policy_version=0, explore_rate=0.5)
    fields.update(kw)
    return TransitionMsg(**fields)


def trainer(seed: int = 0, task: TaskConfig | None = None, model: ModelConfig = SMALL_MODEL,
            **learner: Any) -> Trainer:
    """A small Trainer (fp32 unless precision is given, so exact-value tests are exact)."""
    learner.setdefault("precision", "fp32")
    return Trainer(model, LearnerConfig(**learner), RewardConfig(), task or TaskConfig(), seed=seed)


def batch(n: int = 3, size: int = 32, seed: int = 0) -> list[tuple[TransitionMsg, float, int]]:
    """A mixed batch: pick success, push failure, pick success at episode end, ..."""
    kinds = [dict(primitive="pick", success=True, reward=1.0),
             dict(primitive="push", success=False, reward=0.0, angle_rad=-2.0),
             dict(primitive="pick", success=True, reward=0.5, done=True, angle_rad=1.2)]
    items = []
    for i in range(n):
        kw = kinds[i % len(kinds)]
        items.append((transition(size, seed=seed * 100 + i, row=3 + 2 * i, col=20 - i, **kw),
                      1.0 - 0.1 * i, seed * 100 + i))
    return items
