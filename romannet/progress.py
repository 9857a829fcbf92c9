"""Progress: the one display of `up`, `eval`, `sweep` and the mcap tools.

Progress (below) shows any long work with its rate and ETA: on a terminal one line redrawn in place (tqdm
draws the bar), cut to the terminal's width by dropping the least important fields; otherwise (a log file,
CI, the sweep's logs) one plain line every `log_every_s` seconds with every field, so logs stay readable.
The fleet's live numbers that `up` shows through it are romannet.fleet's.
"""

from __future__ import annotations

import io
import logging
import os
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TextIO

from tqdm import tqdm
from tqdm.utils import disp_len, disp_trim

log = logging.getLogger(__name__)


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
