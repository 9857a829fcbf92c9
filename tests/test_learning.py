"""Learning test: on a tiny synthetic pick task, pick success goes from chance to >= 80 %.

The task: one object (a bright square, 6-10 px, 0.03-0.05 m high) at a random place on a 64x64 heightmap;
an episode is one pick, which succeeds iff the chosen pixel lies on the object (the angle does not matter).
The loop is the paper's Algorithm 1 in one process: act with common.policy.decide (LAE or argmax of the
current model) -> transition with R_tp from common.reward -> a real ReplayStore (fsync off) through the
ReplayClient protocol -> Trainer.train_step -> new priorities. Seeds fix everything (the store's sampling
included), so the run is deterministic. A small RoManNet (8 channels, 1 residual block) keeps it fast.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from romannet.common.action import Action
from romannet.common.config import ExplorationConfig, ModelConfig, RewardConfig, TaskConfig
from romannet.common.config_learner import LearnerConfig
from romannet.common.config_replay import ReplayConfig
from romannet.common.episode_rules import clutter_progress
from romannet.common.policy import decide
from romannet.common.reward import task_progress_reward
from romannet.common.wire import decode_transition
from romannet.common.wire_messages import TransitionMsg
from romannet.learner.trainer import Trainer
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.store import ReplayStore

logger = logging.getLogger(__name__)

SIZE = 64
TASK = TaskConfig(kind="clutter", use_push=False)  # PickNet only
# The paper's rotation head, which the Budget below was measured with.
MODEL = ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=1, precision="fp32")
REWARD = RewardConfig()
EXPLORATION = ExplorationConfig()


@dataclass(frozen=True)
class Budget:
    """The fixed training budget of the test.

    150 episodes, 2 updates each. lr is 10x the paper's 1e-4 so that the budget fits a CI minute; without
    gradient clipping that lr sits on the edge of divergence with the summed loss, and whether a seed
    diverges depends on the CPU's float kernels (on an Intel Xeon seed 0 reached 100 %; on an AMD EPYC seeds
    0 and 1 ended at 0 %, one with non-finite Q maps, and at lr 5e-4 two of seeds 0-4 still diverged).
    Clipping the gradient norm at 10 trains every seed measured: greedy success 98-100 % for seeds 0-4 on the
    AMD box (from 0-10 %), ~15 s each. fp32 here: at 8 channels bf16 is slower. One thread: an 8-channel net
    gains nothing from two, and two wait on each other when other work holds a core (10x slower steps).
    """

    episodes: int = 150
    updates_per_episode: int = 2
    eval_episodes: int = 50
    learner: LearnerConfig = LearnerConfig(lr=1e-3, max_grad_norm=10.0, batch_size=4, min_replay_size=8,
                                           precision="fp32", num_threads=1)


def scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(color uint8 (64, 64, 3), depth float32 (64, 64) m): one bright square on a dark, noisy floor."""
    color = rng.integers(20, 60, (SIZE, SIZE, 3), dtype=np.uint8)
    depth = np.zeros((SIZE, SIZE), dtype=np.float32)
    side = int(rng.integers(6, 11))
    r, c = (int(v) for v in rng.integers(0, SIZE - side + 1, 2))
    color[r:r + side, c:c + side] = rng.integers(180, 256, 3, dtype=np.uint8)
    depth[r:r + side, c:c + side] = rng.uniform(0.03, 0.05)
    return color, depth


def pick(color: np.ndarray, depth: np.ndarray, action: Action, episode: int,
         explore_rate: float) -> TransitionMsg:
    """Execute a pick: success iff the pixel is on the object, which then leaves the scene."""
    success = bool(depth[action.row, action.col] > REWARD.occupied_height_m)
    color_after, depth_after = color.copy(), depth.copy()
    if success:
        on = depth > 0
        color_after[on] = 40
        depth_after[on] = 0.0
    p_after = clutter_progress(depth_after, depth, REWARD.occupied_height_m)
    reward = task_progress_reward("pick", success, p_after, REWARD)
    return TransitionMsg(
        actor_id="test", episode_id=f"ep-{episode}", step=0, start_ns=0, end_ns=1, task="clutter",
        color_before=color, depth_before=depth, color_after=color_after, depth_after=depth_after,
        action=action, success=success, progress_before=0.0, progress_after=p_after, reward=reward, done=True,
        done_reason="picked" if success else "missed", holding_before=False, holding_after=False,
        policy_version=0, explore_rate=explore_rate)


