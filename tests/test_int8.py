"""int8 decisions (model.precision = "int8"): the engine against the fp32 reference, weight swaps, the near-tie
reruns, and how "auto" and bad values resolve."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from romannet.bench.inference import synthetic_scene
from romannet.common import policy
from romannet.common.config import ExplorationConfig, ModelConfig, load_config
from romannet.common.errors import ConfigError
from romannet.common.int8net import (
    Int8Net,
    _QConv,
    act_qparams,
    int8_ops_available,
    int8_weight_bits,
    quantize_u8,
    quantize_weight,
)
from romannet.common.model import RoManNet, load_tensors, preprocess, state_dict_to_tensors
from romannet.common.policy import InferenceEngine, decide, reference_maps, resolve_inference_precision
from romannet.common.weights_wire import resolve_wire_dtype
from romannet.learner.checkpoint import read_package

MODELS = Path(__file__).resolve().parents[1] / "models"

needs_int8 = pytest.mark.skipif(not int8_ops_available(), reason="no oneDNN int8 convolutions in this build/CPU")

# Small nets with PyTorch's Q-head init, so Q maps differ measurably between nets.
SMALL = ModelConfig(channels=16, residual_blocks=2, q_head_init="default", precision="int8")
H = W = 64
EXPLORATION = ExplorationConfig()
PRIMS = ("push", "pick")


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(11)
    return [synthetic_scene(rng, H, W) for _ in range(16)]


def _engine(cfg: ModelConfig = SMALL, seed: int = 0) -> tuple[RoManNet, InferenceEngine]:
    model = RoManNet(cfg, seed=seed).eval()
    return model, InferenceEngine(model, cfg)


def _choice(action):
    return action.primitive, action.row, action.col


@needs_int8
def test_qconv_matches_fp32_convolution_within_rounding():
    torch.manual_seed(0)
    w, b = torch.randn(16, 8, 3, 3) * 0.2, torch.randn(16) * 0.1
    x = torch.randn(1, 8, 12, 12).contiguous(memory_format=torch.channels_last)  # signed: a zero point
    acc = torch.randn(1, 16, 12, 12).contiguous(memory_format=torch.channels_last)
    # 8-bit weights saturate oneDNN's int16 pair sums without VNNI (an error of ~10x tol under ONEDNN_MAX_CPU_ISA=AVX2)
    conv, q = _QConv(w, b, 1, 1, policy.weight_bits_here()), act_qparams(float(x.min()), float(x.max()))
    assert 0 < q.zero_point < 255
    with torch.inference_mode():
        xq = quantize_u8(x, q)
        plain, relu = conv(xq, q), conv(xq, q, relu=True)
        summed = conv(xq, q, add_to=acc.clone())
    ref = F.conv2d(x, w, b, padding=1)
    tol = 0.02 * float(ref.abs().max())
    assert plain.dtype == torch.float32
    assert (plain - ref).abs().max() < tol
    assert (relu - ref.relu()).abs().max() < tol
    assert (summed - (ref + acc)).abs().max() < tol


@needs_int8
def test_int8_decisions_agree_with_fp32_reference_on_fixed_inputs(scenes):
    """With near-tie reruns every decision is the fp32 reference's (the benchmark asks >= 0.99); int8 alone
    keeps Q maps within a few % of their spread (at 64 px; ~0.5 % at 224) and nearly every decision."""
    model, eng = _engine()
    try:
        assert eng.precision == "int8" and all(isinstance(n, Int8Net) for n in eng.nets.values())
        int8_only = 0
        for color, depth in scenes:
            ref, ref_maps = decide(model, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION,
                                   True)
            eng.tie_share = policy.INT8_TIE_SHARE
            fast = decide(eng, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION)
            assert _choice(fast) == _choice(ref)
            eng.tie_share = 0.0  # int8 alone
            alone, maps = decide(eng, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION, True)
            int8_only += _choice(alone) == _choice(ref)
            for p in PRIMS:
                assert np.abs(maps.q[p] - ref_maps.q[p]).max() < 0.06 * ref_maps.q[p].std()
        assert int8_only >= len(scenes) - 1
    finally:
        eng.close()


@needs_int8
def test_trained_net_decisions_agree_with_fp32_reference(scenes):
    """The shipped clutter model (trained nets amplify int8's error 15-40x over random-init ones, relative to
    their maps): with near-tie reruns sized by each net's measured int8 error, every decision is fp32's."""
    tensors, _, cfg = read_package(MODELS / "clutter")
    model = RoManNet(cfg.model).eval()
    load_tensors(model, tensors)
    model.eval()
    eng = InferenceEngine(model, replace(cfg.model, precision="int8", num_threads=0))
    try:
        assert all(0.0 < net.error_spread < float("inf") for net in eng.nets.values())
        for color, depth in scenes:
            ref = decide(model, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION)
            fast = decide(eng, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION)
            assert _choice(fast) == _choice(ref)
    finally:
        eng.close()


def test_weights_take_seven_bits_without_vnni():
    """oneDNN's int8 kernels without VNNI add u8 x s8 products in pairs in int16: 255 x 127 x 2 saturates."""
    assert int8_weight_bits(frozenset({"avx2", "avx512_vnni"}), "") == 8
    assert int8_weight_bits(frozenset({"avx2", "amx_int8"}), "") == 8
    assert int8_weight_bits(frozenset({"avx2", "avx_vnni"}), "AVX2_VNNI") == 8
    assert int8_weight_bits(frozenset({"avx2"}), "") == 7
    assert int8_weight_bits(frozenset({"avx2", "avx512_vnni", "amx_int8"}), "AVX2") == 7  # emulated AVX2 CPU
    assert int8_weight_bits(frozenset({"avx512_vnni"}), "avx512_core") == 7
    w = torch.randn(4, 3, 3, 3)
    for bits, top in ((8, 127), (7, 63)):
        q, scales = quantize_weight(w, bits)
        assert int(q.abs().max()) == top
        assert (q.float() * scales.view(-1, 1, 1, 1) - w).abs().max() <= scales.max() / 2 + 1e-6
    assert 255 * 63 * 2 < 2**15 <= 255 * 127 * 2


