"""Run the sweep's child processes one at a time, with their output in a log file each, and say how far the
whole sweep is.

Why one at a time: two `romannet up` runs side by side took 1.7x longer in total than one after another on
a 2-core machine. Why signals are forwarded rather than shared: each child leads its own session, so a
Ctrl-C in the terminal reaches only the sweep, which passes exactly one SIGINT on (`romannet up` stops its
fleet cleanly on the first and kills it on the second); a child also gets SIGTERM if the sweep dies
(romannet/supervisor.py's exec shim), so none outlives it.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from romannet.supervisor import shim_command

log = logging.getLogger("romannet.sweep")

TICK_S = 0.5


class StopRequests:
    """Counts SIGINT/SIGTERM/SIGHUP while installed; each one is passed on to the child running then."""

    def __init__(self) -> None:
        self.count = 0
        self._previous = {s: signal.signal(s, self._on) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}

    def _on(self, signum: int, _frame: object) -> None:
        self.count += 1
        log.info("received %s: %s", signal.Signals(signum).name, "stopping what is under way cleanly; the same "
                 "command resumes the sweep" if self.count == 1 else "passing it on (the child hurries)")

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def run_child(argv: Sequence[str], log_path: Path, stops: StopRequests,
              on_tick: Callable[[], None] = lambda: None) -> int:
    """Run argv to its end with stdout and stderr appended to log_path; returns its exit code."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("ab") as out:
        out.write(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(argv)}\n".encode())
        out.flush()
        proc = subprocess.Popen(shim_command(list(argv)), stdin=subprocess.DEVNULL, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True, close_fds=True)
        forwarded = 0
        while True:
            try:
                return proc.wait(TICK_S)
            except subprocess.TimeoutExpired:
                pass
            if stops.count > forwarded:
                proc.send_signal(signal.SIGINT)
                forwarded += 1
            on_tick()


@dataclass(frozen=True)
class Pace:
    """What the ETA is computed from: training actions left and the rate this invocation trained at, the
    evaluations left and how long the finished ones took."""

    actions_left: int
    actions_gained: int
    training_s: float
    evals_left: int
    eval_s: tuple[float, ...] = ()


def eta_s(pace: Pace) -> float | None:
    """Seconds left for the whole sweep, None until there is a training rate to go by (or when evaluations
    are left and none has been timed yet)."""
    rest = 0.0
    if pace.actions_left > 0:
        if pace.actions_gained <= 0 or pace.training_s <= 0:
            return None
        rest += pace.actions_left * pace.training_s / pace.actions_gained
    if pace.evals_left > 0:
        if not pace.eval_s:
            return None
        rest += pace.evals_left * sum(pace.eval_s) / len(pace.eval_s)
    return rest


def format_duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    minutes = int(round(seconds / 60))
    return f"{minutes // 60}h{minutes % 60:02d}m" if minutes >= 60 else f"{minutes}m" if minutes else "<1m"


def training_eta(pace: Pace) -> tuple[float | None, list[str]]:
    """The sweep's ETA while a run trains: seconds for the whole sweep, or the training's with a note (a
    progress field) while no evaluation has been timed yet."""
    eta = eta_s(pace)
    if eta is not None or pace.actions_gained <= 0:
        return eta, []
    return _training_only(pace), ["+ evaluations"]


def eval_eta(elapsed_s: float, pace: Pace) -> float | None:
    """The sweep's ETA while an evaluation runs (elapsed_s of it so far)."""
    eta = eta_s(pace)
    return None if eta is None else max(0.0, eta - elapsed_s)


def _training_only(pace: Pace) -> float | None:
    return eta_s(Pace(pace.actions_left, pace.actions_gained, pace.training_s, 0))
