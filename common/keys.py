"""Every Zenoh key expression of the fleet, in one module.

All keys live under `romannet/@v1/<run_id>/...`. The `@v1` chunk is a verbatim chunk: wildcards (`*`,
`**`) never match it, so a `romannet/**` subscriber of a future protocol version cannot pick up v1 traffic
by accident, and two runs on one Zenoh network never see each other's data because the run id is a chunk
of its own. Identifiers that become key chunks (run id, actor id) are validated here, so a malformed id
fails at start-up with a clear message instead of silently addressing the wrong keys.

| key                                   | kind                  | payload                                  |
|---------------------------------------|-----------------------|------------------------------------------|
| .../replay/insert/<actor_id>          | queryable (get)       | Transition -> InsertAck (reply) or error |
| .../replay/sample                     | queryable (get)       | SampleRequest -> SampleBatch or error    |
| .../replay/priorities                 | subscriber (put)      | PriorityUpdate                           |
| .../replay/stats                      | queryable (get)       | (none) -> JSON object                    |
| .../replay/alive                      | liveliness token      |                                          |
| .../weights/announce                  | publisher (put)       | WeightsAnnouncement                      |
| .../weights/data                      | publisher (put)       | Weights (each version, once)             |
| .../weights/fetch                     | queryable (get)       | (version parameter) -> Weights           |
| .../exploration                       | publisher (put)       | ExplorationRate                          |
| .../actor/<actor_id>/alive            | liveliness token      |                                          |
| .../actor/<actor_id>/live/<topic>     | publisher (put)       | an episode topic's MCAP message bytes    |
| .../learner/alive                     | liveliness token      |                                          |
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .errors import ConfigError

PREFIX = "romannet/@v1"
# One key chunk: no '/', and none of Zenoh's special characters (* $ # ? @ at the start). The same
# alphabet as wire identifiers (common/wire_validate.py) plus nothing else, so any actor id that passes
# the wire schema is also a valid key chunk.
_CHUNK_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def check_chunk(field: str, value: str) -> str:
    """Return value if it can be one Zenoh key chunk; raise ConfigError naming the field otherwise."""
    if not isinstance(value, str) or not _CHUNK_RE.fullmatch(value):
        raise ConfigError(field, value, "must be 1..64 characters from A-Z a-z 0-9 . _ -, starting with a "
                          "letter or digit (it becomes one Zenoh key chunk, so no '/', '*', '$', '#', '?')")
    return value


@dataclass(frozen=True)
class RunKeys:
    """The key expressions of one run. Build with `RunKeys(run_id)`; the run id is validated."""

    run_id: str

    def __post_init__(self) -> None:
        check_chunk("run_id", self.run_id)

    @property
    def root(self) -> str:
        """`romannet/@v1/<run_id>`: everything of this run is below it."""
        return f"{PREFIX}/{self.run_id}"

    # ---------------------------------------------------------------------------------------- replay
    def replay_insert(self, actor_id: str) -> str:
        """Where actor_id sends its transitions: the query payload is an encoded Transition of that actor;
        the reply is an encoded InsertAck, sent only after the transition is durable (an error reply says
        why it was refused). One key per actor, so a router's access control can let each actor insert
        under its own id only; the server refuses a transition whose actor_id is not the key's."""
        return f"{self.root}/replay/insert/{check_chunk('actor_id', actor_id)}"

    @property
    def replay_inserts(self) -> str:
        """Key expression of every actor's insert key (the replay server's queryable)."""
        return f"{self.root}/replay/insert/*"

    @property
    def replay_sample(self) -> str:
        """Queryable: the payload is an encoded SampleRequest; the reply is an encoded SampleBatch."""
        return f"{self.root}/replay/sample"

    @property
    def replay_priorities(self) -> str:
        """Subscriber on the server: encoded PriorityUpdate messages from the learner."""
        return f"{self.root}/replay/priorities"

    @property
    def replay_stats(self) -> str:
        """Queryable: no payload; the reply is a UTF-8 JSON object of buffer and server statistics."""
        return f"{self.root}/replay/stats"

    @property
    def replay_alive(self) -> str:
        """Liveliness token of the replay server."""
        return f"{self.root}/replay/alive"

    # ----------------------------------------------------------------------------- learner -> actors
    @property
    def weights_announce(self) -> str:
        """Publisher (learner): an encoded WeightsAnnouncement for each new weights version."""
        return f"{self.root}/weights/announce"

    @property
    def weights_data(self) -> str:
        """Publisher (learner): the encoded Weights of each new version, put once for every actor (a
        router fans it out), just before its announcement."""
        return f"{self.root}/weights/data"

    @property
    def weights_fetch(self) -> str:
        """Queryable (learner): an encoded Weights message; selector parameter `version=<int>`."""
        return f"{self.root}/weights/fetch"

    @property
    def exploration(self) -> str:
        """Publisher (learner): an encoded ExplorationRate (the LAE rate) for actors."""
        return f"{self.root}/exploration"

    # --------------------------------------------------------------------------------- liveliness
    def actor_alive(self, actor_id: str) -> str:
        """Liveliness token of one actor."""
        return f"{self.root}/actor/{check_chunk('actor_id', actor_id)}/alive"

    @property
    def actors_alive(self) -> str:
        """Key expression matching every actor's liveliness token (for liveliness get / subscriber)."""
        return f"{self.root}/actor/*/alive"

    # ------------------------------------------------------------------------------ live episodes
    def actor_live(self, actor_id: str, topic: str) -> str:
        """Publisher: an episode topic of one actor, live (`romannet mcap play --zenoh` publishes recorded
        episodes there; docs/recording.md). "/camera/color" -> `.../actor/<actor_id>/live/camera/color`;
        the payload is the bytes the topic's MCAP messages hold (Foxglove image protobufs, the Transition,
        the /step JSON)."""
        chunks = [check_chunk("topic", chunk) for chunk in topic.strip("/").split("/")]
        return f"{self.root}/actor/{check_chunk('actor_id', actor_id)}/live/{'/'.join(chunks)}"

    @property
    def actors_live(self) -> str:
        """Key expression matching every actor's live episode topics (for a subscriber)."""
        return f"{self.root}/actor/*/live/**"

    @property
    def learner_alive(self) -> str:
        """Liveliness token of the learner."""
        return f"{self.root}/learner/alive"


def actor_id_from_alive_key(key: str) -> str | None:
    """The actor id in an `.../actor/<actor_id>/alive` key, or None if the key has another shape."""
    parts = str(key).split("/")
    if len(parts) >= 3 and parts[-1] == "alive" and parts[-3] == "actor":
        return parts[-2]
    return None
