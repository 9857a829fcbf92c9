"""ReplayClient over Zenoh: what actors and the learner use to talk to `romannet replay`.

Usage (the session is the caller's; close it with the `with`):

    with open_session(make_config(connect=["tcp/127.0.0.1:7447"], listen=[])) as session:
        client = ZenohReplayClient(session, run_id="run-1")
        client.wait_until_ready(timeout_s=10)
        ack = client.insert(transition)          # returns once the server has it on disk
        batch = client.sample(8, timeout_s=5)    # TimeoutError while the rate limiter holds
        raw = client.sample_encoded(8, timeout_s=5)  # the same, as the server's SampleBatch bytes

Every request has a timeout; a server that is not running gives NoReplyError (a TimeoutError) after at
most timeout_s, never a hang. Inserts are idempotent on (actor_id, episode_id, step), so an actor that
got no acknowledgement simply sends the same transition again and gets status "duplicate".
"""

from __future__ import annotations

import json
import logging
import uuid

import zenoh

from . import romannet_pb2 as pb
from . import wire
from .errors import DecodeError
from .keys import RunKeys
from .wire_messages import InsertAckMsg, PriorityUpdateMsg, SampleBatchMsg, SampleRequestMsg, TransitionMsg
from .zenoh_session import RemoteError, query_one, wait_for_liveliness

log = logging.getLogger(__name__)

# The error tokens with which the replay server refuses an insert for good: the bytes themselves are bad
# (replay/rejections.py classifies decode errors into these) or the store cannot hold them. Resending the same
# bytes cannot cure them. Every other error (rate_limited, shutting_down, overloaded, internal, a token this
# client does not know, Zenoh's own errors) is transient: the transition is kept and sent again, because a
# transition dropped on a transient error is acknowledged data lost.
INSERT_REFUSALS = frozenset({"oversized", "schema_version", "undecodable", "missing_field", "non_finite",
                             "wrong_shape", "bad_image", "invalid", "wrong_actor", "store_refused"})


def refused_for_good(reason: str) -> bool:
    """True when an insert refused with this error token must not be resent (see INSERT_REFUSALS)."""
    return reason in INSERT_REFUSALS


# The server answers a request that its rate limiter holds back a little before the client's deadline,
# so the client hears "rate_limited" rather than silence. Seconds.
_REPLY_MARGIN_S = 0.25
# The insert key chunk for bytes that name no valid actor id (never a real actor: ids come from configs).
_UNIDENTIFIED = "0-unidentified"


def _wait_ms(timeout_s: float) -> int:
    """The rate-limiter wait to ask the server for, in ms: the timeout less a margin for the reply."""
    return int(max(0.0, timeout_s - min(_REPLY_MARGIN_S, timeout_s / 4)) * 1000)


def _request_id_of(reply: bytes) -> str:
    """The request_id of an encoded SampleBatch (a parse without decoding any PNG: well under 1 ms)."""
    batch = pb.SampleBatch()
    try:
        batch.ParseFromString(reply)
    except Exception as exc:
        raise DecodeError(f"invalid SampleBatch: not a protobuf SampleBatch message ({exc})") from exc
    return batch.request_id


class RateLimitedError(RemoteError, TimeoutError):
    """The server's rate limiter held the request back for the whole wait: a sample (too few items, or the
    learner samples faster than samples_per_insert allows) or an insert (the learner lags). Retry later."""


