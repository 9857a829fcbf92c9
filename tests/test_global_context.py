"""model.global_context: every pixel's Q sees the whole scene, in training windows and in every inference engine."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from romannet.common.config import ModelConfig
from romannet.common.int8net import int8_ops_available
from romannet.common.model import GRConvNet, RoManNet, preprocess
from romannet.common.policy import InferenceEngine, reference_maps
from romannet.learner.crop import crop_origin

SMALL = ModelConfig(channels=8, residual_blocks=1, precision="fp32")
CTX = dataclasses.replace(SMALL, global_context=True)


def _trained_context(net: GRConvNet, seed: int = 0) -> GRConvNet:
    """A net whose context branch adds something (a fresh one adds exactly zero)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        net.context.out.weight.copy_(torch.randn(net.context.out.weight.shape, generator=gen) * 0.5)
        net.context.out.bias.copy_(torch.randn(net.context.out.bias.shape, generator=gen) * 0.5)
    return net


def test_a_fresh_net_with_the_context_is_the_plain_net():
    plain, ctx = RoManNet(SMALL, seed=3).eval(), RoManNet(CTX, seed=3).eval()
    x = torch.randn(2, 4, 64, 64)
    with torch.no_grad():
        for p in ("push", "pick", "place"):
            q0, r0 = plain.nets[p](x)
            q1, r1 = ctx.nets[p](x)
            torch.testing.assert_close(q1, q0, atol=0, rtol=0)
            torch.testing.assert_close(r1, r0, atol=0, rtol=0)
    assert set(ctx.state_dict()) - set(plain.state_dict()) == {
        k for k in ctx.state_dict() if ".context." in k} != set()


def test_a_pixels_q_changes_with_the_scene_beyond_its_receptive_field():
    # The trunk sees 56 px either side of a pixel: a cube 150 px away changes nothing without the branch,
    # and changes the Q of the far corner with it.
    torch.manual_seed(0)
    plain = GRConvNet(8, 1).eval()
    ctx = _trained_context(GRConvNet(8, 1, global_context=True).eval())
    ctx.load_state_dict({**plain.state_dict(), **{k: v for k, v in ctx.state_dict().items() if "context" in k}})
    depth = np.zeros((224, 224), np.float32)
    color = np.zeros((224, 224, 3), np.uint8)
    stacked = depth.copy()
    stacked[190:210, 190:210] = 0.08  # a stack of two 4 cm cubes, far from pixel (10, 10)
    with torch.no_grad():
        qa, qb = (plain(preprocess(color, d))[0][0, 10, 10] for d in (depth, stacked))
        ca, cb = (ctx(preprocess(color, d))[0][0, 10, 10] for d in (depth, stacked))
    assert float(qa) == pytest.approx(float(qb), abs=1e-6)
    assert abs(float(ca) - float(cb)) > 1e-3


def test_a_training_window_with_the_whole_scene_gives_the_whole_maps_q():
    torch.manual_seed(1)
    net = _trained_context(GRConvNet(8, 1, global_context=True).eval(), seed=1)
    x = torch.randn(1, 4, 224, 224)
    with torch.no_grad():
        whole, _ = net(x)
        for row, col in [(112, 112), (3, 220)]:
            r0, c0 = crop_origin((224, 224), row, col, 128)
            window, _ = net(x[:, :, r0:r0 + 128, c0:c0 + 128], x)
            alone, _ = net(x[:, :, r0:r0 + 128, c0:c0 + 128])
            got = window[0, row - r0, col - c0]
            torch.testing.assert_close(got, whole[0, row, col], atol=1e-5, rtol=0)
            assert abs(float(alone[0, row - r0, col - c0] - whole[0, row, col])) > 1e-4  # the window alone is not


@pytest.mark.parametrize("precision", ["fp32", "bf16", "int8"])
def test_every_inference_engine_adds_the_context(precision):
    if precision == "int8" and not int8_ops_available():
        pytest.skip("this PyTorch build has no int8 convolutions")
    cfg = dataclasses.replace(CTX, precision=precision)
    model = RoManNet(cfg, seed=5).eval()
    for net in model.nets.values():
        _trained_context(net, seed=2)
    rng = np.random.default_rng(0)
    color = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    depth = np.zeros((64, 64), np.float32)
    depth[20:40, 10:30] = 0.05
    eng = InferenceEngine(model, cfg)
    try:
        fast = eng.infer(color, depth, ("pick", "place"))
        ref = reference_maps(model, color, depth, ("pick", "place"))
        for p in ("pick", "place"):
            tol = 1e-4 if eng.precision == "fp32" else 0.05 * float(ref.q[p].std()) + 1e-3
            assert np.abs(fast.q[p] - ref.q[p]).max() < tol
    finally:
        eng.close()


def test_window_training_reads_the_whole_scene_and_trains_the_branch():
    import _learner_helpers as H

    model = dataclasses.replace(CTX, rotation_harmonics=1)
    t = H.trainer(model=model, train_crop_px=32, lr=1e-2, loss_reduction="mean")
    item = (H.transition(64, seed=1, row=50, col=9, reward=1.0, done=True), 1.0, 0)
    seen = []
    branch = t.model.nets["pick"].context
    hook = branch.register_forward_hook(lambda _m, args, _out: seen.append(tuple(args[0].shape)))
    before = branch.out.weight.detach().clone()
    try:
        t.train_step([item])
    finally:
        hook.remove()
    assert seen and seen[0][-2:] == (64, 64)  # the whole 64 px heightmap, not the 32 px window
    assert not torch.equal(branch.out.weight, before)  # the branch learns from its first step
