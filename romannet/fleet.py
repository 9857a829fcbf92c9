"""The fleet's live numbers for `up`'s progress line and summary, read from what the components write.

Sources (the launcher never imports component code, it reads their outputs):
- actors: `<run>/actors/<actor_id>/status.json` (written atomically by each actor): actions, episodes,
  picks, successful_picks, weights_version, explore_rate, spool_items, acked, paused, efficiency_last, ...
- learner: the last row of `<run>/metrics.csv` (update, explore_rate, weights_version, replay_size).
- replay: the server's stats query (size, inserts), asked by the launcher through a function it is given.

Kept apart from romannet.progress (the display, shared by every long command): this is what `up` and the
sweep know about a run; fleet_fields turns a FleetSnapshot into the display's fields.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from romannet.common.fsutil import write_json_atomic


def read_actor_statuses(run_dir: Path) -> dict[str, dict[str, Any]]:
    """{actor_id: status} for every readable `actors/*/status.json` (a missing or torn file is skipped)."""
    out: dict[str, dict[str, Any]] = {}
    for path in sorted((run_dir / "actors").glob("*/status.json")):
        try:
            status = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(status, dict):
            out[path.parent.name] = status
    return out


def read_last_metrics(csv_path: Path, tail_bytes: int = 16384) -> dict[str, str] | None:
    """The last complete row of the learner's metrics.csv as {column: text}, or None if it has no rows.

    Reads the header and only the file's tail: the CSV grows by one row per update."""
    try:
        with csv_path.open("rb") as fh:
            header = fh.readline().decode("utf-8", "replace")
            fh.seek(0, io.SEEK_END)
            end = fh.tell()
            fh.seek(max(len(header), end - tail_bytes))
            tail = fh.read().decode("utf-8", "replace")
    except OSError:
        return None
    pieces = tail.split("\n")
    if not tail.endswith("\n"):
        pieces = pieces[:-1]  # the row being written right now
    lines = [ln for ln in pieces if ln.strip()]
    if not header.strip() or not lines:
        return None
    names = next(csv.reader([header]))
    values = next(csv.reader([lines[-1]]))
    if len(values) != len(names) or values == names:
        return None
    return dict(zip(names, values, strict=True))