class SeededReplayClient(InProcessReplayClient):
    """The in-process client with a seeded sampling generator (the store's default one is not seeded)."""

    def __init__(self, store: ReplayStore, seed: int):
        super().__init__(store)
        self.rng = np.random.default_rng(seed)

    def sample(self, batch_size, timeout_s=10.0):
        batch = self.store.sample(batch_size, timeout_s=timeout_s, rng=self.rng)
        items = tuple(replace(it, transition=decode_transition(it.transition)) for it in batch.items)
        return replace(batch, items=items)


def greedy_success(trainer: Trainer, n: int, seed: int) -> float:
    """Pick success of the argmax policy on n fresh scenes (the same scenes for every call with `seed`)."""
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(n):
        color, depth = scene(rng)
        a = decide(trainer.model, color, depth, False, 0.0, rng, TASK.primitives, EXPLORATION)
        hits += bool(depth[a.row, a.col] > 0)
    return hits / n


@dataclass
class Result:
    before: float  # greedy pick success before training, on the evaluation scenes
    after: float  # ... and after
    losses: list[float]  # per update
    train_success: list[bool]  # per training episode (exploring as LAE says)
    trainer: Trainer


def train(tmp_path, budget: Budget, seed: int = 0) -> Result:
    """Train within the budget and evaluate the greedy policy before and after."""
    threads = torch.get_num_threads()  # the Trainer sets budget.learner.num_threads process-wide
    try:
        return _train(tmp_path, budget, seed)
    finally:
        torch.set_num_threads(threads)


def _train(tmp_path, budget: Budget, seed: int) -> Result:
    torch.manual_seed(seed)
    trainer = Trainer(MODEL, budget.learner, REWARD, TASK, seed=seed, exploration_cfg=EXPLORATION)
    before = greedy_success(trainer, budget.eval_episodes, seed=10_000 + seed)
    rng = np.random.default_rng(seed)
    losses, train_success = [], []
    # Unpaced: this loop sets its own schedule of updates per episode (budget.learner).
    store = ReplayStore(ReplayConfig(capacity_items=10_000, min_size_to_sample=1, fsync=False,
                                     samples_per_insert=0.0, snapshot_every_s=0.0, snapshot_every_inserts=0),
                        tmp_path / "replay")
    try:
        client = SeededReplayClient(store, seed)
        for ep in range(budget.episodes):
            color, depth = scene(rng)
            rate = trainer.exploration.value
            action = decide(trainer.model, color, depth, False, rate, rng, TASK.primitives, EXPLORATION)
            transition = pick(color, depth, action, ep, rate)
            train_success.append(transition.success)
            client.insert(transition)
            if ep + 1 < budget.learner.min_replay_size:
                continue
            for _ in range(budget.updates_per_episode):
                batch = client.sample(budget.learner.batch_size)
                stats = trainer.train_step([(it.transition, it.is_weight, it.item_id) for it in batch.items])
                client.update_priorities(stats.priority_update())
                losses.append(stats.loss)
    finally:
        store.close()
    after = greedy_success(trainer, budget.eval_episodes, seed=10_000 + seed)
    return Result(before, after, losses, train_success, trainer)


def test_pick_success_goes_from_chance_to_80_percent(tmp_path):
    start = time.perf_counter()
    r = train(tmp_path, Budget())
    before, after = r.before, r.after
    logger.info("pick success %.2f -> %.2f in %.1f s", before, after, time.perf_counter() - start)
    assert before <= 0.2, f"the untrained net already picks {before:.0%}: the test would prove nothing"
    assert after >= 0.8, f"pick success after training is {after:.0%} (before: {before:.0%})"
