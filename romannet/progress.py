"""Progress: the one display of `up`, `eval`, `sweep` and the mcap tools, and the fleet's live numbers.

Sources (the launcher never imports component code, it reads their outputs):
- actors: `<run>/actors/<actor_id>/status.json` (written atomically by each actor): actions, episodes,
  picks, successful_picks, weights_version, explore_rate, spool_items, acked, paused, efficiency_last, ...
- learner: the last row of `<run>/metrics.csv` (update, explore_rate, weights_version, replay_size).
- replay: the server's stats query (size, inserts), asked by the launcher through a function it is given.

Progress (below) shows any long work with its rate and ETA: on a terminal one line redrawn in place (tqdm
draws the bar), cut to the terminal's width by dropping the least important fields; otherwise (a log file,
CI, the sweep's logs) one plain line every `log_every_s` seconds with every field, so logs stay readable.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from tqdm import tqdm
from tqdm.utils import disp_len, disp_trim

from romannet.common.fsutil import write_json_atomic

log = logging.getLogger(__name__)


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


# ---------------------------------------------------------------------------------------------------------
# The one progress display of `up`, `eval`, `sweep` and the mcap tools.
#
# The numbers (rate, ETA) are computed here, not by tqdm's own smoothing, so that the line on a terminal and
# the line in a log file say the same, and so a caller with a better estimate (the sweep's ETA covers the
# evaluations still to come) can give its own. tqdm draws the bar and fits the line to the terminal.

FIELD_SEP = " | "
MIN_BAR = 8  # columns: below this a bar says nothing the percentage does not
MAX_BAR = 30
_CLEAR_LINE = "\r\033[K"


def format_duration(seconds: float | None) -> str:
    """`45s`, `12m05s`, `2h01m`; `-` when unknown."""
    if seconds is None or seconds != seconds or seconds < 0:
        return "-"
    s = int(round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    m = int(round(seconds / 60))
    return f"{m // 60}h{m % 60:02d}m"


def format_rate(per_s: float | None, unit: str) -> str:
    """`12.3 actions/s`, `3 runs/min` or `2 runs/h` (whichever keeps the number at 1 or more); `-` when
    unknown."""
    unit = f" {unit}" if unit else ""
    if per_s is None or per_s != per_s:
        return f"-{unit}/s"
    for scale, per in ((1.0, "s"), (60.0, "min"), (3600.0, "h")):
        value = per_s * scale
        if value >= 1 or per == "h":
            return f"{value:.3g}{unit}/{per}" if value < 1000 else f"{value:.0f}{unit}/{per}"
    raise AssertionError("unreachable")


def fit_fields(fields: Sequence[str], room: int, sep: str = FIELD_SEP) -> str:
    """The leading fields that fit in `room` columns, joined by sep (each with sep in front); a field that
    does not fit ends the list, so the most important (first) ones are the ones shown."""
    out = ""
    for f in fields:
        piece = sep + f
        if disp_len(out + piece) > room:
            break
        out += piece
    return out


@dataclass(frozen=True)
class Reading:
    """What one progress line says. done/total place the bar (total None: no bar, no ETA); count is what the
    rate counts when it is not `done` (the mcap tools place the bar by bytes and count transitions)."""

    label: str
    done: float
    total: float | None = None
    unit: str = ""
    rate: float | None = None  # per second, of count (or of done)
    eta: float | None = None  # seconds
    fields: tuple[str, ...] = ()
    counts_done: bool = True  # False: done/total is a fraction of the work, shown as a percentage only
    short_label: str | None = None  # on a terminal, where columns are few

    def position(self) -> str:
        """`1050/2500 actions`, `1050 actions` without a total, `42%` for a fraction of the work."""
        if not self.counts_done:
            return f"{100 * _fraction(self.done, self.total):.0f}%"
        unit = f" {self.unit}" if self.unit else ""
        return f"{_count(self.done)}/{_count(self.total)}{unit}" if self.total else f"{_count(self.done)}{unit}"


def _count(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"


def _fraction(done: float, total: float | None) -> float:
    return min(max(done / total, 0.0), 1.0) if total else 0.0


def plain_line(r: Reading) -> str:
    """The line logged once per interval when the output is not a terminal (and into log files):
    `up: actions 1050/2500 (42%) | 1.23 actions/s | ETA 19m38s | pick 45% | ...`, every field."""
    if r.counts_done:
        unit = f"{r.unit} " if r.unit else ""
        where = f"{unit}{_count(r.done)}" + (f"/{_count(r.total)} ({100 * _fraction(r.done, r.total):.0f}%)"
                                             if r.total else "")
    else:
        where = r.position()
    parts = [f"{r.label}: {where}", format_rate(r.rate, r.unit)]
    if r.total or r.eta is not None:
        parts.append(f"ETA {format_duration(r.eta)}")
    return FIELD_SEP.join([*parts, *r.fields])


def terminal_line(r: Reading, columns: int, ascii_only: bool = False) -> str:
    """The line redrawn in place on a terminal, at most columns - 1 wide (writing the last column makes some
    terminals wrap): `up  42%|####      | 1050/2500 actions, 1.23/s, ETA 19m38s | pick 45% | ...`, with
    as many fields as fit after a bar of at least MIN_BAR columns."""
    width = max(columns - 1, 20)
    label = r.short_label or r.label
    rate = format_rate(r.rate, "" if r.counts_done else r.unit)
    stats = f"{r.position()}, {rate}" if r.counts_done else f"{rate}"
    if r.total or r.eta is not None:
        stats += f", ETA {format_duration(r.eta)}"
    if not r.total:
        head = f"{label} {stats}"
        return disp_trim(head + fit_fields(r.fields, width - disp_len(head)), width)
    fixed = f"{label} 100%|| {stats}"
    if disp_len(fixed) + MIN_BAR > width:  # no room for a bar worth the name: the percentage says it
        head = f"{label} {100 * _fraction(r.done, r.total):.0f}% {stats}"
        return disp_trim(head + fit_fields(r.fields, width - disp_len(head)), width)
    shown = fit_fields(r.fields, width - disp_len(fixed) - MIN_BAR)
    tail = f" {stats}{shown}".replace("{", "{{").replace("}", "}}")
    ncols = min(width, disp_len(fixed) + disp_len(shown) + MAX_BAR)
    return tqdm.format_meter(_fraction(r.done, r.total), 1, 0, ncols=ncols, prefix=label, ascii=ascii_only,
                             bar_format="{desc} {percentage:3.0f}%|{bar}|" + tail)


class RateWindow:
    """Units per second over (about) the last `window_s` seconds, from cumulative totals; a total that goes
    back (an actor restarted from zero) starts it over."""

    def __init__(self, window_s: float = 120.0, min_span_s: float = 1.0):
        self.window_s, self.min_span_s = window_s, min_span_s
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, t: float, value: float) -> None:
        if self._samples and value < self._samples[-1][1]:
            self._samples.clear()
        if len(self._samples) >= 2 and t - self._samples[-2][0] < 0.5:
            self._samples[-1] = (t, value)  # many updates a second: keep one sample per half second
        else:
            self._samples.append((t, value))
        while len(self._samples) > 2 and t - self._samples[1][0] >= self.window_s:
            self._samples.popleft()

    def rate(self) -> float | None:
        if len(self._samples) < 2:
            return None
        (t0, v0), (t1, v1) = self._samples[0], self._samples[-1]
        return (v1 - v0) / (t1 - t0) if t1 - t0 >= self.min_span_s else None


def eta_s(done: float, total: float | None, rate: float | None) -> float | None:
    """Seconds to total at rate; 0 when there; None when unknown (no total or no rate yet)."""
    if not total:
        return None
    if done >= total:
        return 0.0
    return (total - done) / rate if rate else None


def terminal_columns(stream: TextIO) -> int:
    """The terminal's width: $COLUMNS when set (as shutil.get_terminal_size reads it), else the stream's
    terminal, else 80."""
    try:
        env = int(os.environ.get("COLUMNS", ""))
        if env > 0:
            return env
    except ValueError:
        pass
    try:
        cols = os.get_terminal_size(stream.fileno()).columns
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        cols = 0
    return cols if cols > 0 else 80


class Progress:
    """One progress display: redrawn in place on a terminal (at most every `redraw_s`), and logged as a plain
    line every `log_every_s` either way (on a terminal only into the log files: ClearLineFilter keeps those
    records off the console it redraws). As a context manager it puts that filter on the console handlers.

        with Progress("eval", total=30, unit="runs") as bar:
            bar.update(done, ["4 completed", "last h4 seed 100003: done"])
    """

    def __init__(self, label: str, total: float | None = None, unit: str = "", *, stream: TextIO | None = None,
                 log_every_s: float = 30.0, tty: bool | None = None, redraw_s: float = 0.5,
                 window_s: float = 120.0, counts_done: bool = True, short_label: str | None = None,
                 initial: float | None = None):
        self.label, self.total, self.unit, self.counts_done = label, total, unit, counts_done
        self.short_label = short_label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = _isatty(self.stream) if tty is None else tty
        self.log_every_s, self.redraw_s = log_every_s, redraw_s
        self._ascii = not (getattr(self.stream, "encoding", "") or "").lower().replace("-", "").startswith("utf")
        self._window_s = window_s
        self._done_rate, self._count_rate = RateWindow(window_s), RateWindow(window_s)
        if initial is not None:  # where the work starts, so the first update already gives a rate
            self._done_rate.add(time.monotonic(), initial)
            self._count_rate.add(time.monotonic(), initial)
        self._next_log = 0.0  # the first update is logged at once: a log shows the work has begun
        self._next_draw = 0.0
        self._drawn = False
        self._filter: ClearLineFilter | None = None
        self._handlers: list[logging.Handler] = []
        self.last: Reading | None = None

    def reading(self, done: float, fields: Sequence[str] = (), *, count: float | None = None,
                eta: float | None = None, now: float | None = None) -> Reading:
        """Record done (and count) at now; the Reading a line is drawn from."""
        now = time.monotonic() if now is None else now
        self._done_rate.add(now, done)
        if count is not None:
            self._count_rate.add(now, count)
        rate = self._count_rate.rate() if count is not None else self._done_rate.rate()
        if eta is None:
            eta = eta_s(done, self.total, self._done_rate.rate())
        return Reading(self.label, done, self.total, self.unit, rate, eta, tuple(fields), self.counts_done,
                       self.short_label)

    def restart(self, label: str, total: float | None = None, unit: str = "", short_label: str | None = None) -> None:
        """Go on with other work (the sweep's next run): a new label, total and unit, the rate measured afresh."""
        self.label, self.total, self.unit, self.short_label = label, total, unit, short_label
        self._done_rate, self._count_rate = RateWindow(self._window_s), RateWindow(self._window_s)

    def update(self, done: float, fields: Sequence[str] = (), *, count: float | None = None,
               eta: float | None = None, force: bool = False) -> None:
        """Show progress: done of total (count: what the rate counts, if not done); fields most important
        first; eta in seconds when the caller knows better than done/rate (the sweep's covers what follows)."""
        now = time.monotonic()
        self.last = self.reading(done, fields, count=count, eta=eta, now=now)
        if self.tty and (force or now >= self._next_draw):
            self.stream.write(_CLEAR_LINE + terminal_line(self.last, terminal_columns(self.stream), self._ascii))
            self.stream.flush()
            self._drawn = True
            self._next_draw = now + self.redraw_s
        if force or now >= self._next_log:
            log.info("%s", plain_line(self.last), extra={"progress_line": True})
            self._next_log = now + self.log_every_s

    def clear(self) -> None:
        """Erase the in-place line (before a log message, and at the end)."""
        if self.tty and self._drawn:
            self.stream.write(_CLEAR_LINE)
            self.stream.flush()
            self._drawn = False

    def __enter__(self) -> Progress:
        self._filter = ClearLineFilter(self)
        self._handlers = console_handlers()
        for h in self._handlers:
            h.addFilter(self._filter)
        return self

    def __exit__(self, *exc: object) -> None:
        self.clear()
        for h in self._handlers:
            h.removeFilter(self._filter)
        self._handlers = []


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def console_handlers() -> list[logging.Handler]:
    """The root logger's handlers that write to a console (not to a file)."""
    return [h for h in logging.getLogger().handlers
            if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)]


class ClearLineFilter(logging.Filter):
    """For console handlers: a log message never lands in the middle of the progress line, and on a TTY
    the periodic progress records stay off the console (the line itself is there)."""

    def __init__(self, display: Progress):
        super().__init__()
        self._display = display

    def filter(self, record: logging.LogRecord) -> bool:
        if self._display.tty and getattr(record, "progress_line", False):
            return False
        self._display.clear()
        return True
