"""Bytes on the wire: encode and decode every message of schema romannet.v1 (common/romannet.proto).

`encode_<message>(msg) -> bytes` serialises one of the frozen dataclasses of common/wire_messages.py
(re-exported here); `decode_<message>(data) -> msg` parses untrusted bytes and validates everything:
protobuf framing, schema version, missing fields, enum values, heightmap PNG headers (before anything
is decompressed), shapes, dtypes, ranges, finiteness, identifiers. Any failure raises
romannet.common.errors.DecodeError and nothing else, with a message that says what is wrong.

Versioning: every message carries schema_version (major, minor). Decoders accept any minor version of
SCHEMA_MAJOR (new minor versions only add fields, which protobuf skips) and reject other majors.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
from google.protobuf import message as pb_message
from google.protobuf.descriptor_pb2 import FileDescriptorProto, FileDescriptorSet

from . import romannet_pb2 as pb
from .action import Action
from .errors import DecodeError
from .imagecodec import (
    decode_color_png,
    decode_depth_png,
    encode_color_png,
    encode_depth_png,
    read_png_header,
)
from .wire_messages import (
    INSERT_STATUSES,
    MAX_BATCH_ITEMS,
    MAX_PRIORITY_ITEMS,
    MAX_WEIGHTS_BYTES,
    REWARD_LIMIT,
    ExplorationRateMsg,
    InsertAckMsg,
    PriorityUpdateMsg,
    SampleBatchMsg,
    SampleItem,
    SampleRequestMsg,
    TransitionMsg,
    WeightsAnnouncementMsg,
    WeightsMsg,
    sha256_hex,
)
from .wire_validate import check_expected_shape, check_side_px, show

__all__ = [
    "SCHEMA_MAJOR", "SCHEMA_MINOR", "REWARD_LIMIT", "MAX_BATCH_ITEMS", "MAX_PRIORITY_ITEMS",
    "MAX_WEIGHTS_BYTES",
    "TransitionMsg", "WeightsAnnouncementMsg", "WeightsMsg", "ExplorationRateMsg", "PriorityUpdateMsg",
    "SampleRequestMsg", "SampleItem", "SampleBatchMsg", "InsertAckMsg", "sha256_hex",
    "encode_transition", "decode_transition", "encode_weights_announcement", "decode_weights_announcement",
    "encode_weights", "decode_weights", "encode_exploration_rate", "decode_exploration_rate",
    "encode_priority_update", "decode_priority_update", "encode_sample_request", "decode_sample_request",
    "encode_sample_batch", "decode_sample_batch", "encode_insert_ack", "decode_insert_ack", "mcap_schema",
]

SCHEMA_MAJOR = 1
SCHEMA_MINOR = 0
# Refuse oversized input before parsing it. A 224x224 transition is ~10-300 kB.
_MAX_SMALL_BYTES = 64 * 1024
_MAX_PRIORITY_BYTES = 4 * 1024 * 1024
_MAX_TRANSITION_BYTES = 64 * 1024 * 1024
_MAX_BATCH_BYTES = 1 << 30
_MAX_WEIGHTS_MESSAGE_BYTES = MAX_WEIGHTS_BYTES + _MAX_SMALL_BYTES

_PRIMITIVE_TO_PB = {"push": pb.PRIMITIVE_PUSH, "pick": pb.PRIMITIVE_PICK, "place": pb.PRIMITIVE_PLACE}
_PRIMITIVE_FROM_PB = {v: k for k, v in _PRIMITIVE_TO_PB.items()}
_STATUS_TO_PB = {"accepted": pb.INSERT_STATUS_ACCEPTED, "duplicate": pb.INSERT_STATUS_DUPLICATE,
                 "rejected": pb.INSERT_STATUS_REJECTED}
_STATUS_FROM_PB = {v: k for k, v in _STATUS_TO_PB.items()}
_PNGS = (("color_before_png", decode_color_png), ("depth_before_png", decode_depth_png),
         ("color_after_png", decode_color_png), ("depth_after_png", decode_depth_png))
_TRANSITION_REQUIRED = ("step", "start_ns", "end_ns", "action", "success", "progress_before",
                        "progress_after", "reward", "done", "holding_before", "holding_after",
                        "policy_version", "explore_rate")
_ACTION_REQUIRED = ("row", "col", "angle_rad", "q_value", "explored")

_F = TypeVar("_F", bound=Callable[..., Any])
_M = TypeVar("_M", bound=pb_message.Message)


# ---------------------------------------------------------------------------------------------- helpers
def _describe(exc: BaseException) -> str:
    # Our own checks raise ValueError with a readable message; anything else gets its type named.
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


def _decoder(what: str, max_bytes: int) -> Callable[[_F], _F]:
    """Decorator: size-check the input, and turn every failure into DecodeError('invalid <what>: ...')."""
    def wrap(fn: _F) -> _F:
        @functools.wraps(fn)
        def decode(data: bytes, *args: Any, **kwargs: Any) -> Any:
            try:
                if not isinstance(data, bytes | bytearray | memoryview):
                    raise ValueError(f"expected bytes, got {type(data).__name__}")
                if len(data) > max_bytes:
                    raise ValueError(f"message is {len(data)} bytes; at most {max_bytes} are accepted")
                return fn(bytes(data), *args, **kwargs)
            except Exception as exc:  # the contract: DecodeError and nothing else
                raise DecodeError(f"invalid {what}: {_describe(exc)}") from exc
        return decode  # type: ignore[return-value]
    return wrap


@contextlib.contextmanager
def _within(prefix: str) -> Iterator[None]:
    """Prefix errors raised inside with the field they concern, e.g. 'items[3].transition: ...'."""
    try:
        yield
    except Exception as exc:  # re-raised with context; the decorator makes it DecodeError
        raise ValueError(f"{prefix}: {_describe(exc)}") from exc


def _set_version(out: pb_message.Message) -> None:
    out.schema_version.major = SCHEMA_MAJOR
    out.schema_version.minor = SCHEMA_MINOR


def _check_version(msg: pb_message.Message) -> None:
    if not msg.HasField("schema_version"):
        raise ValueError("schema_version is missing")
    version = msg.schema_version
    if version.major != SCHEMA_MAJOR:
        raise ValueError(f"schema_version {version.major}.{version.minor} is not supported: this decoder "
                         f"reads major version {SCHEMA_MAJOR} (upgrade the older side)")


def _require(msg: pb_message.Message, names: tuple[str, ...], prefix: str = "") -> None:
    missing = [prefix + name for name in names if not msg.HasField(name)]
    if missing:
        raise ValueError(f"missing field(s): {', '.join(missing)}")


def _parse(cls: type[_M], data: bytes) -> _M:
    msg = cls()
    try:
        msg.ParseFromString(data)
    except pb_message.DecodeError as exc:
        raise ValueError(f"not a protobuf {cls.__name__} message ({exc})") from exc
    _check_version(msg)
    return msg


# ------------------------------------------------------------------------------------------- Transition
# The one mapping between TransitionMsg and pb.Transition (same field names), both directions. Heightmaps
# are PNGs on the wire; the action is a nested message; the optional fields are unset when None.
_SCALARS = (("actor_id", str), ("episode_id", str), ("task", str), ("step", int), ("start_ns", int),
            ("end_ns", int), ("success", bool), ("progress_before", float), ("progress_after", float),
            ("reward", float), ("done", bool), ("done_reason", str), ("holding_before", bool),
            ("holding_after", bool), ("policy_version", int), ("explore_rate", float))
_OPTIONAL = (("initial_priority", float), ("sim_seed", int))


def _fill_transition(out: pb.Transition, msg: TransitionMsg) -> None:
    _set_version(out)
    for name, cast in _SCALARS:
        setattr(out, name, cast(getattr(msg, name)))
    out.color_before_png = encode_color_png(msg.color_before)
    out.depth_before_png = encode_depth_png(msg.depth_before)
    out.color_after_png = encode_color_png(msg.color_after)
    out.depth_after_png = encode_depth_png(msg.depth_after)
    a = msg.action
    out.action.primitive = _PRIMITIVE_TO_PB[a.primitive]
    out.action.row, out.action.col = int(a.row), int(a.col)
    out.action.angle_rad, out.action.q_value = float(a.angle_rad), float(a.q_value)
    out.action.explored = bool(a.explored)
    for name, cast in _OPTIONAL:
        if getattr(msg, name) is not None:
            setattr(out, name, cast(getattr(msg, name)))
    if msg.next_value is not None:
        out.next_value, out.next_value_version = float(msg.next_value), int(msg.next_value_version)


def transition_msg(t: pb.Transition, primitive: str, color_before: np.ndarray, depth_before: np.ndarray,
                   color_after: np.ndarray, depth_after: np.ndarray) -> TransitionMsg:
    """The dataclass of a checked protobuf Transition (checked_primitive), its heightmaps decoded by the
    caller: the replay server's validation passes placeholders, it keeps no decoded pixels."""
    a = t.action
    has_next = t.HasField("next_value") and t.HasField("next_value_version")
    return TransitionMsg(
        **{name: getattr(t, name) for name, _ in _SCALARS},
        **{name: getattr(t, name) if t.HasField(name) else None for name, _ in _OPTIONAL},
        color_before=color_before, depth_before=depth_before, color_after=color_after, depth_after=depth_after,
        action=Action(primitive, a.row, a.col, a.angle_rad, a.q_value, a.explored),
        next_value=t.next_value if has_next else None,
        next_value_version=t.next_value_version if has_next else None,
    )


