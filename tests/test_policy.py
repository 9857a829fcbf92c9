"""The decision path: which nets run, argmax/holding behaviour, and the fast engine against fp32."""

import numpy as np
import pytest
import torch

from romannet.bench.inference import synthetic_scene
from romannet.common import policy
from romannet.common.config import ExplorationConfig, ModelConfig
from romannet.common.errors import DecodeError
from romannet.common.int8net import int8_ops_available
from romannet.common.model import RoManNet, preprocess, state_dict_to_tensors
from romannet.common.policy import (
    FastNet,
    InferenceEngine,
    PolicyMaps,
    decide,
    fused_ops_available,
    nets_to_run,
    reference_maps,
    resolve_precision,
)

# PyTorch's Q-head init (the default "small" head starts within a few hundredths of 0), so Q maps differ
# measurably between nets and comparisons at atol 1e-3 mean something.
TORCH_INIT = ModelConfig(q_head_init="default")

H, W = 64, 64
EXPLORATION = ExplorationConfig()


@pytest.fixture(scope="module")
def model() -> RoManNet:
    return RoManNet(TORCH_INIT, seed=0).eval()


@pytest.fixture(scope="module")
def engine(model) -> InferenceEngine:
    eng = InferenceEngine(model)  # precision "auto": bf16 where native, else int8 with AVX2, else fp32
    yield eng
    eng.close()


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(3)
    return [synthetic_scene(rng, H, W) for _ in range(12)]


def _count_forward_calls(model: RoManNet) -> tuple[dict[str, int], list]:
    calls = {p: 0 for p in model.nets}
    handles = [net.register_forward_hook(lambda *_, p=p: calls.__setitem__(p, calls[p] + 1))
               for p, net in model.nets.items()]
    return calls, handles


class _Counting:
    def __init__(self, fn, calls, name):
        self.fn, self.calls, self.name = fn, calls, name

    def __call__(self, x):
        self.calls[self.name] += 1
        return self.fn(x)


@pytest.mark.parametrize("holding, primitives, expected", [
    (False, ("push", "pick"), ("push", "pick")),
    (False, ("push", "pick", "place"), ("push", "pick")),
    (False, ("pick", "place"), ("pick",)),
    (True, ("push", "pick", "place"), ("place",)),
    (True, ("pick", "place"), ("place",)),
])
def test_nets_to_run(holding, primitives, expected):
    assert nets_to_run(holding, primitives) == expected


def test_nets_to_run_rejects_impossible_state():
    with pytest.raises(ValueError, match="holding"):
        nets_to_run(True, ("push", "pick"))


@pytest.mark.parametrize("holding, primitives, expected", [
    (False, ("push", "pick", "place"), {"push": 1, "pick": 1, "place": 0}),
    (False, ("pick", "place"), {"push": 0, "pick": 1, "place": 0}),
    (True, ("push", "pick", "place"), {"push": 0, "pick": 0, "place": 1}),
])
def test_reference_decide_runs_only_allowed_nets(model, scenes, holding, primitives, expected):
    calls, handles = _count_forward_calls(model)
    try:
        action, maps = decide(model, *scenes[0], holding, 0.0, np.random.default_rng(0), primitives, EXPLORATION,
                              return_maps=True)
    finally:
        for h in handles:
            h.remove()
    assert calls == expected
    assert set(maps.q) == set(maps.angle) == {p for p, n in expected.items() if n}
    assert action.primitive in maps.q


@pytest.mark.parametrize("holding, primitives, expected", [
    (False, ("push", "pick"), {"push": 1, "pick": 1, "place": 0}),
    (False, ("pick",), {"push": 0, "pick": 1, "place": 0}),
    (True, ("pick", "place"), {"push": 0, "pick": 0, "place": 1}),
])
def test_engine_decide_runs_only_allowed_nets(model, scenes, holding, primitives, expected, monkeypatch):
    eng = InferenceEngine(model)
    calls = {p: 0 for p in eng.nets}
    for p in list(eng.nets):
        monkeypatch.setitem(eng.nets, p, _Counting(eng.nets[p], calls, p))
    try:
        decide(eng, *scenes[1], holding, 0.0, np.random.default_rng(0), primitives, EXPLORATION)
    finally:
        eng.close()
    assert calls == expected


