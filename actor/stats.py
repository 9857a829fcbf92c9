"""Per-actor statistics and the status.json the launcher's progress display reads.

`runs/<run>/actors/<actor_id>/status.json` is rewritten after every action (and when the actor pauses or
stops), atomically: written to a temporary file and renamed over the old one, so a reader never sees half
a file. Fields (counts are of this process's life unless noted):

    actor_id, run_id, pid, state ("starting" | "running" | "paused" | "stopping" | "stopped"), updated_ns
    actions, episodes (finished, any reason), episode_id, episode_step (actions in the current episode)
    picks, successful_picks, pick_success_rate (null before the first pick)
    completed_episodes (done_reason "done"), completion_rate (of finished episodes)
    efficiency_last, efficiency_mean (ideal / actual actions over completed episodes; ideal:
      common.episode_rules.ideal_actions, the objects counted as the episode's successful picks)
    weights_version (in use), initial_weights (true until the learner's first weights arrive),
    weights_versions_used (distinct versions stamped on transitions), weights_versions_recent (<= 16)
    explore_rate (in use), explore_rate_received (false while cfg.exploration.initial_rate is used)
    spool_items, spool_bytes, spool_recovered (found on start), sent (insert requests, resends included),
    acked (transitions the server acknowledged), accepted, duplicates, rejected, send_failures,
    server_reachable, paced_inserts (inserts the rate limiter held back while the learner lagged),
    paused (bool), pause_kind ("paced": waiting for a lagging learner, routine; "waiting": an insert in flight;
    "outage": the replay server does not answer; "robot": a robot stop), pause_reason, last_done_reason
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from romannet.common.fsutil import write_json_atomic

_RECENT_VERSIONS = 16


@dataclass
class ActorStats:
    """Counters of one actor process; `status()` is the status.json object without the sender's part."""

    actor_id: str
    run_id: str
    actions: int = 0
    episodes: int = 0
    episode_id: str = ""
    episode_step: int = 0
    picks: int = 0
    successful_picks: int = 0
    completed_episodes: int = 0
    efficiencies: list[float] = field(default_factory=list)
    weights_version: int = 0
    initial_weights: bool = True
    versions_used: set[int] = field(default_factory=set)
    recent_versions: list[int] = field(default_factory=list)
    explore_rate: float = 0.0
    explore_rate_received: bool = False
    paused: bool = False
    pause_kind: str = ""  # while paused: "paced" | "waiting" | "outage" (a full spool) or "robot" (a stop)
    pause_reason: str = ""
    last_done_reason: str = ""
    state: str = "starting"
    started_ns: int = field(default_factory=time.time_ns)  # with the pid, names this process in a run's ledger

    def record_action(self, primitive: str, success: bool, policy_version: int) -> None:
        """Count one executed action chosen by weights policy_version."""
        self.actions += 1
        self.episode_step += 1
        if primitive == "pick":
            self.picks += 1
            self.successful_picks += int(success)
        if policy_version not in self.versions_used:
            self.versions_used.add(policy_version)
            self.recent_versions = (self.recent_versions + [policy_version])[-_RECENT_VERSIONS:]

    def record_episode_end(self, done_reason: str, efficiency: float | None) -> None:
        """Count a finished episode; efficiency is given for completed ones (done_reason "done")."""
        self.episodes += 1
        self.last_done_reason = done_reason
        if done_reason == "done":
            self.completed_episodes += 1
            if efficiency is not None:
                self.efficiencies.append(efficiency)

    def status(self) -> dict[str, Any]:
        eff = self.efficiencies
        return {
            "actor_id": self.actor_id, "run_id": self.run_id, "pid": os.getpid(), "state": self.state,
            "started_ns": self.started_ns, "updated_ns": time.time_ns(),
            "actions": self.actions, "episodes": self.episodes, "episode_id": self.episode_id,
            "episode_step": self.episode_step, "picks": self.picks, "successful_picks": self.successful_picks,
            "pick_success_rate": self.successful_picks / self.picks if self.picks else None,
            "completed_episodes": self.completed_episodes,
            "completion_rate": self.completed_episodes / self.episodes if self.episodes else None,
            "efficiency_last": eff[-1] if eff else None,
            "efficiency_mean": sum(eff) / len(eff) if eff else None,
            "weights_version": self.weights_version, "initial_weights": self.initial_weights,
            "weights_versions_used": len(self.versions_used), "weights_versions_recent": self.recent_versions,
            "explore_rate": self.explore_rate, "explore_rate_received": self.explore_rate_received,
            "paused": self.paused, "pause_kind": self.pause_kind, "pause_reason": self.pause_reason,
            "last_done_reason": self.last_done_reason,
        }


def write_status(path: Path, status: dict[str, Any]) -> None:
    """Atomically replace `path` with the JSON object (tmp file + rename; no fsync: it is rewritten often)."""
    write_json_atomic(path, status)


def read_status(path: str | Path) -> dict[str, Any] | None:
    """The status object at path, or None if there is none (yet) or it cannot be read."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
