"""model.angle_bins: one Q map per pick/place yaw bin, decided by argmax, trained at the executed bin only."""

from __future__ import annotations

import math

import _learner_helpers as H
import numpy as np
import pytest
import torch

from romannet.bench.inference import synthetic_scene
from romannet.common.action import Action
from romannet.common.config import ExplorationConfig, ModelConfig
from romannet.common.errors import ConfigError
from romannet.common.model import (
    RoManNet,
    angle_bin,
    bin_angles,
    bin_rotations,
    decode_angle,
    parameter_count,
    preprocess,
    preprocess_batch,
)
from romannet.common.policy import InferenceEngine, decide, reference_maps, snap_to_bin
from romannet.learner.checkpoint import architecture

BINNED = ModelConfig(channels=8, residual_blocks=1, angle_bins=8, q_head_init="default", precision="fp32")


def test_bins_cover_half_a_turn_from_zero():
    theta = bin_angles(8)
    np.testing.assert_allclose(np.sort(np.degrees(theta)), [-67.5, -45, -22.5, 0, 22.5, 45, 67.5, 90], atol=1e-9)
    assert theta[0] == 0.0
    assert np.all((theta > -np.pi / 2) & (theta <= np.pi / 2))
    for k in (2, 3, 8, 16):
        for j, t in enumerate(bin_angles(k)):
            assert angle_bin(float(t), k) == j
            assert angle_bin(float(t) + math.pi, k) == j  # a parallel-jaw grasp is the same turned by pi
            assert angle_bin(float(t) - math.pi, k) == j


def test_angle_bin_is_the_nearest_bin():
    assert angle_bin(math.radians(10), 8) == 0
    assert angle_bin(math.radians(12), 8) == 1  # past the half-way 11.25 degrees
    assert angle_bin(math.radians(-80), 8) == 4  # nearest to 90 (= -90)
    assert angle_bin(math.radians(170), 8) == 0
    with pytest.raises(ValueError, match="finite"):
        angle_bin(float("nan"), 8)


def test_bin_rotations_decode_to_the_bin_yaws():
    for k in (2, 4, 8, 16):
        rot = bin_rotations(k)
        assert rot.dtype == np.float32 and rot.shape == (k, 2)
        decoded = decode_angle(rot[:, 0], rot[:, 1], "pick")
        np.testing.assert_allclose(decoded, bin_angles(k), atol=1e-6)  # pi/2 stays pi/2, not -pi/2


def test_config_validates_the_bin_count():
    assert ModelConfig().angle_bins == 0
    for bad in (1, -2, 65):
        with pytest.raises(ConfigError, match="model.angle_bins"):
            ModelConfig(angle_bins=bad)


def test_binned_nets_have_k_q_maps_and_no_rotation_head():
    model = RoManNet(BINNED, seed=0)
    plain = RoManNet(ModelConfig(channels=8, residual_blocks=1), seed=0)
    for p in ("pick", "place"):
        net = model.nets[p]
        assert net.rot_head is None and net.q_head.out_channels == 8
        assert not any("rot_head" in k or "bin_rotation" in k for k in net.state_dict())
        # 8 Q maps in place of 1 Q map + 2 rotation channels: (8 - 3) x (C + 1) more parameters
        assert parameter_count(net) - parameter_count(plain.nets[p]) == 5 * (8 + 1)
    assert model.nets["push"].rot_head is not None and model.nets["push"].q_head.out_channels == 1


def test_forward_is_the_best_bin_and_its_angle():
    model = RoManNet(BINNED, seed=1).eval()
    x = preprocess(*synthetic_scene(np.random.default_rng(0), 32, 32))
    with torch.no_grad():
        model.nets["pick"].q_head.bias.zero_()  # at init the bias alone would choose one bin everywhere
        q_bins = model.nets["pick"].forward_bins(x)
        q, rot = model.nets["pick"](x)
    assert q_bins.shape == (1, 8, 32, 32) and q.shape == (1, 32, 32) and rot.shape == (1, 2, 32, 32)
    torch.testing.assert_close(q, q_bins.max(dim=1).values)
    best = q_bins.argmax(dim=1)[0].numpy()
    angles = decode_angle(rot[0, 0].numpy(), rot[0, 1].numpy(), "pick")
    np.testing.assert_allclose(angles, bin_angles(8)[best], atol=1e-6)
    assert len(np.unique(best)) > 1  # the maps really differ per pixel


