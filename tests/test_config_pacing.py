"""The replay/learner cross-checks (common/config_pacing.py) against the real rate limiter: the settings they
refuse are the ones where the actors and the learner wait on each other forever."""

from __future__ import annotations

import pytest

from romannet.common.config import load_config
from romannet.common.config_learner import LearnerConfig
from romannet.common.config_pacing import check_prefill, inserts_before_first_sample
from romannet.common.config_replay import ReplayConfig
from romannet.common.errors import ConfigError
from romannet.replay.ratelimiter import RateLimiter


def _limiter(replay: ReplayConfig) -> RateLimiter:
    return RateLimiter(replay.min_size_to_sample, replay.spi_limit, replay.spi_tolerance)


def _try(acquire) -> bool:  # type: ignore[no-untyped-def]
    try:
        acquire()
        return True
    except TimeoutError:
        return False


@pytest.mark.parametrize("min_size,spi,tol", [(1, 2.0, 8.0), (1, 2.0, 4.0), (64, 2.0, 8.0), (3, 0.5, 2.0),
                                              (5, 3.0, 7.5)])
def test_inserts_before_first_sample_is_what_the_limiter_admits(min_size: int, spi: float, tol: float) -> None:
    replay = ReplayConfig(min_size_to_sample=min_size, samples_per_insert=spi, spi_tolerance=tol,
                          max_batch_size=2)
    limiter = _limiter(replay)
    admitted = 0
    while admitted < 10_000 and _try(lambda: limiter.acquire_insert(0.0)):
        admitted += 1
    assert admitted == inserts_before_first_sample(replay)


def test_without_a_ratio_every_insert_is_admitted() -> None:
    assert inserts_before_first_sample(ReplayConfig(samples_per_insert=0.0)) == float("inf")


def test_samples_per_insert_0_is_no_ratio_limit_and_a_recipe_can_say_so() -> None:
    cfg = load_config(overrides=["replay.samples_per_insert=0"])
    assert cfg.replay.samples_per_insert == 0.0 and cfg.replay.spi_limit is None
    limiter = _limiter(cfg.replay)
    for _ in range(cfg.replay.min_size_to_sample + 1000):
        limiter.acquire_insert(0.0)


def _run_fleet(replay: ReplayConfig, learner: LearnerConfig, inserts_wanted: int) -> int:
    """Actors insert whenever the limiter lets them; the learner samples a batch whenever it holds
    min_replay_size transitions, the limiter lets it and its updates-per-insert cap allows (learner/gate.py).
    Returns the inserts made before neither side can move (or inserts_wanted)."""
    limiter = _limiter(replay)
    inserts = updates = 0
    while inserts < inserts_wanted:
        moved = False
        if _try(lambda: limiter.acquire_insert(0.0)):
            inserts += 1
            limiter.set_size(inserts)
            moved = True
        cap = learner.max_updates_per_insert * inserts if learner.max_updates_per_insert > 0 else float("inf")
        if inserts >= learner.min_replay_size and updates < cap and \
                _try(lambda: limiter.acquire_samples(learner.batch_size, 0.0)):
            updates += 1
            moved = True
        if not moved:
            break
    return inserts


def test_a_min_replay_size_above_what_the_limiter_admits_deadlocks_and_is_refused() -> None:
    replay = ReplayConfig(min_size_to_sample=1, samples_per_insert=2.0, spi_tolerance=4.0, max_batch_size=4)
    learner = LearnerConfig(batch_size=2, min_replay_size=4)
    assert _run_fleet(replay, learner, 100) == 3  # the learner waits for a 4th, the limiter holds it
    with pytest.raises(ConfigError, match=r"learner.min_replay_size.*must be <= 3.*raise replay.spi_tolerance"):
        load_config(overrides=["replay.min_size_to_sample=1", "replay.samples_per_insert=2.0",
                               "replay.spi_tolerance=4.0", "replay.max_batch_size=4", "learner.batch_size=2",
                               "learner.min_replay_size=4"])
    ok = ReplayConfig(min_size_to_sample=1, samples_per_insert=2.0, spi_tolerance=8.0, max_batch_size=4)
    assert _run_fleet(ok, learner, 100) == 100
    load_config(overrides=["replay.min_size_to_sample=1", "replay.samples_per_insert=2.0",
                           "replay.spi_tolerance=8.0", "replay.max_batch_size=4", "learner.batch_size=2",
                           "learner.min_replay_size=4"])


def test_an_update_cap_below_the_sampling_ratio_deadlocks_and_is_refused() -> None:
    replay = ReplayConfig(min_size_to_sample=4, samples_per_insert=4.0, spi_tolerance=8.0, max_batch_size=8)
    slow = LearnerConfig(batch_size=1, min_replay_size=4, max_updates_per_insert=2.0)  # 2 samples per insert
    assert _run_fleet(replay, slow, 1000) < 20
    with pytest.raises(ConfigError, match=r"learner.max_updates_per_insert.*samples 2 per insert, fewer than"):
        load_config(overrides=["replay.min_size_to_sample=4", "replay.samples_per_insert=4.0",
                               "replay.spi_tolerance=8.0", "replay.max_batch_size=8", "learner.batch_size=1",
                               "learner.min_replay_size=4", "learner.max_updates_per_insert=2.0"])
    enough = LearnerConfig(batch_size=1, min_replay_size=4, max_updates_per_insert=4.0)
    assert _run_fleet(replay, enough, 1000) == 1000


def test_a_learner_batch_larger_than_the_replay_serves_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"learner.batch_size.*replay.max_batch_size \(8\)"):
        load_config(overrides=["replay.max_batch_size=8", "learner.batch_size=16"])


def test_the_first_update_waits_for_the_larger_of_the_two_thresholds():
    from romannet.common.config_pacing import transitions_before_first_update

    replay, learner = ReplayConfig(min_size_to_sample=64), LearnerConfig(min_replay_size=32)
    assert transitions_before_first_update(replay, learner) == 64
    assert transitions_before_first_update(ReplayConfig(min_size_to_sample=8), learner) == 32


def test_a_prefill_from_recordings_is_refused_under_a_ratio_limit() -> None:
    """learner --offline and up --from-recordings feed every recording before the learner's first sample; the
    limiter admits inserts_before_first_sample of them, so a longer feed would wait forever."""
    check_prefill(ReplayConfig(samples_per_insert=0.0))
    paced = ReplayConfig(min_size_to_sample=4, samples_per_insert=2.0, spi_tolerance=8.0, max_batch_size=8)
    with pytest.raises(ConfigError, match=r"admits 8 transitions before the learner's first sample"):
        check_prefill(paced)
    assert inserts_before_first_sample(paced) == 8
