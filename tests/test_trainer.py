"""Trainer: gradients reach only the executed nets, targets, IS weights, LAE, target net, published weights."""

from __future__ import annotations

import math

import _learner_helpers as H
import pytest
import torch

from romannet.common.exploration import lae_update
from romannet.common.model import RoManNet, load_tensors, preprocess_batch
from romannet.common.weightscodec import make_weights, weights_state_dict
from romannet.learner.losses import huber


def _params(model, primitive):
    return {k: v.detach().clone() for k, v in model.nets[primitive].state_dict().items()}


def test_gradients_reach_only_the_executed_primitives():
    t = H.trainer()
    place_before = _params(t.model, "place")
    stats = t.train_step(H.batch(2))  # one pick, one push
    assert set(stats.loss_by_primitive) == {"pick", "push"}
    for name, p in t.model.nets["place"].named_parameters():
        assert p.grad is None, name
    for name, v in t.model.nets["place"].state_dict().items():
        assert torch.equal(v, place_before[name]), name  # no weight decay, momentum or BN update either
    assert all(p.grad is not None for p in t.model.nets["pick"].parameters())
    assert all(p.grad is not None for p in t.model.nets["push"].parameters())

    t = H.trainer()
    t.train_step([(H.transition(primitive="pick"), 1.0, 0)])
    assert all(p.grad is None for net in ("push", "place") for p in t.model.nets[net].parameters())


def test_td_error_is_at_the_executed_pixel_against_the_target():
    t = H.trainer()
    tr = H.transition(primitive="pick", reward=1.0, done=True, row=7, col=19)
    x = preprocess_batch(tr.color_before[None], tr.depth_before[None])
    with torch.no_grad():
        q, _ = t.model.nets["pick"](x)  # train mode, as the step's forward pass
    stats = t.train_step([(tr, 1.0, 42)])
    assert stats.targets == (1.0,)  # done: no bootstrap
    assert stats.td_errors[0] == pytest.approx(abs(float(q[0, 7, 19]) - 1.0), rel=1e-5)
    assert stats.item_ids == (42,)
    assert stats.priority_update().priorities == stats.td_errors
    # LAE: updated once with the paper's L_t = Huber(TD error at the executed pixel).
    assert stats.exploration_loss == pytest.approx(float(huber(torch.tensor(stats.td_errors[0]))), rel=1e-6)
    assert t.exploration.steps == 1
    assert stats.exploration_rate == pytest.approx(lae_update(0.5, stats.exploration_loss, t.exploration_cfg))


def test_bootstrap_only_on_success_and_from_the_allowed_nets():
    t = H.trainer(bootstrap_clip=False)  # the raw max Q of s', as the paper
    ok = H.transition(primitive="pick", reward=0.5, done=False, seed=1)
    fail = H.transition(primitive="pick", success=False, reward=0.0, done=False, seed=2)
    v = t.next_state_values([ok, fail])
    assert v[1] == 0.0
    t.model.eval()
    with torch.no_grad():
        x = preprocess_batch(ok.color_after[None], ok.depth_after[None])
        expected = max(float(t.model.nets[p](x)[0].max()) for p in ("push", "pick"))
    t.model.train()
    assert v[0] == pytest.approx(expected, rel=1e-5)
    stats = t.train_step([(ok, 1.0, 0), (fail, 1.0, 1)])
    assert stats.targets[0] == pytest.approx(0.5 + 0.5 * expected, rel=1e-5)
    assert stats.targets[1] == 0.0


def test_target_network_is_used_and_synced():
    t = H.trainer(target_network=True, target_sync_every_updates=2, bootstrap_clip=False)
    with torch.no_grad():
        for p in t.target.parameters():
            p.add_(0.05)
    ok = H.transition(primitive="pick", reward=1.0, done=False)
    with torch.no_grad():
        x = preprocess_batch(ok.color_after[None], ok.depth_after[None])
        expected = max(float(t.target.nets[p](x)[0].max()) for p in ("push", "pick"))
    assert t.next_state_values([ok])[0] == pytest.approx(expected, rel=1e-5)
    t.train_step([(ok, 1.0, 0)])
    t.train_step([(ok, 1.0, 0)])
    for k, v in t.model.state_dict().items():
        assert torch.equal(v, t.target.state_dict()[k]), k


def test_is_weight_scales_the_loss():
    a, b = H.trainer(), H.trainer()
    tr = H.transition(primitive="push", reward=0.2)
    la = a.train_step([(tr, 1.0, 0)]).loss
    lb = b.train_step([(tr, 0.25, 0)]).loss
    assert lb == pytest.approx(0.25 * la, rel=1e-6)


def test_rotation_head_trained_only_on_success():
    t = H.trainer()
    t.train_step([(H.transition(primitive="pick", success=False, reward=0.0), 1.0, 0)])
    assert not t.model.nets["pick"].rot_head.weight.grad.any()
    t = H.trainer()
    t.train_step([(H.transition(primitive="pick"), 1.0, 0)])
    assert t.model.nets["pick"].rot_head.weight.grad.abs().sum() > 0


