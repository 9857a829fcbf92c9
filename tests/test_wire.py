"""Wire messages: round trips, versioning, weights, generated code, MCAP (rules: test_wire_validation.py)."""

from __future__ import annotations

import ast
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _wire_samples import (
    all_messages,
    assert_transitions_equal,
    heightmaps,
    pb_message,
    pb_transition,
    transition,
)

import romannet.common
from romannet.common import wire
from romannet.common.action import Action
from romannet.common.errors import DecodeError
from romannet.common.interfaces import Observation, StepResult

COMMON_DIR = Path(romannet.common.__file__).parent


# ------------------------------------------------------------------------------------------ round trips
def test_transition_round_trip_is_exact() -> None:
    msg = transition(224, 224)
    back = wire.decode_transition(wire.encode_transition(msg), expected_shape=(224, 224))
    assert_transitions_equal(back, msg)


def test_transition_round_trip_quantises_depth_to_10_um() -> None:
    color, _ = heightmaps(16, 16)
    depth = np.random.default_rng(9).uniform(0, 0.5, (16, 16)).astype(np.float32)
    msg = transition(16, 16, depth_before=depth, color_before=color)
    back = wire.decode_transition(wire.encode_transition(msg))
    assert np.abs(back.depth_before.astype(np.float64) - depth).max() <= 5e-6 + 6e-8
    again = wire.decode_transition(wire.encode_transition(back))
    np.testing.assert_array_equal(again.depth_before, back.depth_before)


def test_transition_optional_fields_round_trip_as_none() -> None:
    msg = transition(initial_priority=None, sim_seed=None, done=False, done_reason="", step=0, start_ns=0,
                     end_ns=0, policy_version=0, reward=0.0, success=False,
                     action=Action("push", 0, 0, 0.0, 0.0, False))
    back = wire.decode_transition(wire.encode_transition(msg))
    assert_transitions_equal(back, msg)
    assert back.initial_priority is None and back.sim_seed is None


def test_a_transition_is_built_from_the_observation_the_action_and_the_step_result() -> None:
    color_b, depth_b = heightmaps(8, 8, 1)
    color_a, depth_a = heightmaps(8, 8, 2)
    action = Action("pick", 3, 4, 0.5, np.float32(0.25), explored=True)
    result = StepResult(Observation(color_a, depth_a, True), np.bool_(True), 0.25, np.float64(0.5), 0.5,
                        done=False, done_reason="", detail="", info={"seed": 17, "step": 3})
    msg = wire.TransitionMsg.from_step(Observation(color_b, depth_b, False), action, result, actor_id="a0",
                                       episode_id="ep000001", step=2, start_ns=10, end_ns=20, task="stacking",
                                       policy_version=4, explore_rate=0.1, next_value=0.7, next_value_version=4)
    assert (msg.color_before, msg.depth_before, msg.color_after, msg.depth_after) == (color_b, depth_b, color_a, depth_a)
    assert (msg.success, msg.progress_before, msg.progress_after, msg.reward) == (True, 0.25, 0.5, 0.5)
    assert type(msg.success) is bool and type(msg.progress_after) is float  # plain Python values
    assert (msg.holding_before, msg.holding_after, msg.done, msg.done_reason) == (False, True, False, "")
    assert (msg.sim_seed, msg.initial_priority, msg.next_value, msg.next_value_version) == (17, None, 0.7, 4)
    assert_transitions_equal(wire.decode_transition(wire.encode_transition(msg)), msg)
    # A real robot reports no scene seed; an episode's end carries its reason.
    robot = StepResult(Observation(color_a, depth_a, False), False, 0.5, 0.5, 0.0, True, "robot_stopped",
                       "protective_stop", {"episode_seed": 3})
    ended = wire.TransitionMsg.from_step(Observation(color_b, depth_b, True), action, robot, actor_id="ur",
                                         episode_id="ep000002", step=0, start_ns=0, end_ns=0, task="stacking")
    assert (ended.sim_seed, ended.done, ended.done_reason, ended.success) == (None, True, "robot_stopped", False)


