"""How large a message each process of the fleet accepts from Zenoh, checked before the bytes are held.

Zenoh reassembles a fragmented message in full before any callback sees it (its own cap is 1 GiB), so a
process's bound on what it receives has to be in its Zenoh config: `transport/link/rx/max_message_size`.
Zenoh drops a larger message as it arrives, having held at most that many bytes of it: the sender's
query gets no reply and the link stays up (tests/test_replay_fuzz.py).

The shipped configs (the embedded default, deploy/zenoh-local.json5, deploy/zenoh/, `romannet deploy`)
set FLEET_MAX_MESSAGE_BYTES, the most any role legitimately receives; the router forwards up to it. Each
service then lowers its own session's limit to what its role can receive (`limit_messages`): a replay
server about one transition, a learner one sample batch. A file's lower value is kept, with a warning
when it is below what the role needs.
"""

from __future__ import annotations

import json
import logging

import zenoh

log = logging.getLogger(__name__)

MIB = 1 << 20
# The most any role receives: weights (RoManNet's three nets are ~23 MB in fp32) and sample batches
# (learner.batch_size items) fit with room to spare; 1 GiB, Zenoh's own default, does not bound memory.
FLEET_MAX_MESSAGE_BYTES = 256 * MIB
# Zenoh's read buffer per link (its default, stated so the configs show every bound in one place).
RX_BUFFER_BYTES = 65535
# Besides a transition's own bytes: protobuf framing, ids, the query's key and parameters.
HEADROOM_BYTES = 1 * MIB
# The replay server also receives priority updates (common/wire.py accepts up to 4 MiB of them).
PRIORITY_UPDATE_BYTES = 4 * MIB
RX_KEY = "transport/link/rx/max_message_size"
# What the shipped configs add under transport/link/rx.
RX_LIMITS = {"buffer_size": RX_BUFFER_BYTES, "max_message_size": FLEET_MAX_MESSAGE_BYTES}


def replay_receive_limit(max_item_bytes: int) -> int:
    """The largest message a replay server needs: one transition of replay.max_item_bytes, or a priority
    update, plus headroom."""
    return max(int(max_item_bytes), PRIORITY_UPDATE_BYTES) + HEADROOM_BYTES


def learner_receive_limit(batch_size: int, max_item_bytes: int) -> int:
    """The largest message a learner needs: a sample batch of batch_size items of at most max_item_bytes
    (in practice far smaller), never above the fleet's cap."""
    return min(int(batch_size) * int(max_item_bytes) + HEADROOM_BYTES, FLEET_MAX_MESSAGE_BYTES)


def message_limit(config: zenoh.Config) -> int:
    """The config's transport/link/rx/max_message_size in bytes."""
    return int(json.loads(config.get_json(RX_KEY)))


def limit_messages(config: zenoh.Config, need: int, who: str) -> int:
    """Lower config's receive limit to `need` bytes (what `who` may legitimately receive) and return the
    limit in force. A lower limit already in the config is kept, with one warning: messages between the
    two would be dropped."""
    current = message_limit(config)
    if current < need:
        log.warning("the Zenoh config limits messages to %d bytes (%s), below the %d bytes this %s may need: "
                    "larger messages will be dropped unanswered; raise it in the config file", current, RX_KEY,
                    need, who)
        return current
    config.insert_json5(RX_KEY, json.dumps(int(need)))
    return int(need)