def test_published_weights_decode_and_load_in_a_fresh_model():
    t = H.trainer()
    t.train_step(H.batch(3))
    msg, ann = make_weights(1, t.state_tensors())
    fresh = RoManNet(H.SMALL_MODEL, seed=99)
    load_tensors(fresh, weights_state_dict(msg))
    for k, v in t.model.state_dict().items():
        assert torch.equal(fresh.state_dict()[k], v), k
    assert ann.size_bytes == len(msg.safetensors)


def test_bf16_step_tracks_fp32():
    """The fast setting computes the same step within bf16's rounding (learning: tests/test_learning.py)."""
    items = H.batch(3)
    l32 = H.trainer(precision="fp32").train_step(items).loss
    l16 = H.trainer(precision="bf16").train_step(items).loss
    assert l16 == pytest.approx(l32, rel=0.05)


def test_auto_precision_is_fp32_where_the_cpu_has_no_native_bf16(monkeypatch):
    """bf16 is emulated (several times slower) on CPUs without AMX/AVX512-BF16: "auto" must not pick it."""
    from romannet.common import policy
    monkeypatch.setattr(policy, "cpu_bf16_flags", lambda: ())
    assert H.trainer(precision="auto").precision == "fp32"
    assert H.trainer(precision="bf16").precision == "bf16"  # asked for explicitly: kept (with a warning)
    monkeypatch.setattr(policy, "cpu_bf16_flags", lambda: ("amx_bf16",))
    expected = "bf16" if torch.backends.mkldnn.is_available() else "fp32"
    assert H.trainer(precision="auto").precision == expected


def test_gradient_clipping_bounds_the_step_gradient():
    items = H.batch(3)
    free = H.trainer()
    free.train_step(items)
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(p.grad) for p in free.model.parameters()
                                                 if p.grad is not None]))
    assert norm > 0.5, "the batch must have a gradient larger than the clip for the test to mean anything"
    clipped = H.trainer(max_grad_norm=0.5)
    clipped.train_step(items)
    grads = [p.grad for p in clipped.model.parameters() if p.grad is not None]
    clipped_norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
    assert float(clipped_norm) == pytest.approx(0.5, rel=1e-4)
    with pytest.raises(ValueError, match="max_grad_norm"):
        H.trainer(max_grad_norm=-1.0)


def test_rejects_bad_batches():
    t = H.trainer()
    with pytest.raises(ValueError):
        t.train_step([])
    with pytest.raises(ValueError):
        t.train_step([(H.transition(), 0.0, 0)])


def test_cuda_device_without_a_gpu_is_a_clear_config_error():
    import torch

    from romannet.common.config import ModelConfig, RewardConfig, TaskConfig
    from romannet.common.config_learner import LearnerConfig
    from romannet.common.errors import ConfigError
    from romannet.learner.trainer import Trainer

    with pytest.raises(ConfigError, match="learner.device"):
        LearnerConfig(device="gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            Trainer(ModelConfig(channels=8, residual_blocks=1), LearnerConfig(device="cuda"), RewardConfig(),
                    TaskConfig())


def test_two_harmonic_rotation_head_learns_a_cube_grasp_the_first_harmonic_averages_away():
    """Successes at one pixel alternate between theta and theta + 90 degrees (a cube grasped across either
    face pair). Trained on them, the second harmonic learns the cube's faces, so the decoded angle is square
    to them; the first harmonic's targets cancel and it stays weak."""
    from romannet.common.config import ModelConfig
    from romannet.common.model import decode_rotation

    theta = 0.35
    t = H.trainer(model=ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=2), lr=0.002)
    items = [(H.transition(primitive="pick", seed=0, row=10, col=12, angle_rad=theta + k * math.pi / 2,
                           reward=0.5, done=True), 1.0, k) for k in range(2)]
    for _ in range(60):
        t.train_step(items)
    t.model.eval()
    with torch.no_grad():
        x = preprocess_batch(items[0][0].color_before[None], items[0][0].depth_before[None])
        rot = t.model.nets["pick"](x)[1][0, :, 10, 12].numpy()
    first, second = math.hypot(rot[0], rot[1]), math.hypot(rot[2], rot[3])
    assert second > 0.6 and first < 0.3 * second, rot
    decoded = float(decode_rotation(rot, "pick"))
    assert abs(math.remainder(decoded - theta, math.pi / 2)) < math.radians(5), math.degrees(decoded)


