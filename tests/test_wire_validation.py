"""Wire decoders: one test per validation rule, each checking DecodeError and its message."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from _wire_samples import all_messages, pb_message, pb_transition, sample_batch, transition

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.imagecodec import encode_color_png, encode_depth_png


# ---------------------------------------------------------------------- Transition validation rules
def _set(path: str, value) -> Callable[[pb.Transition], None]:
    def mutate(m: pb.Transition) -> None:
        *parents, leaf = path.split(".")
        target = m
        for p in parents:
            target = getattr(target, p)
        setattr(target, leaf, value)
    return mutate


def _clear(path: str) -> Callable[[pb.Transition], None]:
    def mutate(m: pb.Transition) -> None:
        *parents, leaf = path.split(".")
        target = m
        for p in parents:
            target = getattr(target, p)
        target.ClearField(leaf)
    return mutate


_C8 = encode_color_png(np.zeros((8, 8, 3), np.uint8))
_D8 = encode_depth_png(np.zeros((8, 8), np.float32))

INVALID_TRANSITIONS = {
    **{f"missing {f}": (_clear(f), f"missing field\\(s\\): {f}") for f in (
        "step", "start_ns", "end_ns", "action", "success", "progress_before", "progress_after", "reward", "done",
        "holding_before", "holding_after", "policy_version", "explore_rate")},
    **{f"missing action.{f}": (_clear(f"action.{f}"), f"missing field\\(s\\): action.{f}") for f in (
        "row", "col", "angle_rad", "q_value", "explored")},
    "primitive unspecified": (_set("action.primitive", 0), "action.primitive = 0 is invalid"),
    "primitive unknown": (_set("action.primitive", 9), "action.primitive = 9 is invalid"),
    "actor_id empty": (_set("actor_id", ""), "actor_id = '' is invalid"),
    "actor_id slash": (_set("actor_id", "a/b"), "actor_id = 'a/b' is invalid.*Zenoh key chunk"),
    "actor_id wildcard": (_set("actor_id", "a*"), "actor_id = 'a\\*' is invalid"),
    "actor_id non-ascii": (_set("actor_id", "robot\u00e9"), "actor_id = .* is invalid"),
    "actor_id too long": (_set("actor_id", "a" * 129), "actor_id = 'aaaa.*\\.\\.\\. is invalid: must be 1..128"),
    "episode_id space": (_set("episode_id", "ep 1"), "episode_id = 'ep 1' is invalid"),
    "task empty": (_set("task", ""), "task = '' is invalid"),
    "end before start": (_set("end_ns", 5), "end_ns = 5 is invalid"),
    "color_before missing": (_set("color_before_png", b""), "color_before_png: missing"),
    "depth_after missing": (_set("depth_after_png", b""), "depth_after_png: missing"),
    "color not a png": (_set("color_before_png", b"GIF89a garbage" * 4), "color_before_png: not a PNG"),
    "color without ihdr": (_set("color_before_png", _C8[:8] + b"\0" * 40), "color_before_png: .*13-byte IHDR"),
    "color is a depth png": (_set("color_after_png", _D8), "color_after_png: .*bit depth 16"),
    "depth is a color png": (_set("depth_before_png", _C8), "depth_before_png: .*expected bit depth 16"),
    "sizes differ": (_set("color_after_png", encode_color_png(np.zeros((12, 8, 3), np.uint8))), "differ in size"),
    "not a multiple of 4": (lambda m: [setattr(m, n, p) for n, p in (
        ("color_before_png", encode_color_png(np.zeros((6, 8, 3), np.uint8))),
        ("color_after_png", encode_color_png(np.zeros((6, 8, 3), np.uint8))),
        ("depth_before_png", encode_depth_png(np.zeros((6, 8), np.float32))),
        ("depth_after_png", encode_depth_png(np.zeros((6, 8), np.float32))))], "multiples of 4"),
    "truncated png": (lambda m: setattr(m, "depth_before_png", m.depth_before_png[:-20]),
                      "depth_before_png: malformed PNG: chunk 'IDAT' claims"),
    "corrupt png": (lambda m: setattr(m, "color_after_png", m.color_after_png[:60] + b"?" + m.color_after_png[61:]),
                    "color_after_png: PNG chunk 'IDAT' has a bad CRC: the data is corrupt"),
    "row outside": (_set("action.row", 8), "action.row = 8 is invalid: must be an integer in \\[0, 7\\]"),
    "col outside": (_set("action.col", 1000), "action.col = 1000 is invalid"),
    "angle nan": (_set("action.angle_rad", math.nan), "angle_rad"),
    "angle beyond a turn": (_set("action.angle_rad", 7.0), "action.angle_rad = 7.0 is invalid"),
    "q inf": (_set("action.q_value", math.inf), "action.q_value = inf is invalid: must be a finite number"),
    "progress_before > 1": (_set("progress_before", 1.5), "progress_before = 1.5 is invalid: must be in \\[0.0, 1.0\\]"),
    "progress_after < 0": (_set("progress_after", -0.1), "progress_after = -0.1 is invalid"),
    "progress nan": (_set("progress_after", math.nan), "progress_after = nan is invalid: must be a finite"),
    "reward inf": (_set("reward", -math.inf), "reward = -inf is invalid"),
    "reward too large": (_set("reward", 11.0), "reward = 11.0 is invalid: must be in \\[-10.0, 10.0\\]"),
    "done without reason": (_set("done_reason", ""), "done_reason = '' is invalid"),
    "reason without done": (_set("done", False), "done_reason = 'goal_reached' is invalid: must be empty unless done"),
    "explore rate > 1": (_set("explore_rate", 1.01), "explore_rate = 1.01 is invalid"),
    "negative priority": (_set("initial_priority", -1.0), "initial_priority = -1.0 is invalid"),
    "nan priority": (_set("initial_priority", math.nan), "initial_priority = nan is invalid"),
}


@pytest.mark.parametrize("case", sorted(INVALID_TRANSITIONS))
def test_invalid_transition_field_raises_a_helpful_decode_error(case: str) -> None:
    mutate, match = INVALID_TRANSITIONS[case]
    m = pb_transition()
    mutate(m)
    with pytest.raises(DecodeError, match="^invalid Transition: .*" + match):
        wire.decode_transition(m.SerializeToString())


def test_expected_shape_mismatch_is_rejected() -> None:
    with pytest.raises(DecodeError, match=r"heightmap size = \(8, 8\) is invalid: heightmaps must be 224x224"):
        wire.decode_transition(wire.encode_transition(transition()), expected_shape=(224, 224))


def test_png_bomb_header_is_refused_before_decoding() -> None:
    m = pb_transition()
    m.color_before_png = _C8[:16] + (100_000).to_bytes(4, "big") + (100_000).to_bytes(4, "big") + _C8[24:]
    with pytest.raises(DecodeError, match="color_before_png: .*100000x100000.*refused before decompressing"):
        wire.decode_transition(m.SerializeToString())


@pytest.mark.parametrize("data, match", [
    (b"\xff\xff\xff", "not a protobuf Transition"),
    (b"", "schema_version is missing"),
    ("text", "expected bytes, got str"),
    (b"\0" * (64 * 1024 * 1024 + 1), "at most"),
])
def test_non_messages_are_rejected(data, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        wire.decode_transition(data)


def test_truncated_transition_is_rejected() -> None:
    data = wire.encode_transition(transition())
    for cut in (1, 10, len(data) // 2, len(data) - 1):
        with pytest.raises(DecodeError, match="^invalid Transition: "):
            wire.decode_transition(data[:cut])


# --------------------------------------------------------------------- other messages' validation rules
def _mutated(name: str, mutate: Callable) -> bytes:
    m = pb_message(name)
    mutate(m)
    return m.SerializeToString()


INVALID_OTHERS = [
    ("weights_announcement", lambda m: setattr(m, "sha256_hex", "AB" * 32), "sha256_hex = 'ABAB"),
    ("weights_announcement", lambda m: setattr(m, "sha256_hex", "ab"), "64 lowercase hex digits"),
    ("weights_announcement", lambda m: setattr(m, "size_bytes", 0), "size_bytes = 0 is invalid"),
    ("weights_announcement", lambda m: m.ClearField("version"), "missing field\\(s\\): version"),
    ("weights", lambda m: setattr(m, "safetensors", m.safetensors[:-1]), "the payload is corrupt or truncated"),
    ("weights", lambda m: setattr(m, "safetensors", b""), "safetensors must be 1.."),
    ("weights", lambda m: m.ClearField("version"), "missing field\\(s\\): version"),
    ("exploration_rate", lambda m: setattr(m, "value", 1.5), "value = 1.5 is invalid: must be in \\[0.0, 1.0\\]"),
    ("exploration_rate", lambda m: setattr(m, "value", math.nan), "value = nan is invalid"),
    ("exploration_rate", lambda m: m.ClearField("value"), "missing field\\(s\\): value"),
    ("exploration_rate", lambda m: setattr(m, "policy", "lae?"), "policy = 'lae\\?' is invalid"),
    ("priority_update", lambda m: m.priorities.append(1.0), "item_ids has 3 entries but priorities has 4"),
    ("priority_update", lambda m: m.priorities.__setitem__(1, math.nan), "priorities\\[1\\] = nan is invalid"),
    ("priority_update", lambda m: m.priorities.__setitem__(2, -0.5), "priorities\\[2\\] = -0.5 is invalid"),
    ("priority_update", lambda m: m.item_ids.extend(range(70000)), "at most 65536"),
    ("sample_request", lambda m: setattr(m, "batch_size", 0), "batch_size = 0 is invalid"),
    ("sample_request", lambda m: setattr(m, "batch_size", 4097), "batch_size = 4097 is invalid"),
    ("sample_request", lambda m: m.ClearField("batch_size"), "missing field\\(s\\): batch_size"),
    ("sample_request", lambda m: setattr(m, "request_id", "#1"), "request_id = '#1' is invalid"),
    ("sample_batch", lambda m: m.items[1].ClearField("transition"), "items\\[1\\]: missing field\\(s\\): transition"),
    ("sample_batch", lambda m: setattr(m.items[0], "probability", 0.0), "probability = 0.0 is invalid: must be in \\(0.0"),
    ("sample_batch", lambda m: setattr(m.items[0], "probability", 1.5), "probability = 1.5 is invalid"),
    ("sample_batch", lambda m: setattr(m.items[1], "is_weight", math.inf), "is_weight = inf is invalid"),
    ("sample_batch", lambda m: setattr(m.items[1].transition, "reward", 99.0),
     "items\\[1\\]: transition: reward = 99.0 is invalid"),
    ("sample_batch", lambda m: m.items[1].transition.CopyFrom(pb_transition(h=16, w=16)),
     "items\\[1\\]: transition: heightmap size = \\(16, 16\\) is invalid: heightmaps must be 8x8"),
    ("sample_batch", lambda m: m.items[1].transition.schema_version.__setattr__("major", 3),
     "items\\[1\\]: transition: schema_version 3.0"),
    ("sample_batch", lambda m: m.items.extend([m.items[0]] * 4096), "4098 items in one batch; at most 4096"),
    ("sample_batch", lambda m: m.ClearField("buffer_size"), "missing field\\(s\\): buffer_size"),
    ("insert_ack", lambda m: setattr(m, "status", 0), "status = 0 is invalid"),
    ("insert_ack", lambda m: setattr(m, "status", 42), "status = 42 is invalid"),
    ("insert_ack", lambda m: m.ClearField("item_id"), "item_id = None is invalid"),
    ("insert_ack", lambda m: setattr(m, "status", pb.INSERT_STATUS_REJECTED), "a rejected insert has no item_id"),
    ("insert_ack", lambda m: setattr(m, "detail", "bell\x07"), "detail = 'bell\\\\x07' is invalid: must be printable"),
    ("insert_ack", lambda m: setattr(m, "detail", "x" * 1025), "at most 1024 characters"),
    ("insert_ack", lambda m: m.ClearField("step"), "missing field\\(s\\): step"),
]


@pytest.mark.parametrize("name, mutate, match", INVALID_OTHERS, ids=[f"{n}-{i}" for i, (n, _, _) in
                                                                    enumerate(INVALID_OTHERS)])
def test_invalid_message_field_raises_a_helpful_decode_error(name: str, mutate: Callable, match: str) -> None:
    title = "".join(part.capitalize() for part in name.split("_"))
    decode = all_messages()[name][2]
    with pytest.raises(DecodeError, match=f"^invalid {title}: .*{match}"):
        decode(_mutated(name, mutate))


def test_weights_must_match_the_announced_digest() -> None:
    msg, _, _ = all_messages()["weights"]
    data = wire.encode_weights(msg)
    assert wire.decode_weights(data, expected_sha256=msg.sha256_hex) == msg
    with pytest.raises(DecodeError, match="differs from the announced"):
        wire.decode_weights(data, expected_sha256="0" * 64)


def test_constructing_an_invalid_message_raises_value_error_not_decode_error() -> None:
    with pytest.raises(ValueError, match="reward = nan") as info:
        transition(reward=math.nan)
    assert not isinstance(info.value, DecodeError)
    with pytest.raises(ValueError, match="depth_before must be a float32"):
        transition(depth_before=np.zeros((8, 8), np.float64))
    with pytest.raises(ValueError, match="heightmaps differ in size"):
        transition(color_after=np.zeros((12, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="different sizes"):
        wire.SampleBatchMsg("r", (wire.SampleItem(1, 1.0, 1.0, transition()),
                                  wire.SampleItem(2, 1.0, 1.0, transition(16, 16))), 2)
    with pytest.raises(ValueError, match="must be equally long"):
        wire.PriorityUpdateMsg((1, 2), (0.5,))


def test_encoding_rejects_depth_beyond_the_16_bit_range() -> None:
    depth = np.full((8, 8), 0.7, np.float32)
    with pytest.raises(ValueError, match="exceeds the encodable maximum"):
        wire.encode_transition(transition(depth_after=depth))


def test_sample_batch_with_raw_items_encodes_like_decoded_items() -> None:
    raw = sample_batch()
    decoded = dataclasses.replace(raw, items=tuple(
        dataclasses.replace(it, transition=wire.decode_transition(it.transition))
        if isinstance(it.transition, bytes) else it for it in raw.items))
    assert wire.encode_sample_batch(raw) == wire.encode_sample_batch(decoded)
