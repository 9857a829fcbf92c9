"""A progress bar for long `romannet mcap` work, in the style of the fleet's progress line.

On a terminal the bar is redrawn in place (at most 10 times a second) and log messages never land in
the middle of it; elsewhere (a log file, CI) it is logged every `log_every_s` seconds.
"""

from __future__ import annotations

import logging
import time
from typing import TextIO

from romannet.progress import ClearLineFilter, ProgressDisplay

_WIDTH = 24
_REDRAW_S = 0.1


def bar_text(label: str, fraction: float, detail: str) -> str:
    """`label  42% |##########..............| detail`."""
    fraction = min(max(fraction, 0.0), 1.0)
    filled = round(fraction * _WIDTH)
    return f"{label} {100 * fraction:3.0f}% |{'#' * filled}{'.' * (_WIDTH - filled)}| {detail}"


class ProgressBar:
    """Context manager: `with ProgressBar("feed") as bar: bar.update(fraction, "12 files ...")`."""

    def __init__(self, label: str, stream: TextIO | None = None, log_every_s: float = 10.0):
        self.label = label
        self.display = ProgressDisplay(stream, log_every_s=log_every_s)
        self._filter = ClearLineFilter(self.display)
        self._handlers: list[logging.Handler] = []
        self._next_draw = 0.0
        self._last = ""

    def __enter__(self) -> ProgressBar:
        self._handlers = [h for h in logging.getLogger().handlers if isinstance(h, logging.StreamHandler)
                          and not isinstance(h, logging.FileHandler)]
        for h in self._handlers:
            h.addFilter(self._filter)
        return self

    def update(self, fraction: float, detail: str, force: bool = False) -> None:
        now = time.monotonic()
        self._last = bar_text(self.label, fraction, detail)
        if force or now >= self._next_draw:
            self.display.show(self._last)
            self._next_draw = now + _REDRAW_S

    def __exit__(self, *exc: object) -> None:
        self.display.clear()
        for h in self._handlers:
            h.removeFilter(self._filter)
