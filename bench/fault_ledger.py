"""Counting for the fault scenario: transitions sent by the actors, acknowledged to them, stored by the replay.

    ledger = Ledger(run_dir, ("actor-0", "actor-1"))
    ledger.killed("actor-0", status, spool_keys(run_dir, "actor-0"), next_episode(run_dir, "actor-0"))
    ledger.final("actor-0", status)          # for each actor once every process has stopped cleanly
    counts = ledger.reconcile(config_path)    # sent, acknowledged, stored, duplicates, lost, ...

* sent: transitions the actors produced (each is spooled, fsync'ed, before it is sent). A process that
  stopped cleanly reports its count in status.json. A SIGKILLed process cannot: its status.json is written
  after each spooled transition, so it may miss the one spooled in the instant before the kill. Its count
  is therefore taken from the transitions themselves: those of its episodes that the replay server stored,
  plus any left in its spool at the kill, and it must lie between its last status count and one more.
* acknowledged: sent minus what is left in the actors' spools after the final stop (the spool removes an
  item only when the server acknowledged it; an empty spool means everything was acknowledged).
* stored: distinct (actor, episode, step) keys in the replay server's durable log, read back with
  ReplayStore; duplicates: log items beyond the distinct keys.
* refused: transitions the server refused and the actor set aside (spool/rejected/): each is a problem.
* lost: sent transitions not stored, including gaps inside an episode (steps are numbered 0, 1, ... per
  episode, so a missing middle step shows even where counts could hide it).
"""

from __future__ import annotations

import json
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

Key = tuple[str, str, int]