def test_holding_gives_place_action(engine, scenes):
    for color, depth in scenes[:3]:
        action = decide(engine, color, depth, True, 0.0, np.random.default_rng(0), ("push", "pick", "place"),
                        EXPLORATION)
        assert action.primitive == "place" and not action.explored


def test_explore_rate_zero_is_argmax_of_the_maps(engine, scenes):
    for color, depth in scenes[:4]:
        action, maps = decide(engine, color, depth, False, 0.0, np.random.default_rng(1), ("push", "pick"),
                              EXPLORATION, return_maps=True)
        assert isinstance(maps, PolicyMaps)
        stacked = np.stack([maps.q["push"], maps.q["pick"]])
        prim_idx, row, col = np.unravel_index(np.argmax(stacked), stacked.shape)
        assert (action.primitive, action.row, action.col) == (("push", "pick")[prim_idx], row, col)
        assert action.q_value == pytest.approx(float(stacked.max()))
        assert action.angle_rad == pytest.approx(float(maps.angle[action.primitive][row, col]))
        assert not action.explored
        assert maps.q["push"].shape == (H, W) and maps.q["push"].dtype == np.float32


def test_explore_rate_one_explores(engine, scenes):
    action = decide(engine, *scenes[0], False, 1.0, np.random.default_rng(2), ("push", "pick"), EXPLORATION)
    assert action.explored and action.primitive in ("push", "pick")


def test_angle_maps_are_in_range(engine, scenes):
    _, maps = decide(engine, *scenes[0], False, 0.0, np.random.default_rng(0), ("push", "pick"), EXPLORATION,
                     return_maps=True)
    assert np.all(np.abs(maps.angle["push"]) <= np.pi + 1e-6)
    assert np.all(np.abs(maps.angle["pick"]) <= np.pi / 2 + 1e-6)


def test_fast_path_agrees_with_fp32_on_fixed_set(model, engine, scenes):
    """Same primitive and pixel as the fp32 reference, and Q maps close ("auto": bf16 where the CPU has it, else
    int8 on x86 with AVX2, whose maps are within a few % of their std; near ties are rerun in fp32)."""
    for color, depth in scenes:
        rng = np.random.default_rng(0)
        fast, fast_maps = decide(engine, color, depth, False, 0.0, rng, ("push", "pick"), EXPLORATION, True)
        ref, ref_maps = decide(model, color, depth, False, 0.0, rng, ("push", "pick"), EXPLORATION, True)
        assert (fast.primitive, fast.row, fast.col) == (ref.primitive, ref.row, ref.col)
        assert fast.angle_rad == pytest.approx(ref.angle_rad, abs=0.02)
        for p in ("push", "pick"):
            # int8 under ONEDNN_MAX_CPU_ISA=AVX2 (7-bit weights): up to 0.063 of the map's std measured here
            tolerance = 0.1 * ref_maps.q[p].std() if engine.precision == "int8" else 1e-3
            assert np.abs(fast_maps.q[p] - ref_maps.q[p]).max() < tolerance


def test_fp32_engine_matches_reference_closely(model, scenes):
    eng = InferenceEngine(model, ModelConfig(precision="fp32"))
    try:
        fast = eng.infer(*scenes[0], ("push", "pick", "place"))
    finally:
        eng.close()
    ref = reference_maps(model, *scenes[0], ("push", "pick", "place"))
    for p in ref.q:
        np.testing.assert_allclose(fast.q[p], ref.q[p], atol=2e-5)


@pytest.mark.skipif(not fused_ops_available(), reason="this PyTorch build lacks oneDNN's fused ops")
def test_fused_and_plain_aten_layers_compute_the_same(model, scenes):
    x = preprocess(*scenes[0])
    with torch.inference_mode():
        fused = FastNet(model.nets["pick"], "fp32", fused=True)(x)
        plain = FastNet(model.nets["pick"], "fp32", fused=False)(x)
        # a second input size re-packs the weights
        small = preprocess(*synthetic_scene(np.random.default_rng(0), 32, 48))
        fused_small = FastNet(model.nets["pick"], "fp32", fused=True)
        fused_small(x)
        np.testing.assert_allclose(fused_small(small).numpy(),
                                   FastNet(model.nets["pick"], "fp32", fused=False)(small).numpy(), atol=2e-5)
    np.testing.assert_allclose(fused.numpy(), plain.numpy(), atol=2e-5)


