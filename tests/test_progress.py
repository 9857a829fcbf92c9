"""The one progress display (romannet/progress.py): its pure pieces, and what a user sees from a real
`romannet eval` on a terminal of 80 or 100 columns and in a log (stderr not a terminal)."""

from __future__ import annotations

import fcntl
import io
import logging
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from romannet.fleet import FleetSnapshot, fleet_fields
from romannet.progress import (
    Progress,
    RateWindow,
    Reading,
    eta_s,
    fit_fields,
    format_duration,
    format_rate,
    plain_line,
    terminal_line,
)

ROMANNET = str(Path(sys.executable).parent / "romannet")


def busy_fleet() -> FleetSnapshot:
    """A fleet whose full line is far wider than any terminal (the old one was 147-151 characters)."""
    actors = {f"actor-{i}": {"weights_version": 1210 + i, "paused": i == 2, "pause_kind": "outage"}
              for i in range(4)}
    return FleetSnapshot(elapsed_s=3600, actions=1050, episodes=310, completed_episodes=120, picks=900,
                         successful_picks=400, moving_pick_success=0.45, efficiency=0.61, updates=1218,
                         learner_explore_rate=0.31, replay_size=104000, spooled=3, actors=actors)


def test_durations_and_rates_read_at_a_glance() -> None:
    assert [format_duration(s) for s in (None, -1, 0, 44.6, 60, 725, 3599, 3600, 7260)] == \
        ["-", "-", "0s", "45s", "1m00s", "12m05s", "59m59s", "1h00m", "2h01m"]
    assert format_rate(None, "runs") == "- runs/s"
    assert format_rate(12.34, "actions") == "12.3 actions/s"
    assert format_rate(0.05, "runs") == "3 runs/min"  # one run every 20 s
    assert format_rate(1 / 1800, "runs") == "2 runs/h"
    assert format_rate(0.0, "runs") == "0 runs/h"
    assert format_rate(2500.0, "") == "2500/s"


def test_fields_are_kept_in_order_of_importance_until_the_room_is_used() -> None:
    fields = ["pick 45%", "updates 1218", "episodes 310 (120 done)"]
    assert fit_fields(fields, 100) == " | pick 45% | updates 1218 | episodes 310 (120 done)"
    assert fit_fields(fields, 26) == " | pick 45% | updates 1218"
    assert fit_fields(fields, 25) == " | pick 45%"  # a field that does not fit ends the list
    assert fit_fields(fields, 5) == ""


def test_eta_and_rate_window() -> None:
    assert eta_s(1000, 2500, 2.0) == 750.0
    assert eta_s(2500, 2500, None) == 0.0 and eta_s(10, None, 2.0) is None and eta_s(10, 100, None) is None
    window = RateWindow(window_s=60, min_span_s=2)
    window.add(0.0, 0)
    window.add(1.0, 10)
    assert window.rate() is None  # one second says little
    for t in range(2, 200):
        window.add(float(t), 10 * t if t < 100 else 1000 + (t - 100))
    assert window.rate() == pytest.approx(1.0)  # only the last minute counts: 1/s since t = 100
    window.add(200.0, 5)  # an actor restarted from zero: the totals went back
    assert window.rate() is None


@pytest.mark.parametrize("columns", [40, 60, 80, 100, 132, 300])
def test_the_terminal_line_fits_the_terminal_with_rate_and_eta(columns: int) -> None:
    fields = tuple(fleet_fields(busy_fleet()))
    r = Reading("up", 1050, 2500, "actions", rate=1.234, eta=1180.0, fields=fields)
    line = terminal_line(r, columns)
    assert len(line) <= columns - 1, line
    if columns >= 80:
        assert line.startswith("up  42%|") and "1050/2500 actions, 1.23/s, ETA 19m40s" in line
        assert "PAUSED actor-2" in line  # an actor stopped by an outage is news: the first field
    if columns >= 300:  # a wide terminal shows everything
        assert line.endswith("weights actor-0:v1210 actor-1:v1211 actor-2:v1212 PAUSED actor-3:v1213")


def test_the_terminal_line_without_a_total_and_for_a_fraction_of_the_work() -> None:
    assert terminal_line(Reading("up", 1050, None, "actions", 1.2, None, ("pick 45%",)), 80) == \
        "up 1050 actions, 1.2/s | pick 45%"
    line = terminal_line(Reading("feed", 0.42, 1.0, "transitions", 310.0, 95.0, ("file 3/12",),
                                 counts_done=False), 80, ascii_only=True)
    assert re.fullmatch(r"feed  42%\|[#0-9 ]+\| 310 transitions/s, ETA 1m35s \| file 3/12", line), line
    assert len(line) <= 79