@needs_int8
def test_near_ties_are_rerun_with_the_exact_nets(scenes, monkeypatch):
    model, eng = _engine()
    try:
        monkeypatch.setattr(eng, "tie_share", 1e9)  # every decision a near tie: all decided in fp32
        for color, depth in scenes[:3]:
            _, maps = decide(eng, color, depth, False, 0.0, np.random.default_rng(0), PRIMS, EXPLORATION, True)
            ref = reference_maps(model, color, depth, PRIMS)
            for p in PRIMS:
                np.testing.assert_allclose(maps.q[p], ref.q[p], atol=2e-5)
        assert eng.exact_reruns == 3
        a = np.array([[1.0, 0.0], [0.5, 0.2]], np.float32)
        low = a - 0.5
        eng.tie_share = 0.01
        eng.nets["push"].error_spread, eng.nets["pick"].error_spread = 1.0, 0.5
        assert eng.tie_tolerance(("pick",)) == 0.005 and eng.tie_tolerance(("push", "pick")) == 0.01
        assert eng.near_ties({"push": low, "pick": a}) == ()
        close = a.copy()
        close[1, 1] = 1.0 - 1e-3
        assert eng.near_ties({"push": low, "pick": close}) == ("pick",)
        assert eng.near_ties({"pick": a - 0.1, "push": close}) == ("push",)
        tied = low + 0.5 - 1e-3  # the runner-up in the other net: both rerun
        assert eng.near_ties({"push": tied, "pick": a}) == ("push", "pick")
        eng.tie_share = 0.0  # fp32 and bf16 engines never rerun
        assert eng.near_ties({"push": tied, "pick": a}) == ()
    finally:
        eng.close()


@needs_int8
def test_overflowing_activations_fall_back_to_the_fp32_net(scenes):
    """Finite weights whose activations overflow (a diverged learner's): int8 cannot quantise infinity, so the
    net answers as the fp32 engine does, whose maps the actor's NaN check (NonFiniteQError) already sees."""
    model, eng = _engine()
    try:
        tensors = state_dict_to_tensors(model)
        for name in ("nets.pick.conv1.weight", "nets.pick.conv2.weight"):
            tensors[name] = tensors[name] * 1e30
        eng.load_state(tensors)
        with torch.inference_mode():
            x = eng.nets["pick"].exact.layers[0](preprocess(*scenes[0]))
            assert not torch.isfinite(eng.nets["pick"].exact.layers[1](x)).all()
        fast = eng.infer(*scenes[0], ("pick",))
        exact = eng.infer(*scenes[0], ("pick",), exact=True)
    finally:
        eng.close()
    np.testing.assert_array_equal(fast.q["pick"], exact.q["pick"])


