"""Sampling for the learner: a batch with one corrupt transition loses that item, not the whole batch.

The replay server checks each record against its checksum as it reads it and quarantines a damaged one,
but bytes can still be bad in ways no checksum sees (a transition stored damaged before records had
checksums, a PNG whose pixels do not decode). Protobuf parses embedded messages eagerly, so parsing the
SampleBatch as a whole fails for one such item, and since new items carry the highest priority it would
be drawn again and again, stalling training. `decode_batch_tolerant` therefore splits the batch along its
wire framing (tags and lengths, field numbers from romannet.proto) without parsing the transitions, then
decodes each transition on its own: it returns the good items and lists the bad ones (the learner counts
them and sets their priority to 0, so the buffer stops offering them).
"""

from __future__ import annotations

from typing import NamedTuple

from google.protobuf import message as pb_message

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.wire_messages import MAX_BATCH_ITEMS, SampleBatchMsg, SampleItem


class CorruptItem(NamedTuple):
    """A sampled item that did not decode: its id (None if even that was unreadable) and why."""

    item_id: int | None
    reason: str


_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5  # protobuf wire types
_BATCH_ITEMS = 3  # SampleBatch.items
_ITEM_TRANSITION = 4  # SampleItem.transition


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(data) or shift > 63:
            raise DecodeError("invalid SampleBatch: a varint runs past its message")
        byte = data[pos]
        value |= (byte & 0x7F) << shift
        pos += 1
        if not byte & 0x80:
            return value, pos
        shift += 7


def split_fields(data: bytes, field_number: int) -> tuple[bytes, list[bytes]]:
    """(the message's bytes without `field_number`, the payloads of that length-delimited field), read
    from the wire framing only; DecodeError if the framing itself is broken."""
    rest, found, pos = bytearray(), [], 0
    while pos < len(data):
        start = pos
        key, pos = _varint(data, pos)
        wire_type = key & 7
        if wire_type == _VARINT:
            _, pos = _varint(data, pos)
        elif wire_type == _I64:
            pos += 8
        elif wire_type == _I32:
            pos += 4
        elif wire_type == _LEN:
            length, pos = _varint(data, pos)
            if key >> 3 == field_number:
                found.append(data[pos:pos + length])
            pos += length
        else:
            raise DecodeError(f"invalid SampleBatch: wire type {wire_type} at byte {start}")
        if pos > len(data):
            raise DecodeError(f"invalid SampleBatch: a field at byte {start} runs past its message")
        if key >> 3 != field_number or wire_type != _LEN:
            rest += data[start:pos]
    return bytes(rest), found


def _decode_item(body: bytes, shape: tuple[int, int] | None) -> tuple[int | None, SampleItem]:
    """(item id or None, the decoded item) of one SampleItem's bytes; DecodeError/ValueError if bad."""
    scalars, transitions = split_fields(body, _ITEM_TRANSITION)
    head = pb.SampleItem()
    try:
        head.ParseFromString(scalars)
    except pb_message.DecodeError as exc:
        raise DecodeError(f"invalid SampleItem ({exc})") from exc
    item_id = head.item_id if head.HasField("item_id") else None
    if len(transitions) != 1:
        raise DecodeError(f"item {item_id}: {len(transitions)} transitions in one SampleItem")
    try:
        transition = wire.decode_transition(transitions[0], shape)
        return item_id, SampleItem(head.item_id, head.probability, head.is_weight, transition)
    except (DecodeError, ValueError) as err:
        raise DecodeError(f"{err}"[:300]) from err


def decode_batch_tolerant(data: bytes, expected_shape: tuple[int, int] | None = None
                          ) -> tuple[SampleBatchMsg, list[CorruptItem]]:
    """(batch of the items that decode and validate, the corrupt items). All kept items share one shape
    (expected_shape if given, else the first good item's). Raises DecodeError only if the batch itself
    (framing, schema version, header fields) is bad."""
    head_bytes, bodies = split_fields(bytes(data), _BATCH_ITEMS)
    m = pb.SampleBatch()
    try:
        m.ParseFromString(head_bytes)
    except pb_message.DecodeError as exc:
        raise DecodeError(f"invalid SampleBatch: not a protobuf SampleBatch message ({exc})") from exc
    if not m.HasField("schema_version") or m.schema_version.major != wire.SCHEMA_MAJOR:
        raise DecodeError(f"invalid SampleBatch: schema_version is missing or not major {wire.SCHEMA_MAJOR}")
    if not m.HasField("buffer_size") or len(bodies) > MAX_BATCH_ITEMS:
        raise DecodeError(f"invalid SampleBatch: buffer_size missing or more than {MAX_BATCH_ITEMS} items")
    items: list[SampleItem] = []
    corrupt: list[CorruptItem] = []
    shape = expected_shape
    for body in bodies:
        try:
            _, item = _decode_item(body, shape)
        except (DecodeError, ValueError) as err:  # ValueError: SampleItem's own field checks
            corrupt.append(CorruptItem(_item_id(body), str(err)[:300]))
            continue
        items.append(item)
        shape = shape or item.transition.shape  # type: ignore[union-attr]
    try:
        return SampleBatchMsg(m.request_id, tuple(items), m.buffer_size), corrupt
    except ValueError as err:
        raise DecodeError(f"invalid SampleBatch: {err}") from err


def _item_id(body: bytes) -> int | None:
    """The item id of a SampleItem's bytes, if even that much is readable."""
    try:
        scalars, _ = split_fields(body, _ITEM_TRANSITION)
        head = pb.SampleItem()
        head.ParseFromString(scalars)
        return head.item_id if head.HasField("item_id") else None
    except (DecodeError, pb_message.DecodeError):
        return None


class TolerantReplayClient(ZenohReplayClient):
    """ZenohReplayClient whose sample() skips corrupt items; see the module docstring.

    last_corrupt: the corrupt items of the latest sample() call (empty when all decoded).
    """

    last_corrupt: tuple[CorruptItem, ...] = ()

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> SampleBatchMsg:
        """A prioritized batch of the items that decode (possibly fewer than batch_size, or none).

        Raises RateLimitedError / NoReplyError (TimeoutErrors) as ZenohReplayClient.sample does.
        """
        batch, corrupt = decode_batch_tolerant(self.sample_encoded(batch_size, timeout_s), self._expected_shape)
        self.last_corrupt = tuple(corrupt)
        return batch