def encode_transition(msg: TransitionMsg) -> bytes:
    """Protobuf bytes of a transition; heightmaps become lossless PNGs (depth quantised to 1e-5 m)."""
    out = pb.Transition()
    _fill_transition(out, msg)
    return out.SerializeToString()


def checked_primitive(t: pb.Transition) -> str:
    """The checks of a parsed Transition before its pixels (schema version, required fields), and the name
    of its action's primitive. Raises ValueError; the replay server's insert check runs the same."""
    _check_version(t)
    _require(t, _TRANSITION_REQUIRED)
    _require(t.action, _ACTION_REQUIRED, "action.")
    primitive = _PRIMITIVE_FROM_PB.get(t.action.primitive)
    if primitive is None:
        raise ValueError(f"action.primitive = {t.action.primitive} is invalid: must be PUSH, PICK or PLACE")
    return primitive


def check_png_sizes(t: pb.Transition, expected_shape: tuple[int, int] | None) -> None:
    """All four PNG headers agree on a valid size, read before any pixel is decompressed."""
    sizes = {}
    for name, _ in _PNGS:
        with _within(name):
            if not getattr(t, name):
                raise ValueError("missing")
            sizes[name] = read_png_header(getattr(t, name))[:2]
    if len(set(sizes.values())) != 1:
        raise ValueError(f"heightmap PNGs differ in size {sizes}; before and after, color and depth "
                         "must match")
    h, w = sizes["color_before_png"]
    check_side_px("heightmap size", h, w)
    check_expected_shape("heightmap size", (h, w), expected_shape)