@needs_int8
@pytest.mark.parametrize("cfg", [
    ModelConfig(channels=8, residual_blocks=1, q_head_init="default", precision="int8"),
    ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=2, q_head_init="default", precision="int8"),
    ModelConfig(channels=4, residual_blocks=1, rotation_harmonics=2, q_head_init="default", precision="int8"),
], ids=["one-harmonic-folded-head", "two-harmonics-folded-head", "fp32-tail"])
def test_int8_heads_match_the_reference(cfg, scenes):
    """The heads folded into conv6 (fewer outputs than channels) or FastNet's tail (as many outputs or more)."""
    model, eng = _engine(cfg, seed=4)
    try:
        assert (eng.nets["pick"].head is None) == (1 + 2 * cfg.rotation_harmonics >= cfg.channels)
        for color, depth in scenes[:4]:
            fast = eng.infer(color, depth, ("push", "pick"))
            ref = reference_maps(model, color, depth, ("push", "pick"))
            for p in ("push", "pick"):
                assert np.abs(fast.q[p] - ref.q[p]).max() < 0.05 * ref.q[p].std()
            best = np.unravel_index(np.argmax(ref.q["pick"]), ref.q["pick"].shape)
            diff = np.angle(np.exp(2j * (fast.angle["pick"][best] - ref.angle["pick"][best])))
            assert abs(diff) < 0.1
    finally:
        eng.close()


def test_precision_auto_is_bf16_where_native_else_int8_with_avx2_else_fp32(monkeypatch):
    """bf16 where the CPU has it; else int8 where oneDNN runs it with AVX2 or more (on a real AVX2 CPU it took
    0.62-0.71 of fp32's decision time, docs/benchmarks.md); else fp32."""
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(policy.torch.backends.mkldnn, "is_available", lambda: True)
    monkeypatch.setattr(policy, "int8_ops_available", lambda: True)
    monkeypatch.setattr(policy, "cpu_flags", lambda: frozenset({"avx2", "avx512_bf16", "amx_bf16"}))
    assert resolve_inference_precision("auto") == "bf16"
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx2")  # oneDNN limited to AVX2: no native bf16 there
    assert not policy.native_bf16() and policy.int8_wins()
    assert resolve_inference_precision("auto") == "int8"
    assert resolve_inference_precision("fp32") == "fp32"  # by name, as asked
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "avx")  # no AVX2: int8 would not win
    assert not policy.int8_wins()
    assert resolve_inference_precision("auto") == "fp32"
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA")
    monkeypatch.setattr(policy, "cpu_flags", lambda: frozenset({"avx2"}))  # a plain AVX2 CPU
    assert resolve_inference_precision("auto") == "int8"
    monkeypatch.setattr(policy, "int8_ops_available", lambda: False)  # e.g. an aarch64 build
    assert resolve_inference_precision("auto") == "fp32"


def test_int8_precision_needs_the_int8_ops(monkeypatch):
    monkeypatch.setattr(policy, "int8_ops_available", lambda: False)  # e.g. an aarch64 build
    with pytest.raises(ValueError, match="int8"):
        resolve_inference_precision("int8")
    with pytest.raises(ValueError, match="'auto', 'fp32', 'bf16' or 'int8'"):
        resolve_inference_precision("int4")


def test_bad_precision_is_a_config_error():
    with pytest.raises(ConfigError, match="model.precision"):
        ModelConfig(precision="int4")
    with pytest.raises(ConfigError, match="model.precision"):
        load_config(overrides=['model.precision="fp16"'])
    assert load_config(overrides=['model.precision="int8"']).model.precision == "int8"


def test_int8_actors_get_fp32_weights_on_the_wire():
    assert resolve_wire_dtype("auto", "int8") == "fp32"
    assert resolve_wire_dtype("bf16", "int8") == "bf16"  # an explicit setting wins


def test_bf16_prepacked_convolutions_need_avx512_or_avx_ne_convert(monkeypatch):
    # Without them oneDNN refuses to prepack bf16 weights, so a bf16 engine there runs plain aten convolutions
    # (tests/test_weights_wire.py's bf16 engine runs on such a CPU).
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(policy, "cpu_flags", lambda: frozenset({"avx2", "fma"}))
    assert not policy.bf16_prepack_runs()
    monkeypatch.setattr(policy, "cpu_flags", lambda: frozenset({"avx2", "avx_ne_convert"}))
    assert policy.bf16_prepack_runs()
    monkeypatch.setattr(policy, "cpu_flags", lambda: frozenset({"avx2", "avx512bw", "avx512vl", "avx512dq"}))
    assert policy.bf16_prepack_runs()
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert not policy.bf16_prepack_runs()
