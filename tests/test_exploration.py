"""Loss Adjusted Exploration, the epsilon schedule, action candidates and select_action."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from romannet.common.config import ExplorationConfig
from romannet.common.exploration import (
    ANGLE_RANGE_RAD,
    ExplorationRate,
    action_candidates,
    epsilon_greedy_rate,
    lae_f,
    lae_update,
    select_action,
)

CFG = ExplorationConfig()
H = W = 64


def peaks_map(peaks: dict[tuple[int, int], float], shape=(H, W)) -> np.ndarray:
    """A smooth float32 map with a Gaussian bump of the given height at each (row, col)."""
    rows, cols = np.indices(shape)
    q = np.zeros(shape, dtype=np.float32)
    for (r, c), height in peaks.items():
        q = np.maximum(q, height * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / 18.0).astype(np.float32))
    return q


def angle_maps(value_by_prim: dict[str, float], shape=(H, W)) -> dict[str, np.ndarray]:
    return {p: np.full(shape, v, dtype=np.float32) for p, v in value_by_prim.items()}


# ------------------------------------------------------------------------------------ LAE
def test_lae_f_at_zero_and_its_closed_form():
    assert lae_f(0.0) == 0.0
    a = abs(0.5 * 0.8) / 0.33
    assert lae_f(0.8) == pytest.approx((1 - math.exp(-a)) / (1 + math.exp(-a)), rel=1e-12)


@given(st.floats(0.0, 1e6), st.floats(0.0, 1e6))
def test_lae_f_is_monotone_bounded_and_symmetric(a, b):
    lo, hi = sorted((a, b))
    assert 0.0 <= lae_f(lo) <= lae_f(hi) <= 1.0
    assert lae_f(-a) == lae_f(a)


def test_lae_f_saturates_without_overflow_and_rejects_nan():
    assert lae_f(1e300) == 1.0
    assert lae_f(float("inf")) == 1.0
    assert lae_f(50.0) > 0.999999
    with pytest.raises(ValueError, match="NaN"):
        lae_f(float("nan"))
    with pytest.raises(ValueError, match="sigma"):
        lae_f(1.0, sigma=0.0)


@given(st.floats(0.0, 20.0), st.floats(0.0, 1.0))
def test_lae_converges_geometrically_to_f_of_a_constant_loss(loss, start):
    target = lae_f(loss, CFG.alpha, CFG.sigma)
    rate = start
    for t in range(1, 40):
        rate = lae_update(rate, loss, CFG)
        # E_t - f = (1 - beta)^t (E_0 - f)
        assert rate - target == pytest.approx((1 - CFG.beta) ** t * (start - target), abs=1e-12)
    assert rate == pytest.approx(target, abs=1e-4)


def test_lae_update_rejects_a_rate_outside_0_1():
    with pytest.raises(ValueError):
        lae_update(1.5, 0.1, CFG)


# ------------------------------------------------------------------------------------ epsilon greedy
def test_epsilon_schedule_matches_vpg():
    assert epsilon_greedy_rate(0, CFG) == 0.5
    assert epsilon_greedy_rate(1000, CFG) == pytest.approx(0.5 * 0.9998**1000)
    assert epsilon_greedy_rate(5000, CFG) == pytest.approx(0.5 * 0.9998**5000)  # ~0.184
    assert epsilon_greedy_rate(20000, CFG) == 0.1  # floored
    with pytest.raises(ValueError):
        epsilon_greedy_rate(-1, CFG)


# ------------------------------------------------------------------------------------ ExplorationRate
def test_exploration_rate_lae_follows_lae_update():
    rate = ExplorationRate(CFG)
    assert rate.value == CFG.initial_rate and rate.steps == 0
    expected = CFG.initial_rate
    for loss in (0.3, 2.0, 0.01):
        expected = lae_update(expected, loss, CFG)
        assert rate.update(loss) == pytest.approx(expected)
    assert rate.steps == 3 and rate.value == pytest.approx(expected)


def test_lae_floor_bounds_the_used_rate_but_not_the_recursion():
    floored, paper = ExplorationRate(replace(CFG, lae_min_rate=0.1)), ExplorationRate(replace(CFG, lae_min_rate=0.0))
    for _ in range(20):  # tiny losses: the paper's LAE decays toward 0
        assert floored.update(1e-4) == pytest.approx(max(paper.update(1e-4), 0.1))
    assert paper.value < 0.01 and floored.value == 0.1
    # The recursion underneath is the paper's: one large loss lifts both to the same unfloored value.
    assert floored.update(5.0) == pytest.approx(paper.update(5.0)) and paper.value > 0.1
    assert floored.state_dict() == paper.state_dict()
    with pytest.raises(ValueError, match="lae_min_rate"):
        replace(CFG, lae_min_rate=1.5)


def test_exploration_rate_epsilon_greedy_follows_the_update_count():
    rate = ExplorationRate(replace(CFG, policy="epsilon_greedy"))
    assert rate.value == 0.5
    for _ in range(10):
        rate.update(123.0)  # the loss does not matter
    assert rate.value == pytest.approx(epsilon_greedy_rate(10, CFG))


def test_state_dict_round_trip():
    rate = ExplorationRate(CFG)
    for loss in (0.5, 0.2):
        rate.update(loss)
    state = rate.state_dict()
    assert set(state) == {"value", "steps"}
    assert type(state["value"]) is float and type(state["steps"]) is int
    restored = ExplorationRate(CFG)
    restored.load_state_dict(state)
    assert restored.state_dict() == state
    assert restored.update(0.7) == rate.update(0.7)
    with pytest.raises(ValueError):
        restored.load_state_dict({"value": 2.0, "steps": 1})
    with pytest.raises(ValueError):
        restored.load_state_dict({"value": 0.2, "steps": -1})


# ------------------------------------------------------------------------------------ candidates
def test_candidates_are_the_local_maxima_across_nets_best_first():
    q = {"push": peaks_map({(10, 10): 0.3, (40, 50): 0.9}), "pick": peaks_map({(20, 30): 0.6, (50, 10): 0.1})}
    cands = action_candidates(q, k=10, min_distance_px=5)
    assert [(p, r, c) for p, r, c, _ in cands[:4]] == [
        ("push", 40, 50), ("pick", 20, 30), ("push", 10, 10), ("pick", 50, 10)]
    assert [v for *_, v in cands[:4]] == pytest.approx([0.9, 0.6, 0.3, 0.1], rel=1e-6)
    # the rest are the far background's (~0) plateaus: non-strict maxima, spaced by min_distance_px
    assert len(cands) <= 2 * 10 and all(v < 1e-3 for *_, v in cands[4:])
    assert action_candidates(q, k=2, min_distance_px=5) == cands[:4]  # k per net


def test_every_allowed_net_contributes_candidates_whatever_its_q_offset():
    # PickNet reads higher everywhere (e.g. untrained offsets): exploration must still try pushes.
    q = {"push": peaks_map({(10, 10): 0.3, (40, 50): 0.2}), "pick": 5.0 + peaks_map({(20, 30): 0.6})}
    cands = action_candidates(q, k=3, min_distance_px=5)
    prims = [p for p, *_ in cands]
    assert prims.count("push") == 3 and prims.count("pick") == 3
    assert ("push", 10, 10) in [(p, r, c) for p, r, c, _ in cands]


@given(st.integers(0, 2**32 - 1), st.integers(1, 20), st.integers(1, 8))
def test_candidates_are_at_most_k_true_local_maxima(seed, k, distance):
    rng = np.random.default_rng(seed)
    q = {"push": rng.random((32, 32)).astype(np.float32), "pick": rng.random((32, 32)).astype(np.float32)}
    cands = action_candidates(q, k, distance)
    assert 1 <= len(cands) <= 2 * k
    assert all(sum(p == prim for p, *_ in cands) <= k for prim in q)
    values = [v for *_, v in cands]
    assert values == sorted(values, reverse=True)
    for prim, r, c, v in cands:
        window = q[prim][max(r - distance, 0):r + distance + 1, max(c - distance, 0):c + distance + 1]
        assert v == q[prim][r, c] == window.max()
    assert cands[0][3] == max(q["push"].max(), q["pick"].max())


def test_plateaus_give_spaced_deterministic_candidates():
    q = {"pick": np.zeros((20, 20), np.float32)}  # a flat map: every pixel is a local maximum
    cands = action_candidates(q, k=4, min_distance_px=5)
    assert [(r, c) for _, r, c, _ in cands] == [(0, 0), (0, 5), (0, 10), (0, 15)]
    tie = {"push": peaks_map({(30, 30): 0.5}), "pick": peaks_map({(30, 30): 0.5})}
    assert [p for p, *_ in action_candidates(tie, 2, 5)][:2] == ["push", "pick"]  # ties: PRIMITIVES order


def test_candidates_reject_bad_maps():
    with pytest.raises(ValueError, match="non-finite"):
        action_candidates({"pick": np.full((8, 8), np.nan, np.float32)}, 3, 2)
    with pytest.raises(ValueError, match="subset"):
        action_candidates({"poke": np.zeros((8, 8), np.float32)}, 3, 2)
    with pytest.raises(ValueError, match="shape"):
        action_candidates({"push": np.zeros((8, 8)), "pick": np.zeros((8, 9))}, 3, 2)


# ------------------------------------------------------------------------------------ select_action
Q = {"push": peaks_map({(10, 10): 0.3, (40, 50): 0.7}), "pick": peaks_map({(20, 30): 0.9, (50, 10): 0.2})}
ANGLES = angle_maps({"push": 0.25, "pick": -0.5})


def test_zero_rate_always_takes_the_argmax():
    rng = np.random.default_rng(0)
    for _ in range(200):
        action = select_action(Q, ANGLES, 0.0, CFG, rng)
        assert (action.primitive, action.row, action.col, action.explored) == ("pick", 20, 30, False)
        assert action.angle_rad == pytest.approx(-0.5) and action.q_value == pytest.approx(0.9)


def test_argmax_reads_the_chosen_nets_angle_and_q_at_the_pixel():
    angles = {"push": np.zeros((H, W), np.float32), "pick": np.zeros((H, W), np.float32)}
    angles["pick"][20, 30] = 1.2
    action = select_action(Q, angles, 0.0, CFG, np.random.default_rng(0))
    assert action.angle_rad == pytest.approx(1.2) and action.q_value == float(Q["pick"][20, 30])


@pytest.mark.parametrize("rate", [0.1, 0.5, 0.9])
def test_exploration_frequency_matches_the_rate(rate):
    rng = np.random.default_rng(1234)
    n = 4000
    explored = sum(select_action(Q, ANGLES, rate, CFG, rng).explored for _ in range(n))
    assert abs(explored / n - rate) < 4 * math.sqrt(rate * (1 - rate) / n)  # 4 binomial standard deviations


def test_exploring_picks_uniformly_among_candidates_and_reports_their_q():
    rng = np.random.default_rng(7)
    cands = {(p, r, c): v for p, r, c, v in action_candidates(Q, CFG.top_k, CFG.candidate_min_distance_px)}
    counts = dict.fromkeys(cands, 0)
    n = 2000
    for _ in range(n):
        action = select_action(Q, ANGLES, 1.0, CFG, rng)
        assert action.explored
        key = (action.primitive, action.row, action.col)
        assert action.q_value == cands[key]
        counts[key] += 1
    expected = n / len(cands)
    assert all(abs(c - expected) < 4 * math.sqrt(expected) for c in counts.values())


def test_explored_angles_are_uniform_in_the_primitive_range_or_from_the_map():
    cfg = replace(CFG, random_angle_prob=1.0)
    rng = np.random.default_rng(3)
    drawn: dict[str, list[float]] = {"push": [], "pick": []}
    for _ in range(1000):
        action = select_action(Q, ANGLES, 1.0, cfg, rng)
        drawn[action.primitive].append(action.angle_rad)
    for prim, angles in drawn.items():
        low, high = ANGLE_RANGE_RAD[prim]
        assert all(low <= a < high for a in angles)
        assert min(angles) < low + 0.2 * (high - low) and max(angles) > high - 0.2 * (high - low)
    assert ANGLE_RANGE_RAD["push"] == (-math.pi, math.pi)
    assert ANGLE_RANGE_RAD["pick"] == ANGLE_RANGE_RAD["place"] == (-math.pi / 2, math.pi / 2)
    from_map = replace(CFG, random_angle_prob=0.0)
    for _ in range(50):
        action = select_action(Q, ANGLES, 1.0, from_map, rng)
        assert action.angle_rad == pytest.approx({"push": 0.25, "pick": -0.5}[action.primitive])


def test_same_seed_same_actions():
    def run(seed):
        rng = np.random.default_rng(seed)
        return [select_action(Q, ANGLES, 0.5, CFG, rng) for _ in range(100)]
    assert run(11) == run(11)
    assert run(11) != run(12)


def test_select_action_with_only_the_allowed_nets():
    q = {"place": peaks_map({(5, 6): 0.4})}
    action = select_action(q, angle_maps({"place": 0.1}), 0.0, CFG, np.random.default_rng(0))
    assert (action.primitive, action.row, action.col) == ("place", 5, 6)


def test_select_action_rejects_bad_input():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="explore_rate"):
        select_action(Q, ANGLES, 1.5, CFG, rng)
    with pytest.raises(ValueError, match="angle maps missing"):
        select_action(Q, angle_maps({"push": 0.0}), 0.0, CFG, rng)
    bad = {"push": Q["push"].copy(), "pick": Q["pick"]}
    bad["push"][3, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        select_action(bad, ANGLES, 0.0, CFG, rng)