@pytest.mark.parametrize("place_bias, expected_v", [(10.0, 2.0), (-5.0, 0.0)])
def test_bootstrap_clip_keeps_the_future_value_in_the_return_range(place_bias, expected_v):
    """learner.bootstrap_clip: a successful pick bootstraps from the place net's max Q; a net far outside
    [0, W / (1 - gamma)] = [0, 2] no longer drags the pick's target with it (off: the raw value)."""
    from romannet.common.config import TaskConfig

    ok = H.transition(primitive="pick", reward=0.25, done=False, holding_after=True, task="stacking")
    for clip in (True, False):
        t = H.trainer(task=TaskConfig(kind="stacking", use_push=False), bootstrap_clip=clip)
        with torch.no_grad():
            t.model.nets["place"].q_head.bias.fill_(place_bias)
        v = t.next_state_values([ok])[0]
        if clip:
            assert v == expected_v
            assert t.train_step([(ok, 1.0, 0)]).targets[0] == pytest.approx(0.25 + 0.5 * expected_v)
        else:
            assert (v > 2.0) if place_bias > 0 else (v < 0.0)


def test_rotation_support_kernel_trains_the_angle_around_the_executed_pixel():
    """learner.rotation_support: "pixel" regresses the executed angle at its pixel only; "kernel" over the Q
    label's support, so the head's angle around the pixel moves toward the target too, not only at it."""
    from romannet.common.config import RewardConfig, load_config
    from romannet.common.errors import ConfigError
    from romannet.learner.targets import q_label, rotation_target

    theta, row, col = 0.6, 12, 14
    item = (H.transition(primitive="pick", seed=3, row=row, col=col, angle_rad=theta, reward=0.5, done=True),
            1.0, 0)
    _, support = q_label((32, 32), row, col, theta, 0.5, 0.0, 0.5, RewardConfig())
    ring = torch.from_numpy(support.copy())
    ring[row, col] = False  # the support without the executed pixel
    target = torch.tensor(rotation_target(theta, "pick"))[:, None]

    def errors(t):
        t.model.eval()
        with torch.no_grad():
            x = preprocess_batch(item[0].color_before[None], item[0].depth_before[None])
            rot = t.model.nets["pick"](x)[1][0]  # (2, h, w)
        t.model.train()
        err = ((rot[:, ring] - target) ** 2).sum(dim=0).mean()
        return float(err), float(((rot[:, row, col] - target[:, 0]) ** 2).sum())

    results = {}
    for where in ("pixel", "kernel"):
        t = H.trainer(rotation_support=where, lr=0.005, loss_reduction="mean", executed_pixel_weight=0.0)
        before = errors(t)
        for _ in range(15):
            t.train_step([item])
        results[where] = (before, errors(t))
    (ring0, _), (ring_pixel, at_pixel) = results["pixel"]
    (ring0k, _), (ring_kernel, at_kernel) = results["kernel"]
    assert ring0 == pytest.approx(ring0k)  # same seed, same start
    assert ring_kernel < 0.5 * ring0 and ring_kernel < 0.7 * ring_pixel, results
    assert at_kernel < 0.75 * results["kernel"][0][1], results  # the executed pixel learns too
    assert at_pixel < 0.25 * results["pixel"][0][1] and ring_pixel > 0.8 * ring0, results  # "pixel": there only
    with pytest.raises(ConfigError, match="'pixel', 'kernel'"):
        load_config(overrides=['learner.rotation_support="everywhere"'])


def test_executed_pixel_weight_adds_the_papers_loss_at_the_executed_pixel():
    """learner.executed_pixel_weight w: the item loss is the support's mean loss + w * Huber(Q(s_t, a_t) - Y_t)
    (the paper's L_t), so a peak of Q at a failed action's pixel is trained down far faster than by the mean
    over the support, where it weighs 1/N."""
    from romannet.common.config import load_config
    from romannet.common.errors import ConfigError

    row, col = 9, 17
    fail = H.transition(primitive="push", seed=3, row=row, col=col, success=False, reward=0.0, done=False)
    base = H.trainer(loss_reduction="mean", executed_pixel_weight=0.0).train_step([(fail, 1.0, 0)])
    weighted = H.trainer(loss_reduction="mean", executed_pixel_weight=2.0).train_step([(fail, 1.0, 0)])
    assert weighted.td_errors == base.td_errors  # same init, same forward pass
    td = base.td_errors[0]
    assert td > 0.01
    assert weighted.loss == pytest.approx(base.loss + 2.0 * float(huber(torch.tensor(td))), rel=1e-5)

    tds = {}  # |Q(s_t, a_t) - 0| before each of five updates on the failed push, at the paper's lr
    for w in (0.0, 1.0):
        t = H.trainer(loss_reduction="mean", executed_pixel_weight=w)
        tds[w] = [t.train_step([(fail, 1.0, 0)]).td_errors[0] for _ in range(5)]
    assert tds[0.0][-1] > 0.9 * td, tds  # the mean over the support barely moves the pixel
    assert min(tds[1.0]) < 0.25 * td, tds  # the paper's L_t takes it most of the way to its label
    for bad in ("-1", "101", "nan"):
        with pytest.raises(ConfigError, match="executed_pixel_weight"):
            load_config(overrides=[f"learner.executed_pixel_weight={bad}"])