def test_parallel_and_sequential_engines_agree(model, scenes):
    par, seq = InferenceEngine(model, parallel_nets=True), InferenceEngine(model, parallel_nets=False)
    try:
        a, b = par.infer(*scenes[2], ("push", "pick")), seq.infer(*scenes[2], ("push", "pick"))
    finally:
        par.close()
        seq.close()
    for p in ("push", "pick"):
        np.testing.assert_allclose(a.q[p], b.q[p], atol=1e-3)


@pytest.mark.parametrize("precision, std_fraction", [
    ("fp32", None),
    pytest.param("int8", 0.06, marks=pytest.mark.skipif(not int8_ops_available(), reason="no oneDNN int8 ops")),
])
def test_engine_load_state_swaps_weights(scenes, precision, std_fraction):
    """New weights replace the old in every precision's folded nets; bad ones are refused and change nothing.
    std_fraction: int8's tolerance as a share of the reference map's std (fp32: 2e-5 absolute)."""
    source, target = RoManNet(TORCH_INIT, seed=1).eval(), RoManNet(TORCH_INIT, seed=2).eval()
    eng = InferenceEngine(target, ModelConfig(precision=precision))
    try:
        before = eng.infer(*scenes[0], ("pick",)).q["pick"]
        eng.load_state(state_dict_to_tensors(source))
        after = eng.infer(*scenes[0], ("pick",)).q["pick"]
        bad = state_dict_to_tensors(source)
        bad["nets.pick.conv1.weight"] = torch.zeros(2, 2)
        with pytest.raises(DecodeError):
            eng.load_state(bad)
        still = eng.infer(*scenes[0], ("pick",)).q["pick"]
    finally:
        eng.close()
    expected = reference_maps(source, *scenes[0], ("pick",)).q["pick"]
    assert not np.allclose(before, expected, atol=1e-3)
    if std_fraction is None:
        np.testing.assert_allclose(after, expected, atol=2e-5)
    else:
        assert np.abs(after - expected).max() < std_fraction * expected.std()
    np.testing.assert_array_equal(still, after)


def test_precision_resolution(monkeypatch):
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)  # a limit below bf16 means no native bf16
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    assert resolve_precision("fp32") == "fp32"
    monkeypatch.setattr(policy, "cpu_bf16_flags", lambda: ())
    assert resolve_precision("auto") == "fp32"
    monkeypatch.setattr(policy, "cpu_bf16_flags", lambda: ("amx_bf16",))
    assert resolve_precision("auto") == ("bf16" if torch.backends.mkldnn.is_available() else "fp32")
    with pytest.raises(ValueError):
        resolve_precision("int8")


def test_inference_ablation_runs_on_any_cpu():
    """`romannet bench inference` times every variant this CPU can run and names the others (on CPUs without
    AVX-512, oneDNN's prepacked bf16 kernels raise): it never ends the benchmark with a traceback."""
    from romannet.bench.inference import _ablation
    cfg = ModelConfig(channels=8, residual_blocks=1, precision="fp32")
    engine = policy.InferenceEngine(RoManNet(cfg, seed=0).eval(), cfg)
    result = _ablation(engine, torch.rand(1, 4, 32, 32), repeats=1)
    for name in ("eager_fp32", "eager_fp32_channels_last", "folded_fp32"):
        assert result[name]["min_ms"] > 0, name
    for name, entry in result.items():
        assert set(entry) in ({"median_ms", "min_ms"}, {"unsupported"}), (name, entry)
        if "unsupported" in entry:
            assert "bf16" in name and entry["unsupported"], (name, entry)