@pytest.mark.parametrize("name", sorted(all_messages()))
def test_every_message_round_trips(name: str) -> None:
    msg, encode, decode = all_messages()[name]
    back = decode(encode(msg))
    if name == "transition":
        assert_transitions_equal(back, msg)
    elif name == "sample_batch":
        _assert_batches_equal(back, msg)
    else:
        assert back == msg


def _assert_batches_equal(back: wire.SampleBatchMsg, msg: wire.SampleBatchMsg) -> None:
    assert (back.request_id, back.buffer_size, len(back.items)) == (msg.request_id, msg.buffer_size, len(msg.items))
    for got, want in zip(back.items, msg.items, strict=True):
        assert (got.item_id, got.probability, got.is_weight) == (want.item_id, want.probability, want.is_weight)
        expected = want.transition
        if isinstance(expected, bytes):
            expected = wire.decode_transition(expected)
        assert_transitions_equal(got.transition, expected)


def test_empty_batch_and_rejected_ack_round_trip() -> None:
    batch = wire.SampleBatchMsg("req-2", (), 0)
    assert wire.decode_sample_batch(wire.encode_sample_batch(batch)).items == ()
    ack = wire.InsertAckMsg("sim-0", "ep-1", 0, "rejected", None, "invalid Transition: reward = nan")
    assert wire.decode_insert_ack(wire.encode_insert_ack(ack)) == ack


def test_decoders_accept_bytearray_and_memoryview() -> None:
    data = wire.encode_exploration_rate(wire.ExplorationRateMsg(1, 0.5, "lae"))
    assert wire.decode_exploration_rate(bytearray(data)) == wire.decode_exploration_rate(memoryview(data))


# ---------------------------------------------------------------------------------------- versioning
def test_newer_minor_version_with_unknown_fields_is_accepted() -> None:
    m = pb_transition()
    m.schema_version.minor = 7
    # A field a later minor version might add (number 100, varint 1): protobuf skips it.
    data = m.SerializeToString() + bytes([0xA0, 0x06, 1])  # tag 100 << 3 | 0 = 800 as a varint
    assert wire.decode_transition(data).step == 7


@pytest.mark.parametrize("major", [0, 2, 1000])
def test_unknown_major_version_is_rejected(major: int) -> None:
    m = pb_transition()
    m.schema_version.major = major
    with pytest.raises(DecodeError, match=f"schema_version {major}.0 is not supported"):
        wire.decode_transition(m.SerializeToString())


def test_missing_schema_version_is_rejected() -> None:
    m = pb_transition()
    m.ClearField("schema_version")
    with pytest.raises(DecodeError, match="schema_version is missing"):
        wire.decode_transition(m.SerializeToString())


@pytest.mark.parametrize("name", sorted(all_messages()))
def test_every_message_checks_the_major_version(name: str) -> None:
    m = pb_message(name)
    m.schema_version.major = 2
    with pytest.raises(DecodeError, match="not supported"):
        all_messages()[name][2](m.SerializeToString())


# ------------------------------------------------------------------------- weights <-> safetensors
def test_state_dict_round_trip_and_digest_check() -> None:
    torch = pytest.importorskip("torch")
    from romannet.common import weightscodec
    state = {"net.conv.weight": torch.randn(4, 3, 3, 3), "net.bn.num_batches_tracked": torch.tensor(5),
             "half": torch.randn(2, 2).to(torch.bfloat16)}
    msg, announcement = weightscodec.make_weights(9, state, created_ns=123)
    assert (announcement.version, announcement.sha256_hex, announcement.size_bytes) == (
        9, msg.sha256_hex, len(msg.safetensors))
    back = weightscodec.weights_state_dict(wire.decode_weights(wire.encode_weights(msg), announcement.sha256_hex))
    assert back.keys() == state.keys()
    for name, tensor in state.items():
        assert back[name].dtype == tensor.dtype and torch.equal(back[name], tensor)
    with pytest.raises(DecodeError, match="differs from the expected"):
        weightscodec.decode_state_dict(msg.safetensors, "f" * 64)


