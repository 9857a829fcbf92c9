"""RoManNet architecture, preprocessing, rotation encoding and the weights tensor-dict round trip."""

import math

import numpy as np
import pytest
import torch
from safetensors.torch import load as safetensors_load
from safetensors.torch import save as safetensors_save

from romannet.common.config import PRIMITIVES, ModelConfig
from romannet.common.errors import ConfigError, DecodeError
from romannet.common.model import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    RoManNet,
    decode_angle,
    decode_rotation,
    encode_angle,
    load_tensors,
    parameter_count,
    preprocess,
    preprocess_batch,
    state_dict_to_tensors,
)

# PyTorch's Q-head init (the default "small" head starts within a few hundredths of 0), so Q maps differ
# measurably between nets and comparisons at atol 1e-3 mean something; the paper's rotation head (cos, sin).
TORCH_INIT = ModelConfig(q_head_init="default", rotation_harmonics=1)

PARAMETERS_PER_NET = 1_900_483  # GR-ConvNet with C = 32, 5 residual blocks, 1x1 heads (1 Q + 2 rotation)


@pytest.fixture(scope="module")
def model() -> RoManNet:
    return RoManNet(TORCH_INIT, seed=0).eval()


def test_parameter_count_is_exact_per_net(model):
    assert set(model.nets) == set(PRIMITIVES)
    for net in model.nets.values():
        assert parameter_count(net) == PARAMETERS_PER_NET
    assert parameter_count(model) == 3 * PARAMETERS_PER_NET


def test_the_default_rotation_head_has_two_harmonics():
    """The clutter recipe's pick head is the default: 4 rotation channels, a 1x1 conv of 2 more outputs."""
    model = RoManNet()
    assert model.cfg.rotation_harmonics == 2
    assert parameter_count(model.nets["pick"]) == PARAMETERS_PER_NET + 2 * (32 + 1)
    with torch.inference_mode():
        q, rot = model.nets["pick"](torch.randn(1, 4, 32, 32))
    assert rot.shape == (1, 4, 32, 32)


def test_parameter_count_follows_config():
    small = RoManNet(ModelConfig(channels=8, residual_blocks=1))
    assert parameter_count(small.nets["push"]) < PARAMETERS_PER_NET / 10


@pytest.mark.parametrize("h, w", [(64, 64), (64, 96), (224, 224)])
def test_output_is_exactly_input_size(model, h, w):
    x = torch.randn(1 if h == 224 else 2, 4, h, w)
    with torch.inference_mode():
        q, rot = model.nets["pick"](x)
    assert q.shape == (x.shape[0], h, w)
    assert rot.shape == (x.shape[0], 2, h, w)
    assert torch.isfinite(q).all() and torch.isfinite(rot).all()


def test_input_size_not_multiple_of_4_is_rejected(model):
    with pytest.raises(ValueError, match="multiples of 4"):
        model.nets["push"](torch.zeros(1, 4, 64, 62))


def test_init_is_deterministic_from_seed_and_leaves_global_rng_alone():
    torch.manual_seed(123)
    expected_next = torch.rand(1)
    torch.manual_seed(123)
    a, b, c = RoManNet(TORCH_INIT, seed=7), RoManNet(TORCH_INIT, seed=7), RoManNet(TORCH_INIT, seed=8)
    assert torch.equal(torch.rand(1), expected_next)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not torch.equal(sa["nets.push.conv1.weight"], sc["nets.push.conv1.weight"])
    # the three nets are independently initialised, not copies
    assert not torch.equal(sa["nets.push.conv1.weight"], sa["nets.pick.conv1.weight"])


def test_state_dict_keys_are_stable():
    keys = list(RoManNet(TORCH_INIT).state_dict())
    assert keys[0] == "nets.push.conv1.weight"
    assert "nets.pick.res.4.conv2.weight" in keys
    assert "nets.place.rot_head.bias" in keys and "nets.place.bn5.running_var" in keys
    assert len(keys) == 3 * 111


def test_preprocess_normalisation_values():
    color = np.zeros((8, 12, 3), np.uint8)
    color[2, 3] = (255, 0, 128)
    depth = np.zeros((8, 12), np.float32)
    depth[2, 3] = 0.04
    x = preprocess(color, depth)
    assert x.shape == (1, 4, 8, 12) and x.dtype == torch.float32
    px = x[0, :, 2, 3].tolist()
    expected = [(v / 255 - m) / s for v, m, s in zip((255, 0, 128), IMAGENET_MEAN, IMAGENET_STD, strict=True)]
    assert px[:3] == pytest.approx(expected, abs=1e-5)
    assert px[3] == pytest.approx((0.04 - 0.01) / 0.03, abs=1e-5)
    assert x[0, 3, 0, 0].item() == pytest.approx(-1 / 3, abs=1e-6)  # floor (d = 0)
    assert x[0, 0, 0, 0].item() == pytest.approx(-0.485 / 0.229, abs=1e-5)  # black