def _transition_from_pb(t: pb.Transition, expected_shape: tuple[int, int] | None) -> TransitionMsg:
    primitive = checked_primitive(t)
    check_png_sizes(t, expected_shape)
    images = {}
    for name, decode_png in _PNGS:
        with _within(name):
            images[name] = decode_png(getattr(t, name))
    return transition_msg(t, primitive, images["color_before_png"], images["depth_before_png"],
                          images["color_after_png"], images["depth_after_png"])


@_decoder("Transition", _MAX_TRANSITION_BYTES)
def decode_transition(data: bytes, expected_shape: tuple[int, int] | None = None) -> TransitionMsg:
    """Validated transition from bytes; expected_shape (h, w) in pixels, if given, must match."""
    return _transition_from_pb(_parse(pb.Transition, data), expected_shape)


# ---------------------------------------------------------------------------------------------- Weights
def encode_weights_announcement(msg: WeightsAnnouncementMsg) -> bytes:
    """Protobuf bytes of a weights announcement."""
    out = pb.WeightsAnnouncement(version=msg.version, sha256_hex=msg.sha256_hex, size_bytes=msg.size_bytes,
                                 created_ns=msg.created_ns, pushed=msg.pushed)
    _set_version(out)
    return out.SerializeToString()


@_decoder("WeightsAnnouncement", _MAX_SMALL_BYTES)
def decode_weights_announcement(data: bytes) -> WeightsAnnouncementMsg:
    """Validated weights announcement from bytes."""
    m = _parse(pb.WeightsAnnouncement, data)
    _require(m, ("version", "size_bytes", "created_ns"))
    return WeightsAnnouncementMsg(m.version, m.sha256_hex, m.size_bytes, m.created_ns, m.pushed)