def test_state_dict_rejects_nan_pickle_and_garbage() -> None:
    torch = pytest.importorskip("torch")
    import io

    from romannet.common import weightscodec
    with pytest.raises(ValueError, match="NaN or inf"):
        weightscodec.encode_state_dict({"w": torch.tensor([1.0, math.nan])})
    import safetensors.torch
    with pytest.raises(DecodeError, match="'w'.*contain NaN or inf"):
        weightscodec.decode_state_dict(safetensors.torch.save({"w": torch.tensor([math.inf])}))
    pickled = io.BytesIO()
    torch.save({"w": torch.ones(2)}, pickled)  # a torch.save/pickle payload must never be loaded
    for data in (pickled.getvalue(), b"", b"\xff" * 64, "str"):
        with pytest.raises(DecodeError, match="^invalid safetensors weights: "):
            weightscodec.decode_state_dict(data)


# ------------------------------------------------------------------------- generated code, versions
def _serialized_descriptor(source: str) -> bytes:
    match = re.search(r"AddSerializedFile\((b'.*?')\)\n", source, re.S)
    assert match, "no serialized descriptor in the generated code"
    return ast.literal_eval(match.group(1))


def _gencode_version(source: str) -> tuple[int, ...]:
    match = re.search(r"# Protobuf Python Version: (\d+)\.(\d+)\.(\d+)", source)
    assert match, "no gencode version in the generated code"
    return tuple(int(g) for g in match.groups())


def test_committed_pb2_is_up_to_date_with_the_proto(tmp_path: Path) -> None:
    pytest.importorskip("grpc_tools")
    proc = subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{COMMON_DIR}", f"--python_out={tmp_path}",
                           str(COMMON_DIR / "romannet.proto")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    fresh = (tmp_path / "romannet_pb2.py").read_text()
    committed = (COMMON_DIR / "romannet_pb2.py").read_text()
    hint = "common/romannet_pb2.py is stale: python -m grpc_tools.protoc -I common --python_out=common common/romannet.proto"
    assert _serialized_descriptor(fresh) == _serialized_descriptor(committed), hint
    if _gencode_version(fresh) == _gencode_version(committed):  # another protoc only changes the header
        assert fresh == committed, hint


def test_pyproject_protobuf_floor_admits_no_runtime_older_than_the_gencode() -> None:
    pyproject = COMMON_DIR.parent / "pyproject.toml"
    if not pyproject.exists():
        pytest.skip("not running from a source checkout")
    floor = re.search(r'"protobuf>=([\d.]+)', pyproject.read_text())
    assert floor, "pyproject.toml has no protobuf>= requirement"
    gencode = _gencode_version((COMMON_DIR / "romannet_pb2.py").read_text())
    assert tuple(int(p) for p in floor.group(1).split(".")) >= gencode, (
        f"romannet_pb2.py needs protobuf>={'.'.join(map(str, gencode))} at runtime; raise the floor in pyproject.toml")


# ------------------------------------------------------------------------------------------------ MCAP
def test_mcap_schema_lets_mcap_tools_read_transitions(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_protobuf.decoder import DecoderFactory

    name, encoding, data = wire.mcap_schema()
    assert (name, encoding) == ("romannet.v1.Transition", "protobuf")
    msg = transition(16, 16)
    path = tmp_path / "episode.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="romannet-tests")
        schema_id = writer.register_schema(name=name, encoding=encoding, data=data)
        channel_id = writer.register_channel(topic="/romannet/transition", message_encoding="protobuf",
                                             schema_id=schema_id)
        writer.add_message(channel_id=channel_id, log_time=msg.end_ns, publish_time=msg.end_ns,
                           data=wire.encode_transition(msg))
        writer.finish()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        [(schema, channel, record, dynamic)] = list(reader.iter_decoded_messages())
    assert (schema.name, channel.topic, record.log_time) == (name, "/romannet/transition", msg.end_ns)
    # The class mcap built from the schema alone reads the fields: the schema is self-contained.
    assert (dynamic.actor_id, dynamic.action.row, dynamic.reward) == (msg.actor_id, msg.action.row, msg.reward)
    assert_transitions_equal(wire.decode_transition(record.data), msg)


def test_mcap_schema_names_other_messages_and_rejects_unknown_ones() -> None:
    assert wire.mcap_schema("SampleBatch")[0] == "romannet.v1.SampleBatch"
    with pytest.raises(ValueError, match="message_name = 'Nope'"):
        wire.mcap_schema("Nope")