def test_two_harmonic_engine_decodes_the_same_angles_as_the_reference(scenes):
    """model.rotation_harmonics = 2: the fast path carries the 4 rotation channels through and decodes the
    same angle maps as the eager reference (and as decode_rotation of the raw head output)."""
    from romannet.common.model import decode_rotation

    cfg = ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=2, precision="fp32")
    model = RoManNet(cfg, seed=3).eval()
    with torch.no_grad():  # a bias on the first harmonic, so the choice between the two candidates matters
        model.nets["pick"].rot_head.bias.copy_(torch.tensor([0.3, -0.2, 0.0, 0.0]))
    eng = InferenceEngine(model, cfg)
    try:
        fast = eng.infer(*scenes[0], ("push", "pick"))
        raw = eng.forward(preprocess(*scenes[0]), ("pick",))["pick"].numpy()
    finally:
        eng.close()
    assert raw.shape[-1] == 5
    ref = reference_maps(model, *scenes[0], ("push", "pick"))
    for p in ("push", "pick"):
        np.testing.assert_allclose(fast.q[p], ref.q[p], atol=2e-5)
        diff = np.abs(np.angle(np.exp(1j * (fast.angle[p] - ref.angle[p]))))  # modulo a full turn
        assert diff.max() < 1e-3
    np.testing.assert_allclose(fast.angle["pick"], decode_rotation(raw[..., 1:], "pick"), atol=1e-6)
    assert np.all(np.abs(fast.angle["pick"]) <= np.pi / 2 + 1e-6)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_prepared_weights_leave_the_nets_in_use_untouched_until_installed(scenes, precision):
    # An actor prepares the next weights while it acts on the current ones (the folded fp32 weights may share
    # storage with the model they were built from): nothing changes until install, and bad weights change nothing.
    if precision == "int8" and not int8_ops_available():
        pytest.skip("this PyTorch build has no oneDNN int8 convolutions")
    cfg = ModelConfig(q_head_init="default", precision=precision)
    old, new = RoManNet(cfg, seed=0).eval(), RoManNet(cfg, seed=1).eval()
    eng = InferenceEngine(RoManNet(cfg, seed=0), cfg)
    try:
        before = eng.infer(*scenes[0], ("push", "pick")).q
        prepared = eng.prepare_async(state_dict_to_tensors(new)).result()
        assert eng.slow_swap == (precision == "int8")
        during = eng.infer(*scenes[0], ("push", "pick")).q
        for p in before:
            np.testing.assert_array_equal(during[p], before[p])
        eng.install(prepared)
        after = eng.infer(*scenes[0], ("push", "pick")).q
        ref_new = reference_maps(new, *scenes[0], ("push", "pick")).q
        ref_old = reference_maps(old, *scenes[0], ("push", "pick")).q
        for p in after:
            assert np.abs(after[p] - ref_new[p]).max() < np.abs(after[p] - ref_old[p]).max()
        bad = {k: v[..., :1] if k.endswith("conv6.weight") else v for k, v in state_dict_to_tensors(old).items()}
        with pytest.raises(DecodeError):
            eng.prepare_async(bad).result()
        np.testing.assert_array_equal(eng.infer(*scenes[0], ("push", "pick")).q["pick"], after["pick"])
        spare = eng._spare
        eng.install(eng.prepare(state_dict_to_tensors(old)))
        assert eng._spare is not spare and eng.model is spare  # the spare was kept through the refusal
        np.testing.assert_array_equal(eng.infer(*scenes[0], ("push", "pick")).q["pick"], before["pick"])
    finally:
        eng.close()


def test_an_engine_for_a_tasks_primitives_builds_and_prepares_only_their_nets(model, scenes):
    # A clutter actor never runs PlaceNet: its engine neither folds nor prepares it, and decides exactly as an
    # engine with all three nets; asking it for PlaceNet is one clear error.
    cfg = ModelConfig(q_head_init="default", precision="fp32")
    full = InferenceEngine(model, cfg, parallel_nets=False)
    clutter = InferenceEngine(RoManNet(TORCH_INIT, seed=0), cfg, parallel_nets=False, primitives=("push", "pick"))
    try:
        assert set(clutter.nets) == {"push", "pick"} and set(full.nets) == {"push", "pick", "place"}
        for color, depth in scenes[:3]:
            a = clutter.infer(color, depth, ("push", "pick")).q
            b = full.infer(color, depth, ("push", "pick")).q
            for p in a:
                np.testing.assert_array_equal(a[p], b[p])
        assert set(clutter.prepare(state_dict_to_tensors(model)).nets) == {"push", "pick"}
        with pytest.raises(ValueError, match="runs the nets of \\['push', 'pick'\\], not 'place'"):
            clutter.infer(*scenes[0], ("place",))
    finally:
        full.close()
        clutter.close()
    for bad in ((), ("grasp",)):
        with pytest.raises(ValueError, match="must be some of"):
            InferenceEngine(model, cfg, primitives=bad)