def encode_weights(msg: WeightsMsg) -> bytes:
    """Protobuf bytes of a weights version (the safetensors payload as is)."""
    out = pb.Weights(version=msg.version, sha256_hex=msg.sha256_hex, safetensors=msg.safetensors)
    _set_version(out)
    return out.SerializeToString()


@_decoder("Weights", _MAX_WEIGHTS_MESSAGE_BYTES)
def decode_weights(data: bytes, expected_sha256: str | None = None) -> WeightsMsg:
    """Weights whose payload matches their SHA-256 and, if given, the announced expected_sha256.

    The payload stays bytes; weightscodec.decode_state_dict turns it into tensors (without pickle).
    """
    m = _parse(pb.Weights, data)
    _require(m, ("version",))
    msg = WeightsMsg(m.version, m.sha256_hex, m.safetensors)
    if expected_sha256 is not None and msg.sha256_hex != expected_sha256:
        raise ValueError(f"sha256_hex = {msg.sha256_hex} differs from the announced {show(expected_sha256)}")
    return msg


@_decoder("ExplorationRate", _MAX_SMALL_BYTES)
def decode_exploration_rate(data: bytes) -> ExplorationRateMsg:
    """Validated exploration rate from bytes (value in [0, 1])."""
    m = _parse(pb.ExplorationRate, data)
    _require(m, ("version", "value"))
    return ExplorationRateMsg(m.version, m.value, m.policy)


def encode_exploration_rate(msg: ExplorationRateMsg) -> bytes:
    """Protobuf bytes of an exploration rate."""
    out = pb.ExplorationRate(version=msg.version, value=float(msg.value), policy=msg.policy)
    _set_version(out)
    return out.SerializeToString()


# ------------------------------------------------------------------------------------------------ replay
def encode_priority_update(msg: PriorityUpdateMsg) -> bytes:
    """Protobuf bytes of a priority update."""
    out = pb.PriorityUpdate(item_ids=[int(i) for i in msg.item_ids],
                            priorities=[float(p) for p in msg.priorities])
    _set_version(out)
    return out.SerializeToString()


@_decoder("PriorityUpdate", _MAX_PRIORITY_BYTES)
def decode_priority_update(data: bytes) -> PriorityUpdateMsg:
    """Validated priority update from bytes (equal lengths, priorities finite and >= 0)."""
    m = _parse(pb.PriorityUpdate, data)
    if len(m.item_ids) > MAX_PRIORITY_ITEMS:
        raise ValueError(f"{len(m.item_ids)} item_ids in one update; at most {MAX_PRIORITY_ITEMS}")
    return PriorityUpdateMsg(tuple(m.item_ids), tuple(m.priorities))


def encode_sample_request(msg: SampleRequestMsg) -> bytes:
    """Protobuf bytes of a sample request."""
    out = pb.SampleRequest(request_id=msg.request_id, batch_size=msg.batch_size)
    _set_version(out)
    return out.SerializeToString()


