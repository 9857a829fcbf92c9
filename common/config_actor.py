"""Configuration of an actor: identity, the on-disk spool, episode recording, limits and timeouts.

One frozen dataclass, validated on construction: a bad value raises ConfigError naming the field, the value
and the fix. The root Config holds it as the `actor` section; `romannet actor --actor-id ID` overrides
actor_id (one config file serves a whole fleet).

Paths left empty are derived from the run directory (`romannet actor --run-dir runs/<run>`):
spool `runs/<run>/actors/<actor_id>/spool`, MCAP episodes `runs/<run>/episodes/<actor_id>/`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from .configbase import require

_MIB = 1 << 20
# The actor id becomes a Zenoh key chunk and a wire identifier (common/keys.py, common/wire_validate.py).
_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


@dataclass(frozen=True)
class ActorConfig:
    """One actor process (`romannet actor`): sim or robot loop, spool, sender and MCAP recorder."""

    actor_id: str = "actor-0"
    # Limits of one run of the process; 0 = no limit (run until SIGTERM/SIGINT).
    episodes: int = 0
    max_actions: int = 0
    # The first N episodes of this actor (by episode index, so a resumed run does not repeat them) are acted by
    # the simulator's scripted oracle instead of the policy: planner demonstrations in replay (SDQfD, BulletArm),
    # counted in max_actions. Simulation only.
    demo_episodes: int = 0
    # Spool: every transition is written (fsync'ed) here before it is sent, and removed once acknowledged.
    spool_dir: str = ""  # "" = <run-dir>/actors/<actor_id>/spool
    # The actor pauses (stops acting) while the spool holds this many ... (2: it waits for the replay's paced
    # acks, replay.samples_per_insert; an actor that must act through a replay outage wants thousands)
    spool_max_items: int = 2
    spool_max_bytes: int = 1024 * _MIB  # ... or this many bytes of encoded transitions
    spool_fsync: bool = True  # False only for throw-away runs and tests
    # Sender: a background thread drains the spool to the replay server.
    insert_timeout_s: float = 10.0  # deadline of one insert request
    resend_backoff_initial_s: float = 0.5  # first pause after a failed insert; doubles up to ...
    resend_backoff_max_s: float = 10.0  # ... this
    shutdown_flush_s: float = 5.0  # on SIGTERM: time spent sending what is left (the rest stays on disk)
    # Initial replay priority: "buffer" lets the server choose (its max priority, as in Schaul et al.);
    # "reward" inserts with |reward| + initial_priority_epsilon (successful actions are sampled first).
    initial_priority: Literal["buffer", "reward"] = "buffer"
    initial_priority_epsilon: float = 0.01
    # Weights and exploration rate from the learner.
    weights_fetch_timeout_s: float = 10.0
    # Episode recording (MCAP, one file per episode).
    record_mcap: bool = True
    mcap_dir: str = ""  # "" = <run-dir>/episodes/<actor_id>
    mcap_chunk_bytes: int = 1 * _MIB  # a crash loses at most the chunk being written
    mcap_compression: Literal["zstd", "lz4", "none"] = "zstd"
    record_camera: bool = True  # the raw camera frames (640x480) besides the heightmaps
    camera_color_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: int = 90

    def __post_init__(self) -> None:
        require(isinstance(self.actor_id, str) and bool(_ID_RE.fullmatch(self.actor_id)), "actor.actor_id",
                self.actor_id, "must be 1..64 characters from A-Z a-z 0-9 . _ -, starting with a letter or "
                "digit (it becomes a Zenoh key chunk and a file name)")
        require(self.episodes >= 0, "actor.episodes", self.episodes, "must be >= 0 (0 = no limit)")
        require(self.max_actions >= 0, "actor.max_actions", self.max_actions, "must be >= 0 (0 = no limit)")
        require(0 <= self.demo_episodes <= 1_000_000, "actor.demo_episodes", self.demo_episodes,
                "must be 0..1000000 episodes (0 = none)")
        require(1 <= self.spool_max_items <= 10_000_000, "actor.spool_max_items", self.spool_max_items,
                "must be 1..10000000 transitions")
        require(_MIB <= self.spool_max_bytes, "actor.spool_max_bytes", self.spool_max_bytes,
                f"must be at least {_MIB} bytes (1 MiB; one 224x224 transition is ~0.1-0.3 MB)")
        for name in ("insert_timeout_s", "resend_backoff_initial_s", "weights_fetch_timeout_s"):
            value = getattr(self, name)
            require(math.isfinite(value) and 0.0 < value <= 3600.0, f"actor.{name}", value,
                    "must be in (0, 3600] seconds")
        require(math.isfinite(self.resend_backoff_max_s)
                and self.resend_backoff_initial_s <= self.resend_backoff_max_s <= 3600.0,
                "actor.resend_backoff_max_s", self.resend_backoff_max_s,
                "must be in [resend_backoff_initial_s, 3600] seconds")
        require(math.isfinite(self.shutdown_flush_s) and 0.0 <= self.shutdown_flush_s <= 3600.0,
                "actor.shutdown_flush_s", self.shutdown_flush_s, "must be in [0, 3600] seconds")
        require(math.isfinite(self.initial_priority_epsilon) and 0.0 < self.initial_priority_epsilon <= 10.0,
                "actor.initial_priority_epsilon", self.initial_priority_epsilon, "must be in (0, 10]")
        require(64 * 1024 <= self.mcap_chunk_bytes <= 256 * _MIB, "actor.mcap_chunk_bytes",
                self.mcap_chunk_bytes, "must be 64 KiB..256 MiB (smaller chunks lose less in a crash)")
        require(1 <= self.jpeg_quality <= 100, "actor.jpeg_quality", self.jpeg_quality, "must be 1..100")

    def priority_for(self, reward: float) -> float | None:
        """The initial replay priority of a transition with this reward (None: the buffer's choice)."""
        if self.initial_priority == "buffer":
            return None
        return abs(float(reward)) + self.initial_priority_epsilon
