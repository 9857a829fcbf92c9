"""Sampling for the learner: a batch with one corrupt transition loses that item, not the whole batch.

The replay server checks PNG headers on insert, not every pixel (that would cost ~10 ms per insert), so a
transition whose pixel data is damaged can sit in the buffer. `wire.decode_sample_batch` refuses a whole
batch for one such item; and since new items carry the highest priority it would be drawn again and again,
stalling training. `TolerantReplayClient.sample` decodes item by item instead, returns the good ones and
lists the bad ones in `last_corrupt` (the learner counts them and sets their priority to 0, so the buffer
stops offering them).
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


def decode_batch_tolerant(data: bytes, expected_shape: tuple[int, int] | None = None
                          ) -> tuple[SampleBatchMsg, list[CorruptItem]]:
    """(batch of the items that decode and validate, the corrupt items). All kept items share one shape
    (expected_shape if given, else the first good item's). Raises DecodeError only if the batch itself
    (framing, schema version, header fields) is bad."""
    m = pb.SampleBatch()
    try:
        m.ParseFromString(data)
    except pb_message.DecodeError as exc:
        raise DecodeError(f"invalid SampleBatch: not a protobuf SampleBatch message ({exc})") from exc
    if not m.HasField("schema_version") or m.schema_version.major != wire.SCHEMA_MAJOR:
        raise DecodeError(f"invalid SampleBatch: schema_version is missing or not major {wire.SCHEMA_MAJOR}")
    if not m.HasField("buffer_size") or len(m.items) > MAX_BATCH_ITEMS:
        raise DecodeError(f"invalid SampleBatch: buffer_size missing or more than {MAX_BATCH_ITEMS} items")
    items: list[SampleItem] = []
    corrupt: list[CorruptItem] = []
    shape = expected_shape
    for it in m.items:
        item_id = it.item_id if it.HasField("item_id") else None
        try:
            transition = wire.decode_transition(it.transition.SerializeToString(), shape)
            items.append(SampleItem(it.item_id, it.probability, it.is_weight, transition))
        except (DecodeError, ValueError) as err:  # ValueError: SampleItem's own field checks
            corrupt.append(CorruptItem(item_id, str(err)[:300]))
            continue
        shape = shape or transition.shape
    try:
        return SampleBatchMsg(m.request_id, tuple(items), m.buffer_size), corrupt
    except ValueError as err:
        raise DecodeError(f"invalid SampleBatch: {err}") from err


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
