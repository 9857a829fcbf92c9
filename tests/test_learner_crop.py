"""Training on a window around the executed pixel, and V(s_{t+1}) taken from the actor's next decision."""

from __future__ import annotations

import dataclasses

import _learner_helpers as H
import pytest
import torch

from romannet.common.config import ModelConfig
from romannet.common.model import GRConvNet
from romannet.learner.crop import crop_origin, head_region
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


def test_a_computed_value_is_reused_while_fresh_then_recomputed():
    """The learner's own V(s_t+1) stands in for a forward pass under the actors' rule (at most
    actor_value_max_age versions old), per transition; past that it is computed again with today's net."""
    t = H.trainer(actor_value_max_age=5, bootstrap_clip=False)
    t.updates = 20
    item = H.transition(32, seed=2, reward=1.0)
    other = dataclasses.replace(item, step=item.step + 1)  # the same s_t+1, another transition
    first = t.next_state_values([item])[0]
    with torch.no_grad():
        for net in t.model.nets.values():
            net.q_head.bias.add_(0.25)  # the net moves on: every Q, so V, by 0.25
    t.updates = 25
    assert t.next_state_values([item, other]) == [pytest.approx(first), pytest.approx(first + 0.25)]
    assert (t.values_computed, t.values_reused) == (2, 1)
    t.updates = 26  # six versions after the first pass: too old
    assert t.next_state_values([item])[0] == pytest.approx(first + 0.25)
    assert (t.values_computed, t.values_reused) == (3, 1)
    off = H.trainer(actor_value_max_age=0)
    off.next_state_values([item])
    off.next_state_values([item])
    assert (off.values_computed, off.values_reused) == (2, 0)


def test_actor_value_usable_rules():
    base = H.transition(32, seed=3)
    with_value = dataclasses.replace(base, next_value=0.1, next_value_version=8)
    assert actor_value_usable(with_value, 10, 2)
    assert not actor_value_usable(with_value, 11, 2)  # too old
    assert not actor_value_usable(with_value, 7, 2)  # from the future: a different learner's versions
    assert not actor_value_usable(with_value, 10, 0)  # off
    assert not actor_value_usable(base, 10, 100)  # none sent


@pytest.mark.parametrize("boxes,size", [
    ([(50, 74, 40, 52), (10, 12, 100, 127)], (128, 128)),   # one box at the map's edge
    ([(0, 0, 0, 0)], (64, 64)),                            # a single pixel in the corner
    ([(0, 127, 3, 9)], (128, 128)),                        # a box as tall as the map
    ([(60, 70, 60, 70), (61, 61, 2, 2), (120, 127, 0, 20)], (128, 96)),
])
def test_head_region_holds_each_box_with_its_margin_or_the_maps_edge(boxes, size):
    margin = 4
    (rh, rw), origins = head_region(boxes, size, margin)
    h, w = size
    assert rh <= h and rw <= w
    for (r0, r1, c0, c1), (o_r, o_c) in zip(boxes, origins, strict=True):
        assert 0 <= o_r <= h - rh and 0 <= o_c <= w - rw
        assert o_r <= r0 and r1 < o_r + rh and o_c <= c0 and c1 < o_c + rw
        assert o_r == 0 or r0 - o_r >= margin  # an inner edge keeps the head's reach clear of the box
        assert o_c == 0 or c0 - o_c >= margin
        assert o_r + rh == h or o_r + rh - 1 - r1 >= margin
        assert o_c + rw == w or o_c + rw - 1 - c1 >= margin


@pytest.mark.parametrize("boxes", [[], [(5, 4, 0, 0)], [(0, 64, 0, 0)], [(-1, 0, 0, 0)]])
def test_head_region_rejects_boxes_outside_the_map(boxes):
    with pytest.raises(ValueError):
        head_region(boxes, (64, 64), 4)


def test_head_on_a_region_equals_the_whole_map_over_the_region_minus_the_radius():
    torch.manual_seed(0)
    net = GRConvNet(8, 1, rotation_harmonics=2).eval()
    x = torch.randn(2, 4, 64, 64)
    with torch.no_grad():
        f = net.features(x)
        whole_q, whole_rot = net.head(f)
        q, rot = net.head(f[:, :, 10:40, 0:30])  # inner edges at rows 10, 39 and column 29; column 0 is the map's
    m = net.head_radius()
    assert m == 4
    torch.testing.assert_close(q[:, m:-m, :-m], whole_q[:, 10 + m:40 - m, 0:30 - m], atol=1e-6, rtol=0)
    torch.testing.assert_close(rot[:, :, m:-m, :-m], whole_rot[:, :, 10 + m:40 - m, 0:30 - m], atol=1e-6, rtol=0)


@pytest.mark.parametrize("learner, model", [
    (dict(train_crop_px=64), H.SMALL_MODEL),                                                  # windows in the map
    (dict(train_crop_px=0, rotation_support="kernel", loss_reduction="mean"), H.SMALL_MODEL),  # whole map
    (dict(train_crop_px=64, augment="rotate", executed_pixel_weight=1.0), H.SMALL_MODEL),     # turned windows
    (dict(train_crop_px=64), dataclasses.replace(H.SMALL_MODEL, pick_angle_bins=4)),          # a Q per angle
])
def test_head_crop_trains_exactly_as_the_whole_window(learner, model):
    # Same nets, same batch (picks and a push, one executed pixel at the map's edge): the step's losses, TD
    # errors and every updated weight agree with the head run on the whole window.
    items = H.batch(4, size=96)
    items.append((H.transition(96, seed=9, row=95, col=0, reward=1.0), 0.7, 9))
    items.append((H.transition(96, seed=8, row=50, col=41, reward=1.0), 0.9, 8))
    runs = []
    for head_crop in (False, True):
        t = H.trainer(model=model, head_crop=head_crop, **learner)
        stats = t.train_step(items)
        runs.append((stats, t.model.state_dict()))
    (full, full_w), (crop, crop_w) = runs
    assert crop.loss == pytest.approx(full.loss, rel=1e-5, abs=1e-7)
    assert crop.td_errors == pytest.approx(full.td_errors, rel=1e-5, abs=1e-6)
    assert crop.loss_by_primitive == pytest.approx(full.loss_by_primitive, rel=1e-5, abs=1e-7)
    assert crop.exploration_loss == pytest.approx(full.exploration_loss, rel=1e-5, abs=1e-7)
    moved = 0
    for name, w in full_w.items():
        torch.testing.assert_close(crop_w[name], w, atol=1e-6, rtol=1e-5, msg=name)
    for name, p in H.trainer(model=model, **learner).model.state_dict().items():
        moved += int(not torch.equal(p, full_w[name]))
    assert moved > 10  # the step did train (so the comparison above compared trained weights)