def _num(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if out == out else None  # NaN -> None


# status.json counters that cover one actor process's life; the ledger adds up those of earlier processes.
_COUNTERS = ("actions", "episodes", "picks", "successful_picks", "completed_episodes", "sent", "acked",
             "accepted", "duplicates", "rejected")


def process_identity(status: dict[str, Any]) -> tuple[Any, Any]:
    """Which process wrote a status: (pid, started_ns). A pid alone comes back after a reboot; status files
    from before started_ns existed give (pid, None)."""
    return status.get("pid"), status.get("started_ns")


class ActorLedger:
    """Totals per actor id across the processes of a run: restarts within one launch and earlier launches.

    An actor's status.json counts the life of one process; when the supervisor restarts a crashed actor,
    `retire(actor_id, status)` banks the dead process's last counts, and `merged()` adds them to whatever
    the new process reports. A status still written by a retired process counts as nothing new (the new
    process has not written its own yet). With a `path` (`<run>/actors/ledger.json`) every retire is saved
    atomically, so `romannet up --resume` starts from the run's totals: `load()` reads the file and the
    launcher retires the statuses the last launch's actors left. `mark_start()` remembers the totals when
    a launch starts (`this_start()` is what its own processes did).
    """

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        self.carried: dict[str, dict[str, int]] = {}
        self._retired: set[tuple[Any, Any]] = set()
        self._at_start: dict[str, int] = {}

    @classmethod
    def load(cls, path: Path) -> ActorLedger:
        """The ledger saved at path (an empty one if there is none yet); RomannetError if it is unreadable."""
        from romannet.common.errors import RomannetError

        ledger = cls(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return ledger
        except (OSError, ValueError) as exc:
            raise RomannetError(f"{path} cannot be read ({exc}): it holds the run's action counts from earlier "
                                "launches; move it away to count them from zero") from None
        try:
            ledger.carried = {str(aid): {k: int(bank.get(k, 0)) for k in _COUNTERS}
                              for aid, bank in data["carried"].items()}
            ledger._retired = {(pid, started) for pid, started in data["retired"]}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise RomannetError(f"{path} is not a ledger ({type(exc).__name__}: {exc}): move it away to count "
                                "the run's earlier actions from zero") from None
        return ledger

    def save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.path, {"carried": self.carried, "retired": sorted(self._retired, key=repr)})

    def retire(self, actor_id: str, status: dict[str, Any] | None) -> None:
        if not status or process_identity(status) in self._retired:
            return
        bank = self.carried.setdefault(actor_id, dict.fromkeys(_COUNTERS, 0))
        for key in _COUNTERS:
            bank[key] += int(_num(status.get(key)) or 0)
        if isinstance(status.get("pid"), int):
            self._retired.add(process_identity(status))
        self.save()

    def merged(self, actor_id: str, status: dict[str, Any]) -> dict[str, Any]:
        bank = self.carried.get(actor_id)
        if bank is None:
            return status
        out = dict(status)
        stale = process_identity(status) in self._retired
        for key in _COUNTERS:
            out[key] = bank[key] + (0 if stale else int(_num(status.get(key)) or 0))
        return out

    def actions(self, actor_id: str) -> int:
        return self.carried.get(actor_id, {}).get("actions", 0)

    def mark_start(self) -> None:
        self._at_start = {aid: bank.get("actions", 0) for aid, bank in self.carried.items()}

    def this_start(self, actor_id: str) -> int:
        """Actions of actor_id's retired processes since mark_start (its share's part already done)."""
        return self.actions(actor_id) - self._at_start.get(actor_id, 0)

    def start_total(self) -> int:
        return sum(self._at_start.values())


class MovingRate:
    """Success rate over (about) the last `window` attempts, from cumulative (attempts, successes) totals."""

    def __init__(self, window: int = 50):
        self.window = window
        self._samples: deque[tuple[int, int]] = deque(maxlen=1000)

    def add(self, attempts: int, successes: int) -> None:
        if self._samples and attempts < self._samples[-1][0]:
            self._samples.clear()  # totals went back (an actor restarted from scratch): start over
        self._samples.append((attempts, successes))

    def value(self) -> float | None:
        if not self._samples:
            return None
        attempts, successes = self._samples[-1]
        base = (0, 0)
        for sample in self._samples:  # the newest sample at least `window` attempts back, else the start
            if attempts - sample[0] >= self.window:
                base = sample
        n = attempts - base[0]
        return (successes - base[1]) / n if n > 0 else None


@dataclass
class FleetSnapshot:
    """What the progress line shows; also the launcher's final summary."""

    elapsed_s: float = 0.0
    actions: int = 0
    episodes: int = 0  # finished, for any reason
    completed_episodes: int = 0  # finished with the task done (the paper's completion)
    picks: int = 0
    successful_picks: int = 0
    moving_pick_success: float | None = None
    efficiency: float | None = None
    updates: int | None = None
    learner_explore_rate: float | None = None
    replay_size: int | None = None
    replay_inserts: int | None = None
    acked: int = 0
    spooled: int = 0
    actors: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items()}


class EpisodeEfficiency:
    """Mean action efficiency over the fleet's last `window` completed episodes.

    Actors report their last completed episode's efficiency and how many they completed; each time an
    actor's count grows, its efficiency_last joins the window (an episode completed between two polls
    of the same actor is missed, which a display can live with)."""

    def __init__(self, window: int = 20):
        self._values: deque[float] = deque(maxlen=window)
        self._seen: dict[str, int] = {}

    def update(self, actor_id: str, status: dict[str, Any]) -> None:
        completed = int(_num(status.get("completed_episodes")) or 0)
        last = _num(status.get("efficiency_last"))
        if completed > self._seen.get(actor_id, 0) and last is not None:
            self._values.append(last)
        self._seen[actor_id] = completed

    def value(self) -> float | None:
        return sum(self._values) / len(self._values) if self._values else None


