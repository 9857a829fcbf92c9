"""When the learner may take its next update: enough data in the replay, and the replay-ratio cap.

The cap (LearnerConfig.max_updates_per_insert) bounds updates per newly inserted transition, so a learner
faster than its actors waits for new experience rather than overfitting a small buffer. The count starts
when this process first reads the replay's stats: the transitions already in the buffer then count as new
(a fresh run starts with exactly those; after a resume they may be trained a little more than the cap
says, which is the safe side of waiting forever for a counter the server may have reset).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from romannet.common.interfaces import ReplayClient
from romannet.common.zenoh_session import ZenohQueryError

log = logging.getLogger(__name__)


@dataclass
class GateState:
    """What the gate last read from the replay server (counts are transitions)."""

    size: int = 0
    inserts: int = 0
    ok: bool = False  # a stats reply has arrived at least once


class ReplayGate:
    """Reads replay stats at most every stats_every_s seconds and answers `ready(updates)`.

    min_size: transitions in the buffer before the first update; max_updates_per_insert: 0 = no cap.
    """

    def __init__(self, client: ReplayClient, min_size: int, max_updates_per_insert: float,
                 stats_every_s: float = 1.0, stats_timeout_s: float = 2.0):
        self._client = client
        self.min_size = int(min_size)
        self.max_updates_per_insert = float(max_updates_per_insert)
        self.stats_every_s = float(stats_every_s)
        self.stats_timeout_s = float(stats_timeout_s)
        self.state = GateState()
        self._next_read_s = 0.0
        self._base: tuple[int, int] | None = None  # (inserts, size) at the first read
        self._base_updates = 0
        self.waiting_reason = ""

    def refresh(self, force: bool = False) -> GateState:
        """Read the stats if due (or forced); a missing server leaves the last state and logs."""
        now = time.monotonic()
        if not force and now < self._next_read_s:
            return self.state
        self._next_read_s = now + self.stats_every_s
        try:
            stats = self._client.stats(timeout_s=self.stats_timeout_s)
            self.state = GateState(size=int(stats["size"]), inserts=int(stats["inserts"]), ok=True)
        except (TimeoutError, ZenohQueryError) as err:  # the server is down, not up yet, or overloaded
            log.debug("replay stats: %s", err)
        except (KeyError, TypeError, ValueError) as err:  # a server of another version: say so, go on
            log.warning("replay stats without usable size/inserts: %s", err)
        return self.state

    def start(self, updates: int) -> None:
        """Begin counting the ratio at the current update count (call once, before the loop)."""
        self._base_updates = int(updates)
        self._base = None

    def allowed_updates(self) -> float:
        """Updates this process may have made so far under the cap (inf without a cap or base)."""
        if self.max_updates_per_insert <= 0 or self._base is None:
            return float("inf")
        base_inserts, base_size = self._base
        new_transitions = max(0, self.state.inserts - base_inserts) + base_size
        return self.max_updates_per_insert * new_transitions

    def ready(self, updates: int) -> bool:
        """True if an update may start now; otherwise `waiting_reason` says why."""
        state = self.refresh()
        if not state.ok:
            self.waiting_reason = "waiting for the replay server's stats"
            return False
        if self._base is None:
            self._base = (state.inserts, state.size)
        if state.size < self.min_size:
            self.waiting_reason = f"replay holds {state.size} of the {self.min_size} transitions needed"
            return False
        done = updates - self._base_updates
        if done >= self.allowed_updates():
            # New inserts lift the cap; the caller waits a little and asks again (stats are re-read then).
            self.waiting_reason = (f"replay ratio cap: {done} updates since start for "
                                   f"{self.allowed_updates() / self.max_updates_per_insert:.0f} new "
                                   f"transitions, at most {self.max_updates_per_insert:g} per transition")
            return False
        self.waiting_reason = ""
        return True
