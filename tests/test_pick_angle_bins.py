"""model.pick_angle_bins: a pick Q per pixel and closing angle (harmonics of the angle), chosen together, trained
at the executed angle."""

from __future__ import annotations

import math

import _learner_helpers as H
import numpy as np
import pytest
import torch

from romannet.common.config import ExplorationConfig, ModelConfig, load_config_text
from romannet.common.errors import ConfigError
from romannet.common.grasp_clearance import (
    GripperFootprint,
    PickClearance,
    angle_bin,
    bin_angles,
    clear_picks,
)
from romannet.common.model import ANGLE_HARMONICS, RoManNet, angle_basis, preprocess
from romannet.common.policy import InferenceEngine, decide, reference_maps
from romannet.common.scenes import synthetic_scene

BINS = 16
SMALL_BINS = ModelConfig(channels=8, residual_blocks=1, q_head_init="default", pick_angle_bins=BINS,
                         precision="fp32")
RG2 = GripperFootprint(travel_m=0.055, pick_depth_m=0.03, tip_floor_m=0.006)


def _scene(seed: int = 0, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    return synthetic_scene(np.random.default_rng(seed), size, size)


def test_the_pick_net_has_one_q_map_per_closing_angle_and_the_maps_take_the_best() -> None:
    model = RoManNet(SMALL_BINS, seed=1).eval()
    color, depth = _scene()
    with torch.no_grad():
        q, rot = model.nets["pick"](preprocess(color, depth))
        push_q, _ = model.nets["push"](preprocess(color, depth))
    assert q.shape == (1, BINS, 64, 64) and push_q.shape == (1, 64, 64)  # push keeps one Q per pixel
    assert model.nets["pick"].q_head.out_channels == 1 + 2 * ANGLE_HARMONICS
    assert "nets.pick.q_basis" not in model.state_dict()  # fixed, not a weight
    maps = reference_maps(model, color, depth, ("push", "pick"))
    bins = maps.q_bins["pick"]
    np.testing.assert_allclose(bins, q[0].numpy(), atol=1e-6)
    np.testing.assert_array_equal(maps.q["pick"], bins.max(axis=0))
    np.testing.assert_array_equal(maps.angle["pick"], bin_angles(BINS)[bins.argmax(axis=0)])
    assert "push" not in maps.q_bins


@pytest.mark.parametrize("precision", ["fp32", "bf16", "int8"])
def test_the_actors_engine_computes_the_same_per_angle_maps(precision: str) -> None:
    model = RoManNet(SMALL_BINS, seed=2).eval()
    color, depth = _scene(3)
    ref = reference_maps(model, color, depth, ("push", "pick"))
    cfg = ModelConfig(channels=8, residual_blocks=1, q_head_init="default", pick_angle_bins=BINS, precision=precision)
    engine = InferenceEngine(RoManNet(SMALL_BINS, seed=2), cfg)
    try:
        fast = engine.infer(color, depth, ("push", "pick"))
    finally:
        engine.close()
    spread = float(np.ptp(ref.q_bins["pick"]))
    tolerance = 1e-5 if engine.precision == "fp32" else 0.02 * spread
    np.testing.assert_allclose(fast.q_bins["pick"], ref.q_bins["pick"], atol=tolerance)
    np.testing.assert_allclose(fast.q["push"], ref.q["push"], atol=max(tolerance, 1e-5))
    agree = (fast.angle["pick"] == ref.angle["pick"]).mean()
    assert agree > (0.999 if engine.precision == "fp32" else 0.9)


def test_the_decision_takes_the_best_clear_pixel_and_angle_together() -> None:
    res = 0.005
    hm = np.zeros((64, 64), np.float32)
    hm[28:36, 28:36] = 0.04  # a 4 cm block with a taller neighbour on +x: closing along x is not clear
    hm[28:36, 44:50] = 0.06
    color = np.zeros((64, 64, 3), np.uint8)
    clearance = PickClearance(RG2, res, BINS)
    clear = clear_picks(hm, res, RG2, BINS)
    model = RoManNet(SMALL_BINS, seed=0)
    # The net's own favourite: closing along x (bin 0: a bias of 1.5 on cos 2a), which the neighbour blocks.
    with torch.no_grad():
        model.nets["pick"].q_head.bias.copy_(torch.tensor([0.0, 1.5, 0.0, 0.0, 0.0]))
    maps = reference_maps(model, color, hm, ("pick",))
    greedy = decide(model, color, hm, False, 0.0, np.random.default_rng(0), ("pick",), ExplorationConfig(),
                    clearance=clearance)
    k = int(angle_bin(np.array(greedy.angle_rad), BINS))
    assert clear[k, greedy.row, greedy.col]
    best = np.where(clear, maps.q_bins["pick"], -np.inf)
    assert maps.q_bins["pick"][k, greedy.row, greedy.col] == pytest.approx(best.max())
    assert greedy.angle_rad == pytest.approx(k * math.pi / BINS)
    assert not clear[0, greedy.row, greedy.col] or k == 0  # bin 0 was the best where it is clear
    explored = [decide(model, color, hm, False, 1.0, np.random.default_rng(s), ("pick",),
                       ExplorationConfig(random_angle_prob=0.0), clearance=clearance) for s in range(8)]
    for a in explored:
        assert clear[angle_bin(np.array(a.angle_rad), BINS), a.row, a.col], a
    # Without the rule the argmax is over every angle: the net's favourite angle everywhere.
    plain = decide(model, color, hm, False, 0.0, np.random.default_rng(0), ("pick",), ExplorationConfig())
    assert plain.angle_rad == pytest.approx(0.0)


def test_the_q_per_angle_is_its_harmonics_at_each_angle() -> None:
    basis = angle_basis(BINS).numpy() * math.sqrt(1 + ANGLE_HARMONICS)  # unit rows
    a = np.arange(BINS) * math.pi / BINS
    np.testing.assert_allclose(basis[:, 0], 1.0)
    np.testing.assert_allclose(basis[:, 1:3], np.stack([np.cos(2 * a), np.sin(2 * a)], 1), atol=1e-6)
    np.testing.assert_allclose(basis[:, 3:5], np.stack([np.cos(4 * a), np.sin(4 * a)], 1), atol=1e-6)
    model = RoManNet(SMALL_BINS, seed=4).eval()
    color, depth = _scene(5)
    seen = []
    model.nets["pick"].q_head.register_forward_hook(lambda module, args, out: seen.append(out))
    with torch.no_grad():
        q, _ = model.nets["pick"](preprocess(color, depth))
    coeffs = seen[0]
    assert coeffs.shape == (1, 1 + 2 * ANGLE_HARMONICS, 64, 64)
    expected = np.einsum("kj,jhw->khw", basis, coeffs[0].numpy()) / math.sqrt(1 + ANGLE_HARMONICS)
    np.testing.assert_allclose(q[0].numpy(), expected, atol=1e-5)


def test_a_pick_at_one_angle_trains_the_nearby_angles_too() -> None:
    """Every pick trains the pixel's value and its angle preference together: a success at one angle raises
    the Q of the angles a few degrees off it, not only its own."""
    t = H.trainer(model=ModelConfig(channels=8, residual_blocks=1, pick_angle_bins=BINS), lr=0.002)
    item = [(H.transition(primitive="pick", seed=0, row=10, col=12, angle_rad=5 * math.pi / BINS, reward=1.0,
                          done=True), 1.0, 0)]
    before = reference_maps(t.model, item[0][0].color_before, item[0][0].depth_before, ("pick",)).q_bins["pick"]
    for _ in range(10):
        t.train_step(item)
    after = reference_maps(t.model, item[0][0].color_before, item[0][0].depth_before, ("pick",)).q_bins["pick"]
    gain = after[:, 10, 12] - before[:, 10, 12]
    assert gain[5] > 0.3 and gain[4] > 0.5 * gain[5] and gain[6] > 0.5 * gain[5]


def test_successes_at_one_angle_and_failures_at_another_teach_which_angle_to_pick() -> None:
    # The recipe's small Q head init: the angles never tried stay near 0, below a learned success.
    t = H.trainer(model=ModelConfig(channels=8, residual_blocks=1, pick_angle_bins=BINS), lr=0.002)
    good, bad = 3 * math.pi / BINS, 11 * math.pi / BINS
    items = [(H.transition(primitive="pick", seed=0, row=10, col=12, angle_rad=good, reward=1.0, done=True), 1.0, 0),
             (H.transition(primitive="pick", seed=0, row=10, col=12, angle_rad=bad, success=False, reward=0.0,
                           done=True), 1.0, 1)]
    for _ in range(80):
        t.train_step(items)
    color, depth = items[0][0].color_before, items[0][0].depth_before
    maps = reference_maps(t.model, color, depth, ("pick",))
    assert maps.q_bins["pick"][3, 10, 12] > maps.q_bins["pick"][11, 10, 12] + 0.5
    assert abs(maps.angle["pick"][10, 12] - good) <= math.pi / BINS + 1e-6  # the best angle: the good one's bin or next


def test_the_bootstrap_is_the_best_q_over_pixels_and_angles() -> None:
    t = H.trainer(model=SMALL_BINS, bootstrap_clip=False)
    with torch.no_grad():  # the pick net's maps far above the push net's, highest at one angle
        t.model.nets["pick"].q_head.bias.copy_(torch.tensor([4.0, 0.0, 0.0, 1.2, 0.5]))
    tr = H.transition(primitive="push", reward=0.2, done=False, seed=4)
    v = t.next_state_values([tr])[0]
    t.model.eval()
    with torch.no_grad():
        x = preprocess(tr.color_after, tr.depth_after)
        expected = max(float(t.model.nets["pick"](x)[0].max()), float(t.model.nets["push"](x)[0].max()))
    assert v == pytest.approx(expected, rel=1e-5)
    assert v > 2.5


def test_the_config_field_and_the_clearance_bins() -> None:
    assert ModelConfig().pick_angle_bins == 0  # one Q per pixel, the angle from the rotation head
    with pytest.raises(ConfigError, match="model.pick_angle_bins"):
        load_config_text("[model]\npick_angle_bins = 12\n")
    cfg = load_config_text('[model]\npick_angle_bins = 8\n[exploration]\npick_clearance = true\npick_angle = "net"\n')
    rule = PickClearance.for_config(cfg)
    assert rule is not None and rule.bins == 8  # judged on the net's own angles
    assert PickClearance.for_config(load_config_text("[exploration]\npick_clearance = true\n")).bins == 16