def test_the_plain_line_keeps_every_field() -> None:
    snap = busy_fleet()
    line = plain_line(Reading("up", snap.actions, 2500, "actions", 1.234, 1180.0, tuple(fleet_fields(snap))))
    assert line.startswith("up: actions 1050/2500 (42%) | 1.23 actions/s | ETA 19m40s | PAUSED actor-2 | pick 45%")
    assert line.endswith("weights actor-0:v1210 actor-1:v1211 actor-2:v1212 PAUSED actor-3:v1213")
    sweep = Reading("sweep: run 12 of 18 clutter-demos-s0", 1364, 2500, "actions", 0.41, 7260.0,
                    ("+ evaluations",), short_label="run 12/18 clutter-demos-s0")
    assert plain_line(sweep) == ("sweep: run 12 of 18 clutter-demos-s0: actions 1364/2500 (55%) | 24.6 actions/min | "
                                 "ETA 2h01m | + evaluations")
    assert terminal_line(sweep, 80) == "run 12/18 clutter-demos-s0 55% 1364/2500 actions, 24.6/min, ETA 2h01m"


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_redraws_on_a_terminal_and_logs_the_plain_line_per_interval(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    caplog.set_level(logging.INFO, "romannet.progress")
    screen = FakeTerminal()
    bar = Progress("eval", total=30, unit="runs", stream=screen, redraw_s=0, log_every_s=3600, initial=0)
    for done in range(1, 4):
        bar.update(done, ["2 completed", "last h4 seed 100002: done in 7 actions " + "x" * 80])
    drawn = [d for d in screen.getvalue().split("\r\033[K") if d]
    assert len(drawn) == 3 and all(len(d) <= 79 for d in drawn), drawn
    assert "3/30 runs" in drawn[-1] and "ETA" in drawn[-1]
    assert [r.getMessage()[:22] for r in caplog.records] == ["eval: runs 1/30 (3%) |"]  # then once an hour
    bar.update(4, ["2 completed"], force=True)
    assert [r.getMessage()[:22] for r in caplog.records][1:] == ["eval: runs 4/30 (13%) "]

    pipe = io.StringIO()  # not a terminal: nothing drawn, one log line per interval
    caplog.clear()
    quiet = Progress("eval", total=30, unit="runs", stream=pipe, log_every_s=0.05)
    for done in range(1, 6):
        quiet.update(done)
        time.sleep(0.03)
    assert pipe.getvalue() == ""
    assert 2 <= len(caplog.records) <= 4


# --- as a user meets it: `romannet eval` (random policy, two-action runs: seconds) -------------------------

EVAL = ["eval", "--policy", "random", "--task", "stacking", "--goal-height", "2", "--runs", "4", "--max-steps",
        "2", "--workers", "1", "--out"]


def _run_on_terminal(args: list[str], columns: int, env_columns: bool) -> str:
    """Run romannet with stderr on a pseudo-terminal of `columns` columns; what the terminal received."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    if env_columns:
        env["COLUMNS"] = str(columns)
    proc = subprocess.Popen(["nice", "-n", "19", ROMANNET, *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=slave, env=env)
    os.close(slave)
    received = b""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.5)
        if ready:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the child closed its end
                break
            if not chunk:
                break
            received += chunk
        elif proc.poll() is not None:
            break
    os.close(master)
    proc.communicate(timeout=30)
    assert proc.returncode == 0, received.decode(errors="replace")
    return received.decode("utf-8", errors="replace")


@pytest.mark.timeout(240)
@pytest.mark.parametrize(("columns", "env_columns"), [(80, True), (100, False)])
def test_eval_progress_on_a_terminal_fits_its_width(tmp_path: Path, columns: int, env_columns: bool) -> None:
    screen = _run_on_terminal([*EVAL, str(tmp_path / "out")], columns, env_columns)
    drawn = [d.split("\r\n")[0] for d in screen.split("\r\x1b[K")[1:] if d.strip()]
    bars = [d for d in drawn if d.startswith("eval ")]
    assert bars, screen
    assert all(len(b) <= columns - 1 for b in bars), bars
    assert any(re.search(r"\d/4 runs, [\d.]+/(s|min), ETA \S+", b) for b in bars), bars


@pytest.mark.timeout(240)
def test_eval_progress_in_a_log_is_a_plain_line(tmp_path: Path) -> None:
    proc = subprocess.run(["nice", "-n", "19", ROMANNET, *EVAL, str(tmp_path / "out")], capture_output=True,
                          text=True, timeout=200)
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "\x1b" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "romannet.progress" in ln]
    assert len(lines) == 2, proc.stderr  # the first run and the last; between them one per 30 s
    assert "eval: runs 1/4 (25%) | " in lines[0]
    assert re.search(r"eval: runs 4/4 \(100%\) \| [\d.]+ runs/(s|min) \| ETA 0s \| \d completed \| last h2 seed",
                     lines[1]), lines[1]


def test_the_mcap_bar_places_by_fraction_and_counts_what_the_tool_handles(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    from romannet.mcaptools.bar import ProgressBar

    monkeypatch.setenv("COLUMNS", "80")
    caplog.set_level(logging.INFO, "romannet.progress")
    screen = FakeTerminal()
    with ProgressBar("feed", "transitions", stream=screen) as bar:
        bar.update(0.42, "file 3/12 | 1200 transitions: 1100 new, 100 duplicate, 0 rejected", count=1200,
                   force=True)
        reading = bar.last
    assert reading is not None and reading.fields == ("file 3/12", "1200 transitions: 1100 new, 100 duplicate, "
                                                      "0 rejected")
    drawn = [d for d in screen.getvalue().split("\r\033[K") if d]
    assert drawn[0].startswith("feed  42%|") and "transitions/s, ETA" in drawn[0] and len(drawn[0]) <= 79
    assert screen.getvalue().endswith("\r\033[K")  # the line is gone when the work is
    assert not caplog.records  # on a terminal the plain line stays off the console handlers (caplog's is one)
