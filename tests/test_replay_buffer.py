"""Prioritized replay: sampling math, eviction, idempotency, priority updates, rate limiting, config."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from _replay_helpers import cfg, tr

from romannet.common.config_replay import ReplayConfig
from romannet.common.errors import ConfigError
from romannet.common.interfaces import ReplayClient
from romannet.common.wire import (
    PriorityUpdateMsg,
    SampleBatchMsg,
    SampleItem,
    TransitionMsg,
    decode_sample_batch,
    encode_transition,
)
from romannet.replay.batchcodec import encode_sample_batch_fast
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.prioritized import RankBasedSampler, annealed_beta, is_weights, rank_probabilities
from romannet.replay.ratelimiter import RateLimiter
from romannet.replay.store import ReplayStore

# chi-square critical value for df = 19 at significance 0.001 (scipy.stats.chi2.ppf(0.999, 19) = 43.820).
CHI2_CRIT_DF19_P001 = 43.820


# ------------------------------------------------------------------------------------------ pure math
def test_rank_probabilities_follow_the_power_law() -> None:
    p = rank_probabilities(5, 0.7)
    assert p.sum() == pytest.approx(1.0)
    assert np.all(np.diff(p) < 0)
    assert p[0] / p[1] == pytest.approx(2**0.7)
    np.testing.assert_allclose(rank_probabilities(4, 0.0), 0.25)  # alpha 0 = uniform


def test_sampling_matches_rank_distribution_chi_square() -> None:
    n, draws, alpha = 20, 200_000, 0.7
    rng = np.random.default_rng(1234)
    sampler = RankBasedSampler(64, alpha)
    priorities = rng.permutation(n).astype(float) + 0.5  # distinct: ranks are unambiguous
    for item_id, prio in enumerate(priorities):
        sampler.add(item_id, prio)
    ids, probs = sampler.sample(draws, rng)
    ranks = np.empty(n, dtype=int)
    ranks[np.argsort(-priorities)] = np.arange(1, n + 1)
    expected_p = rank_probabilities(n, alpha)[ranks - 1]
    np.testing.assert_allclose(probs, expected_p[ids])  # the reported P(i) is the true one
    observed = np.bincount(ids, minlength=n)
    expected = draws * expected_p
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert chi2 < CHI2_CRIT_DF19_P001, chi2


def test_is_weights_formula_and_normalisation() -> None:
    probs = np.array([0.5, 0.1, 0.02])
    w = is_weights(probs, 10, 0.4)
    raw = (10 * probs) ** -0.4
    np.testing.assert_allclose(w, raw / raw.max())
    assert w.max() == 1.0 and w.argmax() == 2  # the least likely item weighs most
    np.testing.assert_allclose(is_weights(probs, 10, 0.0), 1.0)


def test_beta_anneals_linearly_to_one() -> None:
    assert annealed_beta(0.5, 0, 100) == 0.5
    assert annealed_beta(0.5, 50, 100) == pytest.approx(0.75)
    assert annealed_beta(0.5, 100, 100) == 1.0 and annealed_beta(0.5, 10**6, 100) == 1.0
    assert annealed_beta(0.5, 0, 0) == 1.0


def test_sampler_updates_reorder_and_skip_unknown_ids() -> None:
    s = RankBasedSampler(4, 1.0)
    for i, p in enumerate([1.0, 2.0, 3.0]):
        s.add(i, p)
    assert s.ranked()[0].tolist() == [2, 1, 0]
    assert s.update([0, 7, -1], [10.0, 1.0, 1.0]) == 1
    assert s.ranked()[0].tolist() == [0, 2, 1]
    s.remove(2)
    s.add(6, 5.0)  # reuses slot 2
    assert s.ranked()[0].tolist() == [0, 6, 1] and s.update([2], [1.0]) == 0


def test_cached_max_priority_matches_brute_force() -> None:
    # max_priority is cached (O(1) per insert); random adds, removals and updates must not make it stale.
    rng = np.random.default_rng(3)
    s = RankBasedSampler(16, 0.7)
    held: dict[int, float] = {}
    next_id = 0
    for _ in range(3000):
        op = rng.integers(3)
        if op == 0 and len(held) < 16:
            while next_id - 16 in held:  # the slot of id - 16 must be free first
                s.remove(next_id - 16)
                del held[next_id - 16]
            p = float(rng.choice([0.5, 1.0, 2.0, rng.uniform(0, 3)]))
            s.add(next_id, p)
            held[next_id] = p
            next_id += 1
        elif op == 1 and held:
            victim = int(rng.choice(list(held)))
            assert s.remove(victim)
            del held[victim]
        elif held:
            ids = [int(i) for i in rng.choice(list(held), size=int(rng.integers(1, 4)))]
            prios = [float(rng.uniform(0, 3)) for _ in ids]
            s.update(ids, prios)
            held.update(zip(ids, prios, strict=True))  # a repeated id: the last value wins
        assert s.max_priority(default=-1.0) == (max(held.values()) if held else -1.0)


# -------------------------------------------------------------------------------------------- store
@pytest.fixture
def store(tmp_path):
    with ReplayStore(cfg(), tmp_path) as s:
        yield s


def test_insert_sample_and_in_process_client(store: ReplayStore) -> None:
    acks = [store.insert(tr(i, priority=float(i + 1))) for i in range(5)]
    assert [a.status for a in acks] == ["accepted"] * 5 and [a.item_id for a in acks] == list(range(5))
    batch = store.sample(8, rng=np.random.default_rng(0))
    assert batch.buffer_size == 5 and len(batch.items) == 8
    for item in batch.items:
        assert isinstance(item.transition, bytes) and 0 < item.probability <= 1 and 0 < item.is_weight <= 1
    assert max(it.is_weight for it in batch.items) == 1.0
    client = InProcessReplayClient(store)
    assert isinstance(client, ReplayClient)
    decoded = client.sample(2)
    assert all(isinstance(it.transition, TransitionMsg) for it in decoded.items)
    assert client.stats()["size"] == 5
    # The server's path: the same draw, already encoded as the SampleBatch reply.
    raw = store.sample_encoded(8, rng=np.random.default_rng(0), request_id="r-1")
    got = decode_sample_batch(bytes(raw))
    # (IS weights differ: beta anneals with every sampled batch.)
    same_draw = tuple(SampleItem(a.item_id, a.probability, b.is_weight, a.transition)
                      for a, b in zip(batch.items, got.items, strict=True))
    assert bytes(raw) == encode_sample_batch_fast(SampleBatchMsg("r-1", same_draw, 5))


def test_idempotent_inserts_return_the_original_id(store: ReplayStore) -> None:
    first = store.insert(tr(3))
    again = store.insert(tr(3), encoded=encode_transition(tr(3)))
    assert again.status == "duplicate" and again.item_id == first.item_id
    assert store.insert(tr(3, episode="ep-2")).status == "accepted"  # another episode: another key
    results = []
    threads = [threading.Thread(target=lambda: results.append(store.insert(tr(9)))) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert sorted(a.status for a in results) == ["accepted"] + ["duplicate"] * 5
    assert len({a.item_id for a in results}) == 1
    stats = store.stats()
    assert stats["size"] == 3 and stats["duplicates"] == 6


def test_new_items_get_initial_priority_else_current_max(store: ReplayStore) -> None:
    store.insert(tr(0, priority=2.0))
    store.insert(tr(1, priority=7.5))
    item = store.insert(tr(2)).item_id
    assert store._sampler.priority(item) == 7.5
    store.update_priorities(PriorityUpdateMsg((0,), (9.0,)))
    assert store._sampler.priority(store.insert(tr(3)).item_id) == 9.0


def test_eviction_by_items_oldest_first_and_updates_of_evicted_ids_ignored(tmp_path) -> None:
    with ReplayStore(cfg(capacity_items=4), tmp_path) as s:
        for i in range(6):
            s.insert(tr(i, priority=1.0))
        ids, _ = s._sampler.items()
        assert ids.tolist() == [2, 3, 4, 5]
        assert s.update_priorities(PriorityUpdateMsg((0, 1, 3), (5.0, 5.0, 5.0))) == 1
        assert s.stats()["priority_updates_ignored"] == 2
        assert s.insert(tr(0)).status == "accepted"  # an evicted key may come again


def test_eviction_by_bytes_oldest_first(tmp_path) -> None:
    sizes = [len(encode_transition(tr(i, size=64, seed=i))) for i in range(3)]
    with ReplayStore(cfg(capacity_bytes=1 << 20, max_item_bytes=1 << 20), tmp_path) as s:
        budget = 1 << 20
        n = 0
        while True:
            s.insert(tr(n, size=64, seed=n % 3))
            n += 1
            stats = s.stats()
            if stats["evicted"]:
                break
        assert stats["bytes"] <= budget and stats["oldest_item_id"] == stats["evicted"]
        assert stats["bytes"] + sizes[0] + 100 > budget  # evicted only what it had to


def test_oversized_insert_is_rejected_and_counted(tmp_path) -> None:
    with ReplayStore(cfg(max_item_bytes=1024), tmp_path) as s:
        ack = s.insert(tr(0, size=64))
        assert ack.status == "rejected" and "max_item_bytes" in ack.detail
        s.record_rejection("undecodable")
        assert s.stats()["rejected"] == {"oversized": 1, "undecodable": 1}


def test_stats_report_policy_lag_histogram_and_actors(store: ReplayStore) -> None:
    store.insert(tr(0, actor="a", policy_version=3, priority=1.0))
    store.insert(tr(1, actor="b", policy_version=7, priority=4.0))
    st = store.stats()
    assert st["policy_lag"]["latest_policy_version"] == 7 and st["policy_lag"]["max"] == 4
    assert st["per_actor"] == {"a": {"held": 1, "inserted": 1}, "b": {"held": 1, "inserted": 1}}
    assert sum(st["priority_histogram"]["counts"]) == 2 and st["top_priorities"][0]["item_id"] == 1


# ------------------------------------------------------------------------------------- rate limiting
def test_sampling_waits_for_min_size_and_is_released_by_inserts(tmp_path) -> None:
    with ReplayStore(cfg(min_size_to_sample=3), tmp_path) as s:
        s.insert(tr(0))
        with pytest.raises(TimeoutError, match="min_size_to_sample 3"):
            s.sample(1, timeout_s=0.05)
        got = []
        sampler = threading.Thread(target=lambda: got.append(s.sample(1, timeout_s=10)))
        sampler.start()
        time.sleep(0.05)
        assert not got
        s.insert(tr(1))
        s.insert(tr(2))
        sampler.join(10)
        assert got and got[0].buffer_size == 3


def test_samples_per_insert_blocks_inserts_until_sampled(tmp_path) -> None:
    # spi 1, tolerance 2 (window [-1, 3]), batches of 1: after min size 2 an insert needs samples.
    with ReplayStore(cfg(min_size_to_sample=2, samples_per_insert=1.0, spi_tolerance=1.0,
                         max_batch_size=1), tmp_path) as s:
        for i in range(3):
            s.insert(tr(i))
        with pytest.raises(TimeoutError, match="an insert"):
            s.insert(tr(3), timeout_s=0.05)
        done = []
        inserter = threading.Thread(target=lambda: done.append(s.insert(tr(3), timeout_s=10)))
        inserter.start()
        time.sleep(0.05)
        assert not done
        s.sample(1)
        inserter.join(10)
        assert done and done[0].status == "accepted"
        s.sample(1)
        s.sample(1)
        with pytest.raises(TimeoutError, match="samples"):
            s.sample(1, timeout_s=0.05)


def test_limiter_counts_batches_reverb_style() -> None:
    lim = RateLimiter(min_size_to_sample=1, samples_per_insert=2.0, tolerance=4.0)
    lim.acquire_insert(0)
    lim.set_size(1)
    lim.acquire_samples(4, 0)  # d: 2 - 4 = -2 >= 2 - 4
    with pytest.raises(TimeoutError):
        lim.acquire_samples(1, 0)
    lim.close()


@pytest.mark.parametrize(("kwargs", "field"), [
    (dict(samples_per_insert=4.0, spi_tolerance=10.0, max_batch_size=32), "replay.spi_tolerance"),
    (dict(min_size_to_sample=2000, capacity_items=1000), "replay.min_size_to_sample"),
    (dict(samples_per_insert=-1.0), "replay.samples_per_insert"),
    (dict(alpha=-1.0), "replay.alpha"),
])
def test_deadlocking_or_invalid_configs_are_refused(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        ReplayConfig(**kwargs)
    assert err.value.field == field and "must" in str(err.value)
    if field == "replay.spi_tolerance":
        assert "deadlock" in str(err.value) and ">= 18" in str(err.value)