@_decoder("SampleRequest", _MAX_SMALL_BYTES)
def decode_sample_request(data: bytes) -> SampleRequestMsg:
    """Validated sample request from bytes."""
    m = _parse(pb.SampleRequest, data)
    _require(m, ("batch_size",))
    return SampleRequestMsg(m.request_id, m.batch_size)


def encode_sample_batch(msg: SampleBatchMsg) -> bytes:
    """Protobuf bytes of a batch; items holding encoded transition bytes are embedded as they are."""
    out = pb.SampleBatch(request_id=msg.request_id, buffer_size=msg.buffer_size)
    _set_version(out)
    for item in msg.items:
        it = out.items.add(item_id=item.item_id, probability=float(item.probability),
                           is_weight=float(item.is_weight))
        if isinstance(item.transition, bytes):
            it.transition.MergeFromString(item.transition)
        else:
            _fill_transition(it.transition, item.transition)
    return out.SerializeToString()


@_decoder("SampleBatch", _MAX_BATCH_BYTES)
def decode_sample_batch(data: bytes, expected_shape: tuple[int, int] | None = None) -> SampleBatchMsg:
    """Validated batch; every transition must have expected_shape (h, w) if given, else the first's."""
    m = _parse(pb.SampleBatch, data)
    _require(m, ("buffer_size",))
    if len(m.items) > MAX_BATCH_ITEMS:  # before decoding any PNG
        raise ValueError(f"{len(m.items)} items in one batch; at most {MAX_BATCH_ITEMS}")
    items = []
    shape = expected_shape
    for i, it in enumerate(m.items):
        with _within(f"items[{i}]"):
            _require(it, ("item_id", "probability", "is_weight", "transition"))
            with _within("transition"):
                transition = _transition_from_pb(it.transition, shape)
            items.append(SampleItem(it.item_id, it.probability, it.is_weight, transition))
        shape = shape or transition.shape
    return SampleBatchMsg(m.request_id, tuple(items), m.buffer_size)


def encode_insert_ack(msg: InsertAckMsg) -> bytes:
    """Protobuf bytes of an insert acknowledgement."""
    out = pb.InsertAck(actor_id=msg.actor_id, episode_id=msg.episode_id, step=msg.step,
                       status=_STATUS_TO_PB[msg.status], detail=msg.detail)
    if msg.item_id is not None:
        out.item_id = msg.item_id
    _set_version(out)
    return out.SerializeToString()


@_decoder("InsertAck", _MAX_SMALL_BYTES)
def decode_insert_ack(data: bytes) -> InsertAckMsg:
    """Validated insert acknowledgement from bytes."""
    m = _parse(pb.InsertAck, data)
    _require(m, ("step",))
    status = _STATUS_FROM_PB.get(m.status)
    if status is None:
        raise ValueError(f"status = {m.status} is invalid: must be one of {INSERT_STATUSES}")
    item_id = m.item_id if m.HasField("item_id") else None
    return InsertAckMsg(m.actor_id, m.episode_id, m.step, status, item_id, m.detail)  # type: ignore[arg-type]


# -------------------------------------------------------------------------------------------------- MCAP
def mcap_schema(message_name: str = "Transition") -> tuple[str, str, bytes]:
    """(schema name, schema encoding "protobuf", serialised FileDescriptorSet) for an MCAP writer.

    romannet.proto imports nothing, so its one FileDescriptorProto is the complete schema.
    """
    if message_name not in pb.DESCRIPTOR.message_types_by_name:
        raise ValueError(f"message_name = {message_name!r} is invalid: must be one of "
                         f"{sorted(pb.DESCRIPTOR.message_types_by_name)}")
    fds = FileDescriptorSet(file=[FileDescriptorProto.FromString(pb.DESCRIPTOR.serialized_pb)])
    return f"{pb.DESCRIPTOR.package}.{message_name}", "protobuf", fds.SerializeToString()