def test_preprocess_batch_matches_single():
    rng = np.random.default_rng(0)
    color = rng.integers(0, 256, size=(3, 16, 20, 3), dtype=np.uint8)
    depth = rng.uniform(0, 0.1, size=(3, 16, 20)).astype(np.float32)
    batch = preprocess_batch(color, depth)
    assert batch.shape == (3, 4, 16, 20)
    for i in range(3):
        assert torch.equal(batch[i:i + 1], preprocess(color[i], depth[i]))


def test_preprocess_rejects_bad_inputs():
    with pytest.raises(ValueError, match="uint8"):
        preprocess(np.zeros((8, 8, 3), np.float32), np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError, match="does not match"):
        preprocess(np.zeros((8, 8, 3), np.uint8), np.zeros((8, 4), np.float32))


@pytest.mark.parametrize("primitive", PRIMITIVES)
def test_angle_round_trip(primitive):
    half_range = math.pi if primitive == "push" else math.pi / 2
    thetas = np.linspace(-half_range, half_range, 101)[1:]  # the open end -half_range is excluded
    c, s = encode_angle(thetas, primitive)
    back = decode_angle(c, s, primitive)
    np.testing.assert_allclose(back, thetas, atol=1e-9)
    # torch and float paths agree with numpy
    ct, st = encode_angle(torch.from_numpy(thetas), primitive)
    np.testing.assert_allclose(decode_angle(ct, st, primitive).numpy(), thetas, atol=1e-9)
    assert decode_angle(*encode_angle(0.3, primitive), primitive) == pytest.approx(0.3)


def test_pick_and_place_encode_theta_and_theta_plus_pi_alike():
    for primitive in ("pick", "place"):
        for theta in (-1.2, 0.0, 0.4, 1.5):
            a = encode_angle(theta, primitive)
            b = encode_angle(theta + math.pi, primitive)
            assert a == pytest.approx(b, abs=1e-12)
            assert decode_angle(*b, primitive) == pytest.approx(theta)
    # push is directional: opposite directions have opposite encodings
    assert encode_angle(0.4 + math.pi, "push")[0] == pytest.approx(-math.cos(0.4))


def test_decode_ranges_and_boundaries():
    assert decode_angle(-1.0, -0.0, "push") == pytest.approx(math.pi)  # atan2(-0, -1) = -pi folds to +pi
    assert decode_angle(-1.0, -0.0, "pick") == pytest.approx(math.pi / 2)
    arr = decode_angle(np.array([-1.0], np.float32), np.array([-0.0], np.float32), "place")
    assert arr.dtype == np.float32 and arr[0] == pytest.approx(math.pi / 2)
    rng = np.random.default_rng(0)
    c, s = rng.normal(size=1000) * 3, rng.normal(size=1000) * 3  # the head's output need not be unit length
    push, pick = decode_angle(c, s, "push"), decode_angle(c, s, "pick")
    assert np.all((push > -math.pi) & (push <= math.pi))
    assert np.all((pick > -math.pi / 2) & (pick <= math.pi / 2))
    with pytest.raises(ValueError):
        encode_angle(0.0, "throw")


def test_weights_round_trip_through_safetensors(model):
    other = RoManNet(TORCH_INIT, seed=99).eval()
    tensors = safetensors_load(safetensors_save(state_dict_to_tensors(model)))
    load_tensors(other, tensors)
    x = torch.randn(1, 4, 32, 32)
    with torch.inference_mode():
        for p in PRIMITIVES:
            assert torch.equal(other.nets[p](x)[0], model.nets[p](x)[0])


def _mutated(tensors, key, value):
    out = dict(tensors)
    if value is None:
        del out[key]
    else:
        out[key] = value
    return out


@pytest.mark.parametrize("case", ["missing", "unexpected", "shape", "dtype", "nan", "negative_var", "not_tensor"])
def test_mismatched_weights_raise_decode_error(model, case):
    tensors = state_dict_to_tensors(model)
    key = "nets.pick.conv3.weight"
    bad = {
        "missing": lambda: _mutated(tensors, key, None),
        "unexpected": lambda: _mutated(tensors, "nets.throw.conv1.weight", torch.zeros(1)),
        "shape": lambda: _mutated(tensors, key, torch.zeros(3, 3)),
        "dtype": lambda: _mutated(tensors, key, tensors[key].double()),
        "nan": lambda: _mutated(tensors, key, tensors[key].clone().fill_(float("nan"))),
        "negative_var": lambda: _mutated(tensors, "nets.push.bn1.running_var", -torch.ones(32)),
        "not_tensor": lambda: _mutated(tensors, key, np.zeros(tensors[key].shape, np.float32)),
    }[case]()
    target = RoManNet(TORCH_INIT, seed=5)
    before = state_dict_to_tensors(target)
    with pytest.raises(DecodeError):
        load_tensors(target, bad)
    after = state_dict_to_tensors(target)
    assert all(torch.equal(before[k], after[k]) for k in before)  # nothing half-loaded


