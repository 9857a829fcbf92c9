"""Training on a window around the executed pixel, and V(s_{t+1}) taken from the actor's next decision."""

from __future__ import annotations

import dataclasses

import _learner_helpers as H
import pytest
import torch

from romannet.common.config import ModelConfig
from romannet.common.model import GRConvNet
from romannet.learner.crop import crop_origin
from romannet.learner.trainer import actor_value_usable


@pytest.mark.parametrize("row,col", [(112, 112), (0, 0), (223, 223), (5, 200), (130, 61)])
def test_crop_window_holds_the_pixel_on_the_stride_grid(row, col):
    r0, c0 = crop_origin((224, 224), row, col, 128)
    assert r0 % 4 == 0 and c0 % 4 == 0
    assert 0 <= r0 <= 224 - 128 and 0 <= c0 <= 224 - 128
    assert r0 <= row < r0 + 128 and c0 <= col < c0 + 128
    if 64 <= row <= 224 - 64:  # room on both sides: centred to within the stride
        assert abs(row - (r0 + 64)) <= 2


@pytest.mark.parametrize("crop,size,pixel", [(130, 224, (1, 1)), (256, 224, (1, 1)), (128, 224, (224, 3))])
def test_crop_window_rejects_bad_requests(crop, size, pixel):
    with pytest.raises(ValueError):
        crop_origin((size, size), *pixel, crop)


def test_window_output_equals_the_whole_heightmap_over_the_label_support():
    # The recipe's net (32 channels, 5 residual blocks): its Q on a 128 px window equals its Q on the whole
    # 224 px heightmap at every pixel within 12 px of the executed one (the TPG kernel's support).
    torch.manual_seed(0)
    net = GRConvNet(32, 5).eval()
    x = torch.randn(1, 4, 224, 224)
    with torch.no_grad():
        whole, _ = net(x)
        for row, col in [(112, 112), (3, 220), (100, 60)]:
            r0, c0 = crop_origin((224, 224), row, col, 128)
            window, _ = net(x[:, :, r0:r0 + 128, c0:c0 + 128])
            rs = slice(max(row - 12, r0), min(row + 13, r0 + 128))
            cs = slice(max(col - 12, c0), min(col + 13, c0 + 128))
            got = window[0, rs.start - r0:rs.stop - r0, cs.start - c0:cs.stop - c0]
            torch.testing.assert_close(got, whole[0, rs, cs], atol=1e-6, rtol=0)


def test_crop_training_moves_the_whole_maps_q_toward_the_target():
    # The paper's rotation head, which lr 1e-2 was set for (with two harmonics this tiny net's Q overshoots).
    model = ModelConfig(channels=8, residual_blocks=1, rotation_harmonics=1)
    t = H.trainer(model=model, train_crop_px=32, lr=1e-2, loss_reduction="mean")
    item = (H.transition(64, seed=1, row=50, col=9, reward=1.0, done=True), 1.0, 0)
    x = t._inputs([item[0].color_before], [item[0].depth_before])

    def q_at_pixel() -> float:
        t.model.eval()
        with torch.no_grad():
            q, _ = t.model.nets["pick"](x)
        t.model.train()
        return float(q[0, 50, 9])

    before = q_at_pixel()
    for _ in range(30):
        stats = t.train_step([item])
    after = q_at_pixel()
    assert stats.targets == (1.0,)
    assert abs(after - 1.0) < 0.5 * abs(before - 1.0)


def test_actor_value_is_used_when_fresh_and_recomputed_when_stale():
    t = H.trainer(actor_value_max_age=5, bootstrap_clip=True)
    t.updates = 20
    base = H.transition(32, seed=2, reward=1.0)
    fresh = dataclasses.replace(base, next_value=0.7, next_value_version=17)
    stale = dataclasses.replace(base, next_value=0.7, next_value_version=10)
    huge = dataclasses.replace(base, next_value=50.0, next_value_version=20)
    values = t.next_state_values([fresh, stale, huge, base])
    assert values[0] == pytest.approx(0.7)
    assert values[2] == pytest.approx(2.0)  # clipped into the return range [0, 1 / (1 - 0.5)]
    assert values[1] == pytest.approx(values[3])  # stale and absent: both computed here, same s_t+1
    assert values[1] != pytest.approx(0.7)
    assert (t.actor_values_used, t.values_computed) == (2, 2)


def test_actor_value_usable_rules():
    base = H.transition(32, seed=3)
    with_value = dataclasses.replace(base, next_value=0.1, next_value_version=8)
    assert actor_value_usable(with_value, 10, 2)
    assert not actor_value_usable(with_value, 11, 2)  # too old
    assert not actor_value_usable(with_value, 7, 2)  # from the future: a different learner's versions
    assert not actor_value_usable(with_value, 10, 0)  # off
    assert not actor_value_usable(base, 10, 100)  # none sent