class ZenohReplayClient:
    """ReplayClient (common/interfaces.py) backed by a replay server reached through `session`.

    run_id selects the server (`romannet/@v1/<run_id>/replay/...`); expected_shape (h, w) in pixels, if
    given, is enforced on every sampled transition. actor_id: the actor this client inserts for (its
    transitions go to `.../replay/insert/<actor_id>`, the only insert key a secure router lets that actor
    use); None reads it from each transition. max_insert_bytes: the server's replay.max_item_bytes; a larger
    transition is refused here ("oversized"), not sent: beyond the server's Zenoh cap it would be dropped
    unanswered and resent for ever.
    """

    def __init__(self, session: zenoh.Session, run_id: str, expected_shape: tuple[int, int] | None = None,
                 actor_id: str | None = None, max_insert_bytes: int | None = None):
        self._session = session
        self._max_insert_bytes = max_insert_bytes
        self.keys = RunKeys(run_id)
        self._expected_shape = expected_shape
        self._insert_key = self.keys.replay_insert(actor_id) if actor_id is not None else None

    def wait_until_ready(self, timeout_s: float = 10.0) -> bool:
        """True once the server's liveliness token is visible (it serves from then on), else False."""
        return wait_for_liveliness(self._session, self.keys.replay_alive, timeout_s)

    def insert(self, transition: TransitionMsg, timeout_s: float = 10.0) -> InsertAckMsg:
        """Insert; returns the acknowledgement once the transition is durable on the server.

        Raises NoReplyError (TimeoutError) when the server did not answer in timeout_s seconds (the
        transition may or may not be stored: send it again), RemoteError when it refused the bytes.
        A transition the store itself refuses comes back as an ack with status "rejected".
        """
        return self.insert_encoded(wire.encode_transition(transition), timeout_s)

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> InsertAckMsg:
        """insert() for a transition already encoded with wire.encode_transition (actors that also
        record MCAP encode once and reuse the bytes)."""
        key = self._insert_key or self._insert_key_of(data)
        if self._max_insert_bytes is not None and len(data) > self._max_insert_bytes:
            raise RemoteError(key, "oversized", f"transition is {len(data)} bytes; the replay server accepts at "
                              f"most {self._max_insert_bytes} (replay.max_item_bytes): not sent")
        try:
            reply = query_one(self._session, key, data, timeout_s,
                              parameters=f"wait_ms={_wait_ms(timeout_s)}")
        except RemoteError as err:
            if err.reason == "rate_limited":
                raise RateLimitedError(err.key, err.reason, err.detail) from None
            raise
        return wire.decode_insert_ack(reply)

    def _insert_key_of(self, data: bytes) -> str:
        """The insert key of an encoded transition's actor (a protobuf parse, no PNG decoding). Bytes that
        name no valid actor go to a key no actor may use, and the server answers why they are refused."""
        try:
            return self.keys.replay_insert(pb.Transition.FromString(data).actor_id)
        except Exception:  # not a Transition, or an actor id that is no key chunk: the server judges it
            return self.keys.replay_insert(_UNIDENTIFIED)

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> SampleBatchMsg:
        """A prioritized batch of batch_size transitions (decoded and validated).

        Raises RateLimitedError (a TimeoutError) when the rate limiter held the request for the whole
        timeout, NoReplyError (a TimeoutError) when the server did not answer.
        """
        return wire.decode_sample_batch(self.sample_encoded(batch_size, timeout_s), self._expected_shape)

    def sample_encoded(self, batch_size: int, timeout_s: float = 10.0) -> bytes:
        """sample() without the decoding: the server's SampleBatch reply as it came (protobuf bytes), for
        callers that decode it their own way (e.g. item by item). The reply is checked to answer this
        request (its request_id); nothing else is validated, so decode it with wire.decode_sample_batch or
        an equally strict decoder. Raises as sample() does, and DecodeError for a reply that is not a
        SampleBatch.
        """
        request = SampleRequestMsg(uuid.uuid4().hex, batch_size)
        try:
            reply = query_one(self._session, self.keys.replay_sample, wire.encode_sample_request(request),
                              timeout_s, parameters=f"wait_ms={_wait_ms(timeout_s)}")
        except RemoteError as err:
            if err.reason == "rate_limited":
                raise RateLimitedError(err.key, err.reason, err.detail) from None
            raise
        answered = _request_id_of(reply)
        if answered != request.request_id:  # a reply meant for another request: a server bug
            raise RemoteError(self.keys.replay_sample, "mismatch",
                              f"reply is for request {answered}, not {request.request_id}")
        return reply

    def update_priorities(self, update: PriorityUpdateMsg) -> None:
        """Publish new priorities by item id (fire and forget; ids of evicted items are ignored)."""
        self._session.put(self.keys.replay_priorities, wire.encode_priority_update(update),
                          congestion_control=zenoh.CongestionControl.BLOCK)

    def stats(self, timeout_s: float = 10.0) -> dict:
        """The server's statistics: buffer size and bytes, rates, rejected counts by reason, ..."""
        reply = query_one(self._session, self.keys.replay_stats, None, timeout_s)
        return json.loads(reply.decode("utf-8"))
