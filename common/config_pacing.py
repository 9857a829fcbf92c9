"""Checks across the replay and learner sections: settings each valid alone that stall a fleet together.

The replay server's samples-per-insert limiter (replay/ratelimiter.py) holds inserts while the learner is
behind; the learner (learner/gate.py) waits for learner.min_replay_size transitions and caps its updates per
insert. Some combinations wait on each other forever; the root Config refuses them with the numbers and the
fix. (They can only be checked where one config file serves both, as `romannet up` and the recipes do.)
A pre-fill from recordings (check_prefill) inserts before the learner samples at all: a ratio would hold it.
"""

from __future__ import annotations

import math

from .config_learner import LearnerConfig
from .config_replay import ReplayConfig
from .configbase import require


def inserts_before_first_sample(replay: ReplayConfig) -> float:
    """How many transitions the limiter admits before anything has been sampled (inf without a ratio)."""
    spi = replay.spi_limit
    if spi is None:
        return math.inf
    return replay.min_size_to_sample + math.floor(replay.spi_tolerance / spi + 1e-9)


def transitions_before_first_update(replay: ReplayConfig, learner: LearnerConfig) -> int:
    """How many transitions a run must make before the learner's first update: the replay serves no sample
    below replay.min_size_to_sample, and the learner asks for none below learner.min_replay_size."""
    return max(replay.min_size_to_sample, learner.min_replay_size)


def check_pacing(replay: ReplayConfig, learner: LearnerConfig) -> None:
    """Raise ConfigError for a replay/learner pair that deadlocks or can never sample."""
    require(learner.batch_size <= replay.max_batch_size, "learner.batch_size", learner.batch_size,
            f"must be <= replay.max_batch_size ({replay.max_batch_size}), the largest batch the replay server "
            "serves")
    spi = replay.spi_limit
    if spi is None:
        return
    admitted = inserts_before_first_sample(replay)
    require(learner.min_replay_size <= admitted, "learner.min_replay_size", learner.min_replay_size,
            f"must be <= {admitted:g}: the replay's samples_per_insert limiter admits replay.min_size_to_sample "
            f"({replay.min_size_to_sample}) + spi_tolerance / samples_per_insert ({replay.spi_tolerance:g} / "
            f"{spi:g}) transitions before the learner's first sample, so the learner would wait for "
            "transitions the actors cannot send; lower it or raise replay.spi_tolerance")
    if learner.max_updates_per_insert > 0:
        per_insert = learner.batch_size * learner.max_updates_per_insert
        require(per_insert >= spi, "learner.max_updates_per_insert", learner.max_updates_per_insert,
                f"times learner.batch_size ({learner.batch_size}) samples {per_insert:g} per insert, fewer than "
                f"replay.samples_per_insert ({spi:g}) the limiter waits for, so the actors and the learner "
                "would end up waiting on each other; raise it (or 0 = no cap) or lower samples_per_insert")


def check_prefill(replay: ReplayConfig) -> None:
    """Raise ConfigError where the replay's ratio limit would hold a pre-fill from recordings (learner --offline,
    up --from-recordings) forever: the learner samples only once every recorded transition is in."""
    spi = replay.spi_limit
    require(spi is None, "replay.samples_per_insert", replay.samples_per_insert,
            f"must be 0 (no ratio limit) to pre-fill the replay from recordings: the limiter admits "
            f"{inserts_before_first_sample(replay):g} transitions before the learner's first sample, and the "
            "learner samples only once the recordings are fed; pass --set replay.samples_per_insert=0")