class FleetProgress:
    """Collects a FleetSnapshot from the run directory and the replay stats function."""

    def __init__(self, run_dir: Path, replay_stats: Callable[[], dict[str, Any] | None] | None = None,
                 pick_window: int = 50, ledger: ActorLedger | None = None):
        self.run_dir = run_dir
        self.ledger = ledger or ActorLedger()
        self._replay_stats = replay_stats
        self._picks = MovingRate(pick_window)
        self._efficiency = EpisodeEfficiency()
        self._started = time.monotonic()

    def snapshot(self) -> FleetSnapshot:
        snap = FleetSnapshot(elapsed_s=time.monotonic() - self._started)
        snap.actors = {aid: self.ledger.merged(aid, s) for aid, s in read_actor_statuses(self.run_dir).items()}
        for aid, status in snap.actors.items():
            snap.actions += int(_num(status.get("actions")) or 0)
            snap.episodes += int(_num(status.get("episodes")) or 0)
            snap.completed_episodes += int(_num(status.get("completed_episodes")) or 0)
            snap.picks += int(_num(status.get("picks")) or 0)
            snap.successful_picks += int(_num(status.get("successful_picks")) or 0)
            snap.acked += int(_num(status.get("acked")) or 0)
            snap.spooled += int(_num(status.get("spool_items")) or 0)
            self._efficiency.update(aid, status)
        self._picks.add(snap.picks, snap.successful_picks)
        snap.moving_pick_success = self._picks.value()
        snap.efficiency = self._efficiency.value()
        row = read_last_metrics(self.run_dir / "metrics.csv")
        if row is not None:
            updates = _num(row.get("update"))
            snap.updates = int(updates) if updates is not None else None
            snap.learner_explore_rate = _num(row.get("explore_rate"))
        if self._replay_stats is not None:
            stats = self._replay_stats()
            if stats:
                snap.replay_size = int(stats.get("size", 0))
                snap.replay_inserts = int(stats.get("inserts", 0))
        return snap


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f}%"


def _pause_mark(status: dict) -> str:
    """" paced" / " waiting" for an actor waiting for the learner or an acknowledgement (routine), " PAUSED"
    for one stopped by an outage or a robot stop (news)."""
    if not status.get("paused"):
        return ""
    kind = status.get("pause_kind")
    return f" {kind}" if kind in ("paced", "waiting") else " PAUSED"


def fleet_fields(snap: FleetSnapshot) -> list[str]:
    """The fleet's progress fields, most important first (a narrow terminal shows the first few): actors
    stopped by an outage, pick success, learner updates, episodes, efficiency, LAE, replay, spool, and
    each actor's weights version."""
    paused = [aid for aid, s in sorted(snap.actors.items()) if _pause_mark(s) == " PAUSED"]
    lae = "-" if snap.learner_explore_rate is None else f"{snap.learner_explore_rate:.2f}"
    per_actor = " ".join(f"{aid}:v{s.get('weights_version', '-')}" + _pause_mark(s)
                         for aid, s in sorted(snap.actors.items()))
    fields = [f"PAUSED {' '.join(paused)}"] if paused else []
    return fields + [
        f"pick {_pct(snap.moving_pick_success)}",
        f"updates {'-' if snap.updates is None else snap.updates}",
        f"episodes {snap.episodes} ({snap.completed_episodes} done)",
        f"eff {_pct(snap.efficiency)}",
        f"LAE {lae}",
        f"replay {'-' if snap.replay_size is None else snap.replay_size}",
        f"spool {snap.spooled}",
        f"weights {per_actor or '-'}",
    ]