@pytest.mark.parametrize("primitive", PRIMITIVES)
def test_two_harmonic_angle_round_trip(primitive):
    half_range = math.pi if primitive == "push" else math.pi / 2
    thetas = np.linspace(-half_range, half_range, 201)[1:]
    channels = np.stack(encode_angle(thetas, primitive, harmonics=2), axis=-1)
    assert channels.shape == (200, 4)
    np.testing.assert_allclose(decode_rotation(channels, primitive), thetas, atol=1e-9)
    # one harmonic through the same entry point is decode_angle
    one = np.stack(encode_angle(thetas, primitive), axis=-1)
    np.testing.assert_allclose(decode_rotation(one, primitive), thetas, atol=1e-9)
    ct = encode_angle(torch.tensor(0.3, dtype=torch.float64), primitive, harmonics=2)
    assert len(ct) == 4 and float(ct[2]) == pytest.approx(math.cos(0.6 if primitive == "push" else 1.2))


def test_second_harmonic_keeps_a_cube_grasp_that_the_first_averages_away():
    """A cube is grasped alike at theta and theta + 90 degrees. Regression toward both (the mean of their
    targets) leaves nothing of the first harmonic (2 theta and 2 theta + pi cancel) but all of the second,
    and the decoded angle is square to the cube's faces again."""
    for theta in (-1.3, -0.4, 0.0, 0.25, 0.7, 1.5):
        targets = np.array([encode_angle(theta, "pick", 2), encode_angle(theta + math.pi / 2, "pick", 2)])
        mean = targets.mean(axis=0)
        assert np.hypot(mean[0], mean[1]) < 1e-12 and np.hypot(mean[2], mean[3]) == pytest.approx(1.0)
        decoded = float(decode_rotation(mean, "pick"))
        # square to the faces: equal to theta modulo 90 degrees
        assert math.remainder(decoded - theta, math.pi / 2) == pytest.approx(0.0, abs=1e-9)
    # an oblong object: the first harmonic (successes across its short side only) picks that candidate
    theta = 0.4
    short_side = np.array([*encode_angle(theta, "pick", 1), *encode_angle(theta, "pick", 2)[2:]])
    short_side[:2] *= 0.2  # a weak first harmonic still decides
    assert float(decode_rotation(short_side, "pick")) == pytest.approx(theta)
    long_side = short_side.copy()
    long_side[:2] *= -1
    assert float(decode_rotation(long_side, "pick")) == pytest.approx(theta - math.pi / 2)


def test_two_harmonic_decode_ranges_and_bad_channel_counts():
    rng = np.random.default_rng(1)
    out = rng.normal(size=(500, 4)) * 2
    push, pick = decode_rotation(out, "push"), decode_rotation(out, "pick")
    assert np.all((push > -math.pi) & (push <= math.pi + 1e-12))
    assert np.all((pick > -math.pi / 2) & (pick <= math.pi / 2 + 1e-12))
    with pytest.raises(ValueError, match="2 or 4 channels"):
        decode_rotation(np.zeros((3, 3)), "pick")
    with pytest.raises(ValueError, match="harmonics"):
        encode_angle(0.0, "pick", harmonics=3)
    with pytest.raises(ConfigError, match="model.rotation_harmonics"):
        ModelConfig(rotation_harmonics=3)


def test_two_harmonic_model_has_a_four_channel_rotation_head():
    model = RoManNet(ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=2)).eval()
    with torch.inference_mode():
        q, rot = model.nets["pick"](torch.randn(1, 4, 32, 32))
    assert q.shape == (1, 32, 32) and rot.shape == (1, 4, 32, 32)
    # its weights do not load into a one-harmonic model (a clear error, not a silent reshape)
    with pytest.raises(DecodeError):
        load_tensors(RoManNet(ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=1)),
                     state_dict_to_tensors(model))


def test_small_q_head_init_scales_the_q_head_and_keeps_the_rest_of_the_init():
    """model.q_head_init = "small": the Q head is PyTorch's init of the same seed times 0.01, so Q maps start
    a hundred times flatter (not flat: the argmax and the exploration candidates still have an order, and
    failures labelled 0 still give a gradient); every other weight, and the rotation head's output, is the
    default init's."""
    small = dict(channels=8, residual_blocks=1)
    scaled = RoManNet(ModelConfig(q_head_init="small", **small), seed=3)
    default = RoManNet(ModelConfig(q_head_init="default", **small), seed=3)
    x = torch.randn(2, 4, 32, 32)
    for p in PRIMITIVES:
        scaled.nets[p].eval()
        default.nets[p].eval()
        with torch.no_grad():
            q, rot = scaled(x, p)
            q_default, rot_default = default(x, p)
        assert torch.allclose(q, 0.01 * q_default, atol=1e-7)
        assert float(q.std()) > 0  # an order for the argmax
        assert torch.equal(rot, rot_default)
    scaled_sd, default_sd = scaled.state_dict(), default.state_dict()
    assert scaled_sd.keys() == default_sd.keys()
    for k, v in scaled_sd.items():
        if ".q_head." not in k:
            assert torch.equal(v, default_sd[k]), k
    with pytest.raises(ConfigError, match="q_head_init"):
        ModelConfig(q_head_init="zero")