def actor_status(run_dir: Path, actor_id: str) -> dict[str, Any]:
    """The actor's status.json, or {} while it does not exist or is being replaced."""
    try:
        return json.loads((run_dir / "actors" / actor_id / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def spool_keys(run_dir: Path, actor_id: str) -> set[Key]:
    """Keys of the transitions waiting in an actor's spool (files on disk; no process needed)."""
    from romannet.actor.sender import item_key

    keys = set()
    for path in sorted((run_dir / "actors" / actor_id / "spool").glob("*.pb")):
        key = item_key(path.read_bytes())
        if key is not None:
            keys.add(key)
    return keys


def rejected_reasons(run_dir: Path, actor_id: str) -> list[str]:
    """The reasons noted beside the transitions the replay server refused and the actor set aside
    (spool/rejected/*.json, actor/spool.py): nothing the fault scenario sends should ever land there."""
    reasons = []
    for note in sorted((run_dir / "actors" / actor_id / "spool" / "rejected").glob("*.json")):
        try:
            reasons.append(str(json.loads(note.read_text()).get("reason", "?")))
        except (OSError, ValueError):
            reasons.append(f"unreadable note {note.name}")
    return reasons


def next_episode(run_dir: Path, actor_id: str) -> int:
    """The episode index the actor's next process will start with (its state.json, written before an
    episode starts): every episode of the processes so far has a lower index."""
    return int(json.loads((run_dir / "actors" / actor_id / "state.json").read_text())["next_episode"])


def logged_keys(config_path: Path, replay_dir: Path) -> list[Key]:
    """The (actor, episode, step) key of every item in a stopped replay server's durable log, in log order
    (a key twice is a duplicate)."""
    from romannet.common.config import load_config
    from romannet.replay.store import ReplayStore

    with ReplayStore(load_config(config_path).replay, replay_dir) as store:
        return [tuple(meta.key) for _, _, meta in store.recovered.items]  # type: ignore[misc]


def _episode_index(episode_id: str) -> int:
    match = re.fullmatch(r"ep(\d+)", episode_id or "")
    return int(match.group(1)) if match else -1


@dataclass
class _Process:
    status: dict[str, Any]
    killed: bool
    spool_at_kill: set[Key] = field(default_factory=set)
    next_episode: int = 0  # killed processes: every episode of theirs has a lower index


class Ledger:
    """Per actor, its processes in order (a SIGKILLed one, then its restart, ...); see the module docstring."""

    def __init__(self, run_dir: Path, actor_ids: tuple[str, ...]):
        self.run_dir = run_dir
        self.actor_ids = actor_ids
        self._procs: dict[str, list[_Process]] = {a: [] for a in actor_ids}

    def killed(self, actor_id: str, status: dict[str, Any], spooled: set[Key], next_episode: int) -> None:
        """A process of actor_id was SIGKILLed: its last status file, the keys left in its spool and the
        next episode index in its state.json (read right after the kill, before any restart)."""
        self._procs[actor_id].append(_Process(dict(status), killed=True, spool_at_kill=set(spooled),
                                              next_episode=next_episode))

    def final(self, actor_id: str, status: dict[str, Any]) -> None:
        self._procs[actor_id].append(_Process(dict(status), killed=False))

    def reconcile(self, config_path: Path) -> dict[str, Any]:
        logged = logged_keys(config_path, self.run_dir / "replay")
        stored = set(logged)
        problems: list[str] = []
        per_actor: dict[str, dict[str, Any]] = {}
        totals = Counter()
        for actor_id in self.actor_ids:
            mine = {k for k in stored if k[0] == actor_id}
            episodes: dict[str, set[int]] = defaultdict(set)
            for _, episode, step in mine:
                episodes[episode].add(step)
            gaps = {ep: sorted(set(range(max(steps) + 1)) - steps) for ep, steps in episodes.items()}
            gaps = {ep: g for ep, g in gaps.items() if g}
            if gaps:
                problems.append(f"{actor_id}: steps missing inside episodes {gaps}")
            sent, first_episode = 0, 0
            for proc in self._procs[actor_id]:
                status = proc.status
                if proc.killed:
                    own = {k for k in mine if first_episode <= _episode_index(k[1]) < proc.next_episode}
                    count = len(own | proc.spool_at_kill)
                    reported = int(status.get("actions", 0))
                    if not reported <= count <= reported + 1:
                        problems.append(f"{actor_id}: killed process reported {reported} actions but "
                                        f"{count} of its transitions are stored or spooled")
                    missing = proc.spool_at_kill - stored
                    if missing:
                        problems.append(f"{actor_id}: {len(missing)} transition(s) spooled at the kill never "
                                        "stored")
                    sent += count
                    first_episode = proc.next_episode
                else:
                    sent += int(status.get("actions", 0))
                    if status.get("state") != "stopped":
                        problems.append(f"{actor_id}: last process ended in state {status.get('state')!r}")
            refused = rejected_reasons(self.run_dir, actor_id)
            if refused:
                problems.append(f"{actor_id}: {len(refused)} transition(s) refused by the replay server and set "
                                f"aside in its spool's rejected/ (first: {refused[0][:200]})")
            left = len(spool_keys(self.run_dir, actor_id))
            lost = sent - len(mine) + sum(len(g) for g in gaps.values())
            if len(mine) > sent:
                problems.append(f"{actor_id}: {len(mine)} stored but only {sent} sent")
            per_actor[actor_id] = {"sent": sent, "acknowledged": sent - left, "stored": len(mine),
                                   "left_in_spool": left, "refused": len(refused), "episodes": len(episodes),
                                   "processes": len(self._procs[actor_id])}
            totals.update(sent=sent, acknowledged=sent - left, left_in_spool=left, lost=max(0, lost))
        duplicates = len(logged) - len(stored)
        extra = len({k for k in stored if k[0] not in self.actor_ids})
        if extra:
            problems.append(f"{extra} stored transition(s) of unknown actors")
        return {"sent": totals["sent"], "acknowledged": totals["acknowledged"], "stored": len(stored),
                "duplicates": duplicates, "lost": totals["lost"], "left_in_spools": totals["left_in_spool"],
                "per_actor": per_actor,
                "counts_agree": not problems and duplicates == 0 and
                totals["sent"] == totals["acknowledged"] == len(stored),
                "problems": problems}