def test_engine_decides_as_the_reference():
    model = RoManNet(BINNED, seed=2).eval()
    with torch.no_grad():
        model.nets["pick"].q_head.bias.zero_()
    scenes = [synthetic_scene(np.random.default_rng(s), 64, 64) for s in range(3)]
    engine = InferenceEngine(model, BINNED)
    try:
        for scene in scenes:
            fast = engine.infer(*scene, ("push", "pick"))
            ref = reference_maps(model, *scene, ("push", "pick"))
            for p in ("push", "pick"):
                np.testing.assert_allclose(fast.q[p], ref.q[p], atol=2e-5)
            same = np.isclose(fast.angle["pick"], ref.angle["pick"], atol=1e-5)
            assert same.mean() > 0.99  # only near-ties between two bins may pick the other
            assert set(np.round(np.degrees(np.unique(fast.angle["pick"])), 3)) <= \
                set(np.round(np.degrees(bin_angles(8)), 3))
    finally:
        engine.close()


def test_bf16_engine_agrees_with_fp32_where_the_cpu_has_it():
    cfg = ModelConfig(channels=8, residual_blocks=1, angle_bins=8, q_head_init="default", precision="auto")
    model = RoManNet(cfg, seed=4).eval()
    engine = InferenceEngine(model, cfg)
    scene = synthetic_scene(np.random.default_rng(9), 64, 64)
    try:
        fast = engine.infer(*scene, ("pick",))
    finally:
        engine.close()
    ref = reference_maps(model, *scene, ("pick",))
    np.testing.assert_allclose(fast.q["pick"], ref.q["pick"], atol=2e-2)
    assert np.isclose(fast.angle["pick"], ref.angle["pick"], atol=1e-5).mean() > 0.9


def test_decisions_execute_a_bin_yaw_also_when_exploring():
    model = RoManNet(BINNED, seed=3).eval()
    scene = synthetic_scene(np.random.default_rng(5), 64, 64)
    rng = np.random.default_rng(0)
    cfg = ExplorationConfig(random_angle_prob=1.0)
    yaws = set(np.round(bin_angles(8), 9))
    for _ in range(20):
        a = decide(model, *scene, holding=False, explore_rate=1.0, rng=rng, primitives=("pick",),
                   exploration_cfg=cfg)
        assert round(a.angle_rad, 9) in yaws
    push = Action("push", 1, 2, 0.1234, 0.0)
    assert snap_to_bin(push, 8) is push
    pick = Action("pick", 1, 2, math.radians(50), 0.0)
    assert snap_to_bin(pick, 0) is pick
    assert snap_to_bin(pick, 8).angle_rad == pytest.approx(math.radians(45))


def test_training_moves_the_executed_bin_only():
    t = H.trainer(model=BINNED)
    tr = H.transition(primitive="pick", reward=1.0, done=True, row=7, col=19, angle_rad=math.radians(44))
    net = t.model.nets["pick"]
    x = preprocess_batch(tr.color_before[None], tr.depth_before[None])
    with torch.no_grad():
        before = net.forward_bins(x)[0, :, 7, 19].clone()  # train mode, as the step's forward pass
    stats = t.train_step([(tr, 1.0, 0)])
    executed = angle_bin(math.radians(44), 8)
    assert executed == 2
    assert stats.td_errors[0] == pytest.approx(abs(float(before[executed]) - 1.0), rel=1e-5)
    grad = net.q_head.weight.grad[:, :, 0, 0]
    assert grad[executed].abs().sum() > 0
    others = [k for k in range(8) if k != executed]
    assert torch.count_nonzero(grad[others]) == 0  # no label for the bins that were not executed
    assert torch.count_nonzero(net.q_head.bias.grad[others]) == 0


def test_training_pulls_the_executed_bin_toward_its_target():
    t = H.trainer(model=BINNED, lr=1e-3)
    tr = H.transition(primitive="pick", reward=1.0, done=True, row=7, col=19, angle_rad=0.0)
    errors = [t.train_step([(tr, 1.0, 0)]).td_errors[0] for _ in range(10)]
    assert max(errors[-3:]) < 0.5 * errors[0]


def test_saved_configs_before_the_field_are_rotation_heads():
    assert architecture({"channels": 32, "residual_blocks": 5, "rotation_harmonics": 2})["angle_bins"] == 0
    assert architecture(BINNED)["angle_bins"] == 8
